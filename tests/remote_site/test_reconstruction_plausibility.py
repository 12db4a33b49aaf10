"""Frames that are no tactile image are refused by name, never reconstructed into bumps.

Found by an audit (defect 1): a solid grey frame (a USB camera resyncing), swapped colour
channels, pure noise or a frame 23.75 % saturated (just under the saturation gate) passed the
frame checks and reconstructed into 4-16 mm bumps over ~80 % of the pad, with the real
GelSight Mini calibration and the simulated one; the tactile frame carried them to the display.
The real presses (at most 0.84 mm) and the simulated palpation at the arm's force limit must
all still reconstruct.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from remote_site.agent.pipeline import FramePipeline
from remote_site.agent.stiffness_stage import StiffnessStage
from remote_site.agent.world import build_world
from remote_site.arm.base import ArmReading
from remote_site.phantom.phantom import PixelGrid
from remote_site.reconstruction.calibration import Calibration, fit_calibration
from remote_site.reconstruction.frames import load_rgb
from remote_site.reconstruction.label_check import screen_presses
from remote_site.reconstruction.labels import labels_from_npz
from remote_site.reconstruction.reconstructor import ReconstructionSettings, Reconstructor
from remote_site.sensor.base import SensorFrame
from remote_site.sensor.shapes import ball_depth_mm
from remote_site.sensor.sim_calibration import simulated_calibration
from remote_site.sensor.simulator import SimulatedSensor
from remote_site.stiffness.estimator import StiffnessConfig
from remote_site.tactile import TactileAssembler
from shared.errors import ConfigError, InputDataError
from shared.timebase import now_us
from tests.remote_site.test_agent_safety import STIFFNESS_CALIB, WS
from tests.support import kit_path, require_kit

DATA = kit_path("data", "gelsight", "gsmini_ball_9.47mm")
EXAMPLES = kit_path("data", "gelsight", "gsmini_examples")
PITCHES = (None, 0.507)  # full resolution and the station's grid


@pytest.fixture(scope="module")
def real_calibration() -> Calibration:
    """Fitted on the kit's train presses (as ``teletouch sensor calibrate`` does)."""
    data = require_kit(DATA)
    entries = json.loads((data / "train_test_split.json").read_text())["train"]
    names = [f"press_{int(e.rsplit('/', 1)[1]):02d}.png" for e in entries]
    background = load_rgb(data / "background.png")
    presses = [(load_rgb(data / lb.image), lb) for lb in labels_from_npz(data, names)]
    kept, _ = screen_presses(background, presses)
    return fit_calibration(background, kept, 9.47, 0.0634)


@pytest.fixture(scope="module", params=["real", "sim"])
def calibration(request: pytest.FixtureRequest) -> Calibration:
    if request.param == "real":
        return request.getfixturevalue("real_calibration")
    return simulated_calibration()


def _not_images(calibration: Calibration) -> dict[str, np.ndarray]:
    """The audit's frames, built on this calibration's background (and a real press)."""
    bg = calibration.background_rgb.astype(np.uint8)
    press = load_rgb(require_kit(DATA) / "press_00.png")
    saturated = bg.copy()
    saturated[:, :76] = 255  # 23.75 % of the columns: just under the 25 % gate
    return {"solid grey": np.full_like(bg, 128),
            "noisy grey": np.clip(128 + np.random.default_rng(1).normal(0, 2.1, bg.shape),
                                  0, 255).astype(np.uint8),
            "R/B swapped": press[..., ::-1].copy(),
            "noise": np.random.default_rng(0).integers(0, 256, bg.shape, dtype=np.uint8),
            "23.75 % saturated": saturated}


@pytest.mark.parametrize("kind", ["solid grey", "noisy grey", "R/B swapped", "noise",
                                  "23.75 % saturated"])
def test_frames_that_are_no_tactile_image_are_refused_by_name(calibration: Calibration,
                                                             kind: str) -> None:
    rec = Reconstructor(calibration)
    frame = _not_images(calibration)[kind]
    for pitch in PITCHES:
        with pytest.raises(InputDataError, match=r"uniform|noise|max_height_mm"):
            hm = rec.height_map(frame, out_pitch_mm=pitch)
            pytest.fail(f"{kind} at pitch {pitch}: reconstructed to {hm.height_mm.min():.2f}"
                        f"..{hm.height_mm.max():.2f} mm over {hm.mask.mean():.0%}")


