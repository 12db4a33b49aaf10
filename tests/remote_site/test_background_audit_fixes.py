"""The station background after an audit (defects 2 and 3).

2. A background captured while the pad pressed (the arm's one force reading said ~0) was
   accepted; the press then read flat, every lifted frame read as contact against it, and it
   was never replaced (0 refreshes in 60 s). Now a background in use that shows contact
   against the calibration's and makes the lifted gel read as contact is replaced once the
   pad is lifted. (A first fix refused such a start capture: a review found that a gel whose
   lighting changed since calibration day then read as contact all session.)
3. With the project's own force noise (0.1 N rms per reading, ``remote_site/agent/world.py``)
   every reading of the 2 s quiet stretch had to be below 0.05 N: never refreshed, and the
   start capture (one reading) refused in ~37 % of sessions. Now the median force of the
   stretch is judged, and one reading refuses only when it is a press (3 sigma above).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from remote_site.agent.background import BackgroundSettings, BackgroundTracker
from remote_site.reconstruction.calibration import Calibration
from remote_site.reconstruction.frames import load_rgb
from remote_site.reconstruction.reconstructor import Reconstructor
from remote_site.sensor.base import SensorFrame, TactileSensor
from remote_site.sensor.photometric import PhotometricSettings
from remote_site.sensor.shapes import ball_depth_mm
from remote_site.sensor.sim_calibration import simulated_calibration
from remote_site.sensor.simulator import SimulatedSensor
from shared.errors import ConfigError
from shared.timebase import now_us
from tests.remote_site.test_reconstruction_plausibility import DATA, real_calibration
from tests.support import require_kit

__all__ = ["real_calibration"]  # the module fixture, shared

FPS = 60.0
PITCH_MM = 0.507  # the station's grid


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class StillSensor(TactileSensor):
    """Delivers the same image as a new frame on every read."""

    captures_on_demand = True

    def __init__(self, rgb: np.ndarray, mm_per_px: float) -> None:
        super().__init__(rgb.shape[:2], mm_per_px)
        self.rgb = rgb
        self.seq = 0

    def _connect(self) -> None:
        pass

    def _disconnect(self) -> None:
        pass

    def _latest(self) -> SensorFrame:
        self.seq += 1
        return SensorFrame(self.rgb.copy(), now_us(), self.seq)


def _sim_frames(depth_mm: float, n: int = 12) -> list[np.ndarray]:
    """``n`` simulated frames (camera noise 2.1 grey levels) of a 6 mm ball pressed
    ``depth_mm`` deep (0: the pad lifted)."""
    sensor = SimulatedSensor(settings=replace(PhotometricSettings(), noise_dn=2.1), seed=1)
    shape = sensor.shape_hw
    depth = (ball_depth_mm(shape, sensor.mm_per_px, shape[1] / 2, shape[0] / 2, 3.0, depth_mm)
             if depth_mm > 0 else np.zeros(shape, np.float32))
    return [sensor.render(depth) for _ in range(n)]


@pytest.fixture(params=["real", "sim"])
def setup(request: pytest.FixtureRequest) -> tuple[Calibration, list[np.ndarray],
                                                    list[np.ndarray]]:
    """(calibration, press frames, lifted frames): the kit's GelSight Mini or the simulator."""
    if request.param == "real":
        data = require_kit(DATA)
        calibration = request.getfixturevalue("real_calibration")
        return (calibration, [load_rgb(data / "press_00.png")],
                [load_rgb(data / "background.png")])
    return simulated_calibration(), _sim_frames(0.4), _sim_frames(0.0)


def _feed(tracker: BackgroundTracker, clock: Clock, frames: list[np.ndarray],
          forces: Iterator[float] | Callable[[], float], seconds: float) -> int:
    """Offer ``seconds`` of frames at 60 frames/s, as the pipeline does (contact judged
    against the background in use, at the station's grid); the number of refreshes."""
    rec = tracker.reconstructor
    refreshes = 0
    for i in range(round(seconds * FPS)):
        frame = frames[i % len(frames)]
        contact = rec.height_map(frame, out_pitch_mm=PITCH_MM).contact
        force = forces() if callable(forces) else next(forces)
        refreshes += tracker.offer(frame, force, contact)
        clock.t += 1.0 / FPS
    return refreshes


# --------------------------------------------------------------------------- defect 2


