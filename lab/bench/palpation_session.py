"""One palpation session simulated in-process, fast: world -> station pipeline -> recording.

For benchmarks that need hundreds of sessions (:mod:`lab.bench.palpation_ood`). The remote
station's own pieces run unchanged: the simulated arm (1 kHz dynamics, force noise and bias)
on the simulated world (registration error, non-linear tissue), the simulated sensor
(photometric rendering with camera noise and LED drift), the station's
:class:`~remote_site.agent.pipeline.FramePipeline` (reconstruction with the shipped
simulator calibration, background tracking, tactile frame assembly). What is left out is the
network (relay, link emulation, the local station's display loop) and real time: the arm is
stepped in simulated time (``realtime=False``) and frames are taken every ``1 / frame_rate``
simulated seconds, so a 20 s session takes a few seconds. The operator's platform path goes
through the same workspace map the stations use. The accepted frames become a
:class:`~local_site.recording.Recording`, exactly what the local station's analysis reads.

Not modelled here (the full ``teletouch bench palpation`` covers them): link delay and loss,
frames dropped by the local station, the stiffness stage's per-frame layers (the analysis
does not read them).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from local_site.recording import Recording
from remote_site.agent.background import BackgroundTracker
from remote_site.agent.pipeline import FramePipeline
from remote_site.agent.stiffness_stage import StiffnessStage
from remote_site.agent.world import SimWorld
from remote_site.arm.base import ArmLimits
from remote_site.arm.sim import SimArm, SimArmConfig
from remote_site.phantom.reference_presses import sim_stiffness_calibration
from remote_site.reconstruction.reconstructor import Reconstructor
from remote_site.registration import RegistrationEstimate, calibrate_with_fiducials, guarded
from remote_site.sensor.sim_calibration import simulated_calibration
from remote_site.sensor.simulator import SimulatedSensor
from remote_site.stiffness.estimator import StiffnessConfig
from remote_site.tactile import TactileAssembler
from shared.errors import ConfigError
from shared.protocol.messages import TactileFrame
from shared.workspace import WorkspaceMap

__all__ = ["Operator", "operator_path", "simulate_registration", "simulate_session"]


@dataclass(frozen=True)
class Operator:
    """A scripted operator in PLATFORM coordinates (mm).

    Attributes:
        kind: ``raster`` (boustrophedon lines along x) or ``free`` (straight strokes between
            random points, like a clinician palpating by feel).
        region: (x0, x1, y0, y1) of the area moved over.
        spacing_mm: raster line spacing.
        speed_mm_s: sliding speed.
        press_z_mm: platform z while pressing (10 = 3 mm into the phantom with the default
            workspace map).
        duration_s: length of a ``free`` session (a raster lasts as long as its lines).
        seed: the free operator's random strokes.
    """

    kind: str = "raster"
    region: tuple[float, float, float, float] = (1.0, 59.0, 1.0, 59.0)
    spacing_mm: float = 4.0
    speed_mm_s: float = 45.0
    press_z_mm: float = 10.0
    duration_s: float = 22.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind not in ("raster", "free"):
            raise ConfigError(f"operator kind must be raster or free, got {self.kind!r}")
        x0, x1, y0, y1 = self.region
        if not (x1 > x0 and y1 > y0):
            raise ConfigError(f"operator region must have x1 > x0 and y1 > y0: {self.region}")


def _polyline(points: list[tuple[float, float]], speed: float, dt: float
              ) -> NDArray[np.float64]:
    out = [np.asarray(points[0], float)]
    carry = 0.0
    for a, b in itertools.pairwise(points):
        pa, pb = np.asarray(a, float), np.asarray(b, float)
        length = float(np.linalg.norm(pb - pa))
        step = speed * dt
        s = step - carry
        while s <= length:
            out.append(pa + (pb - pa) * (s / length))
            s += step
        carry = length - (s - step)
    return np.asarray(out)


def operator_path(op: Operator, dt_s: float) -> NDArray[np.float64]:
    """Platform positions (N, 3) every ``dt_s``: lower onto the start, palpate, lift."""
    x0, x1, y0, y1 = op.region
    if op.kind == "raster":
        ys = np.arange(y0, y1 + 1e-9, op.spacing_mm)
        pts: list[tuple[float, float]] = []
        for i, y in enumerate(ys):
            a, b = (x0, x1) if i % 2 == 0 else (x1, x0)
            pts += [(a, float(y)), (b, float(y))]
    else:
        rng = np.random.default_rng([op.seed, 0xF4EE])
        pts = [(float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1)))]
        length = 0.0
        while length < op.speed_mm_s * op.duration_s:
            nxt = (float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1)))
            length += math.dist(pts[-1], nxt)
            pts.append(nxt)
    xy = _polyline(pts, op.speed_mm_s, dt_s)
    if op.kind == "free":
        xy = xy[: max(1, int(op.duration_s / dt_s))]
    lift = 45.0
    n_down = max(2, int(0.4 / dt_s))
    down = np.column_stack([np.repeat(xy[:1], n_down, 0),
                            np.linspace(lift, op.press_z_mm, n_down)])
    pressed = np.column_stack([xy, np.full(len(xy), op.press_z_mm)])
    up = np.column_stack([np.repeat(xy[-1:], n_down, 0),
                          np.linspace(op.press_z_mm, lift, n_down)])
    hover = np.column_stack([np.repeat(xy[:1], n_down, 0), np.full(n_down, lift)])
    return np.vstack([hover, down, pressed, up])


def _recording(frames: list[TactileFrame], platform: NDArray[np.float64], dt_s: float,
               meta: dict[str, Any]) -> Recording:
    heights = np.stack([f.layers["height_mm"] for f in frames]).astype(np.float32)
    t_us = (np.arange(len(platform)) * dt_s * 1e6).astype(np.int64)
    return Recording(
        platform_t_us=t_us, platform_mm=np.asarray(platform, float),
        frame_center_mm=np.array([f.center_mm for f in frames], float).reshape(-1, 2),
        frame_pitch_mm=np.array([f.pitch_mm for f in frames], float),
        frame_contact=np.array([f.contact for f in frames], bool),
        frame_force_n=np.array([f.force_n for f in frames], float),
        frame_indentation_mm=np.array([f.indentation_mm for f in frames], float),
        frame_height_mm=heights,
        frame_rx_us=np.array([f.ts_us for f in frames], np.int64),
        frame_seq=np.array([f.seq for f in frames], np.int64),
        meta=meta)


def simulate_session(world: SimWorld, operator: Operator, *,
                     workspace: WorkspaceMap | None = None,
                     frame_rate_hz: float = 30.0) -> Recording:
    """Run one palpation session of ``operator`` on ``world``; return what was recorded.

    Args:
        world: the simulated world (phantom, realism, the session's registration error).
        operator: the scripted operator (platform coordinates).
        workspace: the platform <-> phantom map the stations use (default map).
        frame_rate_hz: tactile frames per simulated second.

    Raises:
        ConfigError: bad settings.
    """
    ws = workspace or WorkspaceMap()
    if not (math.isfinite(frame_rate_hz) and frame_rate_hz > 0):
        raise ConfigError("frame_rate_hz must be > 0")
    dt = 1.0 / frame_rate_hz
    options = world.arm_options()
    # 250 Hz instead of the live 1 kHz: the same dynamics (time constant 25 ms), 4x cheaper
    arm = SimArm(config=SimArmConfig(realtime=False, loop_hz=250.0, seed=world.seed),
                 limits=ArmLimits(), **options)
    holder: list[SimulatedSensor] = []
    sensor = SimulatedSensor(**world.sensor_options(arm, lambda: holder[0]))
    holder.append(sensor)
    world.prepare_sensor(sensor)
    sensor.render(np.zeros(sensor.shape_hw, np.float32))  # compile the renderer first
    reconstructor = Reconstructor(simulated_calibration())
    stiffness_cal = sim_stiffness_calibration()
    assembler = TactileAssembler(ws, stiffness_to_k=stiffness_cal.stiffness_to_k())
    stiffness = StiffnessStage(StiffnessConfig().with_calibration(stiffness_cal))
    arm.connect()
    sensor.connect()
    try:
        background = BackgroundTracker(reconstructor)
        background.capture(sensor, arm.state().force_n)
        pipeline = FramePipeline(sensor, reconstructor, assembler, stiffness, arm.state,
                                 background=background)
        platform = operator_path(operator, dt)
        frames: list[TactileFrame] = []
        for seq, p in enumerate(platform):
            arm.move_to(tuple(float(v) for v in ws.forward(p)))
            arm.advance(dt)
            outcome = pipeline.process(seq, None)
            if outcome.frame is not None:
                frames.append(outcome.frame)
    finally:
        sensor.disconnect()
        arm.disconnect()
    meta = {"workspace": {k: list(v) if isinstance(v, tuple) else v
                          for k, v in ws.config.__dict__.items()},
            "simulated_session": {"operator": operator.__dict__,
                                  "frame_rate_hz": frame_rate_hz,
                                  "rejected": dict(pipeline.rejected)}}
    return _recording(frames, platform, dt, meta)


def simulate_registration(world: SimWorld) -> RegistrationEstimate:
    """The station's fiducial registration (:mod:`remote_site.registration`) on ``world``.

    The same procedure the remote station runs at start-up, with the simulated arm stepped
    in simulated time.

    Raises:
        CalibrationError: too few fiducials found (see
            :func:`remote_site.registration.calibrate_with_fiducials`).
    """
    arm = SimArm(config=SimArmConfig(realtime=False, loop_hz=250.0, seed=world.seed),
                 limits=ArmLimits(), **world.arm_options())
    holder: list[SimulatedSensor] = []
    sensor = SimulatedSensor(**world.sensor_options(arm, lambda: holder[0]))
    holder.append(sensor)
    world.prepare_sensor(sensor)
    arm.connect()
    sensor.connect()
    try:
        return calibrate_with_fiducials(guarded(arm), sensor,
                                        Reconstructor(simulated_calibration()),
                                        [f.center_mm for f in world.phantom.fiducials],
                                        wait=arm.advance)
    finally:
        sensor.disconnect()
        arm.disconnect()
