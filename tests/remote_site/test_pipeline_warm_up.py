"""The remote station's frame pipeline: its reconstruction warm-up before a session."""

from __future__ import annotations

from remote_site.agent.pipeline import FramePipeline
from remote_site.agent.stiffness_stage import StiffnessStage
from remote_site.arm.base import ArmReading
from remote_site.sensor.base import SensorFrame
from remote_site.stiffness.estimator import StiffnessConfig
from remote_site.tactile import TactileAssembler
from shared.timebase import now_us
from tests.remote_site.test_agent_safety import CALIB, STIFFNESS_CALIB, WS

SPEED_MM_PER_S = 45.0


class MovingArm:
    """The pad slides along +x at a constant speed; readings carry the true position."""

    def __init__(self) -> None:
        self.t0_us = now_us()

    def x_at(self, t_us: int) -> float:
        return SPEED_MM_PER_S * (t_us - self.t0_us) / 1e6

    def state(self) -> ArmReading:
        x = self.x_at(now_us())
        return ArmReading((x, 0.0, 1.0), (SPEED_MM_PER_S, 0.0, 0.0), 0.5, "moving", None, 0.0)


class LateSensor:
    """A sensor whose frame was captured ``delay_us`` after it is asked for, as happens
    when the capture thread runs later than the arm read (the stamp says when)."""

    def __init__(self, arm: MovingArm, delay_us: int) -> None:
        self.arm = arm
        self.delay_us = delay_us
        self.captured_us: int | None = None
        self.rgb = CALIB.background_rgb.copy()  # no contact: the placement is the point

    def read_latest(self, max_age_ms: float) -> SensorFrame:
        t = now_us()
        while now_us() < t + self.delay_us:  # the capture happens later (a busy wait: the
            pass                              # arm keeps moving meanwhile)
        self.captured_us = now_us()
        return SensorFrame(rgb=self.rgb, timestamp_us=self.captured_us, seq=1)


def test_the_warm_up_runs_the_whole_reconstruction_before_the_session() -> None:
    """A synthetic press goes through evidence, model, Poisson and zero level at both
    resolutions, so no kernel loads in the first frames of a session (the fault suite
    measures what that stall did to the arm's watchdog)."""
    from remote_site.reconstruction.reconstructor import Reconstructor

    arm = MovingArm()
    assembler = TactileAssembler(WS, stiffness_to_k=STIFFNESS_CALIB.stiffness_to_k())
    stiffness = StiffnessStage(StiffnessConfig().with_calibration(STIFFNESS_CALIB))
    pipeline = FramePipeline(LateSensor(arm, 0), Reconstructor(CALIB),  # type: ignore[arg-type]
                             assembler, stiffness, arm.state)
    calls: list[tuple[object, bool]] = []
    orig = pipeline.reconstructor.height_map

    def spy(rgb: object, out_pitch_mm: float | None = None) -> object:
        hm = orig(rgb, out_pitch_mm=out_pitch_mm)  # type: ignore[arg-type]
        calls.append((out_pitch_mm, hm.contact and not hm.skipped))
        return hm

    pipeline.reconstructor.height_map = spy  # type: ignore[method-assign,assignment]
    assert pipeline.warm_up() > 0.0
    assert calls == [(pipeline.phantom_pitch_mm, True), (None, True)]
    assert pipeline.process(1, None).frame is not None