def test_a_start_capture_during_a_press_is_replaced_once_lifted(setup: Any) -> None:
    calibration, press, lifted = setup
    clock = Clock()
    rec = Reconstructor(calibration)
    tracker = BackgroundTracker(rec, clock=clock)
    with StillSensor(press[0], calibration.mm_per_px) as sensor:
        assert tracker.capture(sensor, force_n=0.01)  # the force reading says "lifted"
    assert rec.height_map(lifted[0], out_pitch_mm=PITCH_MM).contact  # the lifted gel: contact
    clock.t += 1.0
    assert _feed(tracker, clock, lifted, lambda: 0.0, seconds=5.0) >= 1
    assert not rec.height_map(lifted[0], out_pitch_mm=PITCH_MM).contact
    assert rec.height_map(press[0], out_pitch_mm=PITCH_MM).contact  # the press shows again


def test_a_gel_whose_lighting_changed_since_calibration_keeps_its_own_background() -> None:
    """LEDs 10 % brighter on one side and dimmer on the other since calibration day: the
    lifted gel reads as contact against the calibration's background. Its start capture must
    be taken and kept (found by review: refused, every frame of the session read as
    contact, no refresh ever)."""
    calibration = simulated_calibration()
    lifted = _sim_frames(0.0)
    h, w = lifted[0].shape[:2]
    x = np.mgrid[0:h, 0:w][1] / w - 0.5
    gain = np.stack([1 + 0.2 * x, np.ones_like(x), 1 - 0.2 * x], -1)
    drifted = [np.clip(f * gain, 0, 255).astype(np.uint8) for f in lifted]
    clock = Clock()
    rec = Reconstructor(calibration)
    assert rec.height_map(drifted[0], out_pitch_mm=PITCH_MM).contact  # against calibration's
    tracker = BackgroundTracker(rec, clock=clock)
    with StillSensor(drifted[0], calibration.mm_per_px) as sensor:
        assert tracker.capture(sensor, force_n=0.0)
    clock.t += 1.0
    assert _feed(tracker, clock, drifted, lambda: 0.0, seconds=10.0) >= 1
    assert not any(rec.height_map(f, out_pitch_mm=PITCH_MM).contact for f in drifted)


def test_a_background_taken_during_a_press_is_replaced_once_lifted(setup: Any) -> None:
    calibration, press, lifted = setup
    clock = Clock()
    rec = Reconstructor(calibration)
    tracker = BackgroundTracker(rec, clock=clock)
    assert tracker._use(np.mean(np.stack(press).astype(np.float32), axis=0), clock())  # the
    # old start capture's way in; now the lifted gel reads as contact against it
    assert rec.height_map(lifted[0], out_pitch_mm=PITCH_MM).contact
    clock.t += 1.0
    assert _feed(tracker, clock, lifted, lambda: 0.0, seconds=5.0) >= 1
    assert not rec.height_map(lifted[0], out_pitch_mm=PITCH_MM).contact
    assert rec.height_map(press[0], out_pitch_mm=PITCH_MM).contact


def test_a_real_contact_is_not_taken_for_a_bad_background(setup: Any) -> None:
    """A press at a force the arm does not feel, against a good station background: the
    calibration's background shows it too, so nothing is replaced."""
    calibration, press, lifted = setup
    clock = Clock()
    rec = Reconstructor(calibration)
    tracker = BackgroundTracker(rec, clock=clock)
    with StillSensor(lifted[0], calibration.mm_per_px) as sensor:
        assert tracker.capture(sensor, force_n=0.0)
    good = rec.background_rgb.copy()
    clock.t += 10.0
    assert _feed(tracker, clock, press, lambda: 0.0, seconds=10.0) == 0
    assert np.array_equal(rec.background_rgb, good)


# --------------------------------------------------------------------------- defect 3


@pytest.mark.parametrize("offset_n", [-0.1, 0.0])
def test_force_noise_does_not_block_refreshes(offset_n: float) -> None:
    rng = np.random.default_rng(7)
    clock = Clock()
    tracker = BackgroundTracker(Reconstructor(simulated_calibration()), clock=clock)
    refreshes = _feed(tracker, clock, _sim_frames(0.0), lambda: offset_n + rng.normal(0, 0.1),
                      seconds=60.0)
    assert refreshes >= 10 and tracker.source == "station"