def test_every_real_press_still_reconstructs(real_calibration: Calibration) -> None:
    """All 51 ball presses (train and test) and the other Mini's bead, key and seed (against
    their own background); none is refused, the presses' peaks stay under 1 mm."""
    rec = Reconstructor(real_calibration)
    data, examples = require_kit(DATA), require_kit(EXAMPLES)
    for pitch in PITCHES:
        peaks = [rec.height_map(load_rgb(p), out_pitch_mm=pitch).max_height_mm
                 for p in sorted(data.glob("press_??.png"))]
        assert len(peaks) == 51 and min(peaks) > 0.3 and max(peaks) < 1.0
        other_bg = load_rgb(examples / "background.png")
        for name in ("bead", "key", "seed"):
            hm = rec.height_map(load_rgb(examples / f"{name}.png"), background=other_bg,
                                out_pitch_mm=pitch)
            assert hm.contact and np.abs(hm.height_mm).max() < 3.0, name


def test_simulated_palpation_at_the_force_limit_is_not_refused() -> None:
    """The demo's own frames: the pad on a tumor at the arm's 10 N force limit (the deepest
    the simulator renders: its linear gel model goes 4.3 mm deep, reconstructed 2.5 mm)."""
    rec = Reconstructor(simulated_calibration())
    grid = PixelGrid(width_px=320, height_px=240, mm_per_px=0.0634)
    for scene, seed in (("breast", 2), ("severity", 1), ("localization", 0)):
        world = build_world(scene, seed)
        sensor = SimulatedSensor(settings=world.sensor_settings(), seed=seed)
        phantom = world.phantom
        for x, y in [t.center_mm for t in phantom.tumors]:
            lo, hi = 0.0, 30.0  # the depth of a 10 N press, by bisection
            for _ in range(40):
                mid = (lo + hi) / 2
                lo, hi = (lo, mid) if phantom.force_n((x, y, -mid)) > 10.0 else (mid, hi)
            frame = sensor.render(phantom.contact((x, y, -lo), grid).depth_map_mm)
            for pitch in (*PITCHES, 1.7):
                hm = rec.height_map(frame, out_pitch_mm=pitch)
                assert hm.contact and 0.1 < hm.max_height_mm < 3.0


def test_max_height_is_a_setting() -> None:
    assert ReconstructionSettings().max_height_mm == 4.0  # documented: docs/reconstruction.md
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ConfigError, match="max_height_mm"):
            ReconstructionSettings(max_height_mm=bad)
    sensor = SimulatedSensor()
    s = sensor.shape_hw
    press = sensor.render(ball_depth_mm(s, sensor.mm_per_px, s[1] / 2, s[0] / 2, 3.0, 0.5))
    peak = Reconstructor(simulated_calibration()).height_map(press).max_height_mm
    assert 0.4 < peak < 0.6
    strict = Reconstructor(simulated_calibration(), ReconstructionSettings(max_height_mm=0.3))
    with pytest.raises(InputDataError, match=r"max_height_mm 0\.3"):
        strict.height_map(press)


class _ScriptedSensor:
    def __init__(self, frames: list[np.ndarray]) -> None:
        self.frames = frames
        self.seq = 0

    def read_latest(self, max_age_ms: float) -> SensorFrame:
        self.seq += 1
        return SensorFrame(rgb=self.frames.pop(0), timestamp_us=now_us(), seq=self.seq)


def test_the_station_counts_a_refused_frame_and_goes_on() -> None:
    calibration = simulated_calibration()
    sensor = SimulatedSensor()
    s = sensor.shape_hw
    press = sensor.render(ball_depth_mm(s, sensor.mm_per_px, s[1] / 2, s[0] / 2, 3.0, 0.4))
    frames = [*_not_images(calibration).values(), press]
    reading = ArmReading((0.0, 0.0, -0.5), (0.0, 0.0, 0.0), 0.5, "ok", None, 0.0)
    pipeline = FramePipeline(
        _ScriptedSensor(frames), Reconstructor(calibration),  # type: ignore[arg-type]
        TactileAssembler(WS, stiffness_to_k=STIFFNESS_CALIB.stiffness_to_k()),
        StiffnessStage(StiffnessConfig().with_calibration(STIFFNESS_CALIB)), lambda: reading)
    outcomes = [pipeline.process(i + 1, None) for i in range(len(frames))]
    refused = outcomes[:-1]
    assert all(o.status == "rejected" and o.reason == "bad_frame" and o.frame is None
               for o in refused)
    assert pipeline.rejected == {"bad_frame": len(refused)}
    last = outcomes[-1]
    assert last.status == "ok" and last.frame is not None and pipeline.processed == 1
    assert last.frame.contact and 0.2 < float(np.max(last.frame.layers["height_mm"])) < 0.5