@pytest.mark.parametrize("force_n", [0.3, 1.0])
def test_a_press_blocks_refreshes(force_n: float) -> None:
    """A press well above the noise (0.3 N: under one reading's press threshold, so only the
    median stops it; 1 N: every reading) holds the refresh off, whatever the image shows; the
    refreshes resume once the pad is lifted."""
    rng = np.random.default_rng(3)
    clock = Clock()
    tracker = BackgroundTracker(Reconstructor(simulated_calibration()), clock=clock)
    lifted = _sim_frames(0.0)
    assert _feed(tracker, clock, lifted, lambda: force_n + rng.normal(0, 0.1), 20.0) == 0
    assert tracker.source == "calibration"
    assert _feed(tracker, clock, lifted, lambda: rng.normal(0, 0.1), 5.0) >= 1


def test_a_slow_press_is_not_taken_into_the_background() -> None:
    """The pad lifted, then a press whose force rises slowly (0.2 N/s) while the image
    barely changes yet: the stretch's median lags about 1 s behind, so a refresh came 1 s
    into the press and took in the gel's deformation (found by review). The recent
    readings' median holds it off."""
    clock = Clock()
    tracker = BackgroundTracker(Reconstructor(simulated_calibration()), clock=clock)
    lifted = _sim_frames(0.0)
    assert _feed(tracker, clock, lifted, lambda: 0.0, seconds=3.0) >= 1  # refreshed once
    start = clock.t
    assert _feed(tracker, clock, lifted, lambda: 0.2 * (clock.t - start), seconds=3.0) == 0


def test_the_start_capture_tolerates_force_noise() -> None:
    """One reading refuses the start capture only when it is a press: >= max_force_n +
    3 x force_noise_n (0.35 N by default); noisy readings of a lifted pad pass."""
    calibration = simulated_calibration()
    lifted = _sim_frames(0.0, 1)[0]
    assert BackgroundSettings().press_force_n == pytest.approx(0.35)
    for force_n, accepted in ((0.06, True), (0.2, True), (0.34, True), (0.36, False),
                              (1.0, False), (float("nan"), False)):
        tracker = BackgroundTracker(Reconstructor(calibration), clock=Clock())
        with StillSensor(lifted, calibration.mm_per_px) as sensor:
            assert tracker.capture(sensor, force_n=force_n) is accepted, force_n


def test_force_noise_is_a_checked_setting() -> None:
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="force_noise_n"):
            BackgroundSettings(force_noise_n=bad)
    assert BackgroundSettings(force_noise_n=0.0).press_force_n == pytest.approx(0.05)


def test_a_light_touch_on_a_gel_changed_since_calibration_keeps_a_good_background(
        real_calibration: Calibration) -> None:
    """The gel has a shallow dent since calibration day (it barely shows against the
    calibration's background), the station's background is good, and a light touch lands
    on the dent with the force reading ~0.03 N: the touch must stay visible. A review found
    the recovery judged the touch frame (no contact against the calibration's background,
    because the dent cancels it) and replaced the good background within 4 s, after which
    the touch read flat; only a background that itself shows contact is suspect now."""
    data = require_kit(DATA)
    rng = np.random.default_rng(0)
    bg = load_rgb(data / "background.png").astype(np.float32)
    press = load_rgb(data / "press_07.png").astype(np.float32)
    rest = bg - 0.2 * (press - bg)  # the dent, the mirror of a fifth of the press

    def noisy(img: np.ndarray) -> np.ndarray:
        return np.clip(img + rng.normal(0, 2.1, img.shape), 0, 255).astype(np.uint8)

    clock = Clock()
    rec = Reconstructor(real_calibration)
    tracker = BackgroundTracker(rec, clock=clock)
    with StillSensor(noisy(rest), real_calibration.mm_per_px) as sensor:
        assert tracker.capture(sensor, force_n=0.0)
    good = rec.background_rgb.copy()
    touch = [noisy(rest + min(0.2, 0.2 * i / 12) * (press - bg)) for i in range(24)]
    frames = touch + [touch[-1]] * (6 * int(FPS))  # pressing in, then held 6 s
    shown = []
    for frame in frames:
        contact = rec.height_map(frame, out_pitch_mm=PITCH_MM).contact
        tracker.offer(frame, 0.03 + rng.normal(0, 0.01), contact)
        shown.append(contact)
        clock.t += 1.0 / FPS
    assert np.array_equal(rec.background_rgb, good), "the good background was replaced"
    assert all(shown[24:]), f"the held touch read flat in {shown[24:].count(False)} frames"
