"""The station's own no-contact background: swap, start capture, refresh when idle, drift."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.agent.background import BackgroundSettings, BackgroundTracker, channel_drift
from remote_site.reconstruction.reconstructor import Reconstructor
from remote_site.sensor.photometric import PhotometricSettings
from remote_site.sensor.shapes import ball_depth_mm
from remote_site.sensor.sim_calibration import simulated_calibration
from remote_site.sensor.simulator import SimulatedSensor
from shared.errors import ConfigError, DeviceTimeoutError, InputDataError

#: the illumination drifted since calibration day: the left-right gradient doubled (one side's
#: LED dimmer) and the channels' gains moved by a few percent. A uniform gain alone is
#: compensated by the reconstruction's per-frame brightness normalisation; the spatial part
#: is what a stale background turns into false slopes.
DRIFT = PhotometricSettings(illumination_tilt=0.16, brightness=(1.03, 0.97, 1.02))


@pytest.fixture(scope="module")
def calibration() -> Any:
    return simulated_calibration()


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


# --------------------------------------------------------------------------- swap


def test_set_background_is_validated(calibration: Any) -> None:
    rec = Reconstructor(calibration)
    good = calibration.background_rgb.astype(np.float32)
    for bad in (good[:-1], good.astype(np.int32), np.where(good > 100, np.nan, good),
                np.zeros_like(good)):
        with pytest.raises(InputDataError):
            rec.set_background(bad)
    assert np.array_equal(rec.background_rgb, good)  # a refused swap changes nothing
    rec.set_background(good * 0.9)
    assert np.allclose(rec.background_rgb, good * 0.9)


def test_swapped_background_is_used_at_every_pitch(calibration: Any) -> None:
    sensor = SimulatedSensor(settings=PhotometricSettings(illumination_tilt=0.16, noise_dn=0.0))
    frame = sensor.render(np.zeros(sensor.shape_hw, np.float32))
    rec = Reconstructor(calibration)
    for pitch in (None, 0.5):  # prime the pooled-background cache with the old background
        rec.height_map(frame, out_pitch_mm=pitch)
    rec.set_background(frame)
    for pitch in (None, 0.5):
        assert np.abs(rec.height_map(frame, out_pitch_mm=pitch).height_mm).max() == 0.0


@settings(max_examples=30, deadline=None)
@given(shift=st.lists(st.floats(-40, 40), min_size=3, max_size=3))
def test_channel_drift_is_the_mean_absolute_difference(shift: list[float]) -> None:
    ref = np.full((12, 16, 3), 100.0, np.float32)
    ref[::2] = 120.0
    moved = ref + np.asarray(shift, np.float32)
    assert channel_drift(moved, ref) == pytest.approx([abs(v) for v in shift], abs=1e-4)
    with pytest.raises(InputDataError):
        channel_drift(moved[:, :3], ref)


# --------------------------------------------------------------------------- start capture


def _flat_errors(rec: Reconstructor, sensor: SimulatedSensor, n: int = 5) -> float:
    """p99 |height| (mm) over ``n`` flat-gel frames, at full resolution."""
    sensor.set_depth(np.zeros(sensor.shape_hw, np.float32))
    heights = [rec.height_map(sensor.read_latest(1000).rgb).height_mm for _ in range(n)]
    return float(np.percentile(np.abs(np.stack(heights)), 99))


def test_station_background_cuts_the_flat_gel_error_under_led_drift(calibration: Any) -> None:
    with SimulatedSensor(settings=DRIFT, seed=3) as sensor:
        drifted_bg = sensor.background_rgb * np.asarray(DRIFT.brightness)
        stale = Reconstructor(calibration)
        fresh = Reconstructor(calibration)
        tracker = BackgroundTracker(fresh)
        assert tracker.capture(sensor, force_n=0.0)
        flat_stale, flat_fresh = _flat_errors(stale, sensor), _flat_errors(fresh, sensor)
        # a ball press, 0.4 mm deep: peak height error with either background
        s = sensor.shape_hw
        depth = ball_depth_mm(s, sensor.mm_per_px, s[1] / 2, s[0] / 2, 3.0, 0.4)
        sensor.set_depth(depth)
        press = sensor.read_latest(1000).rgb
        peak_stale = stale.height_map(press).max_height_mm
        peak_fresh = fresh.height_map(press).max_height_mm
    summary = tracker.summary()
    assert summary["source"] == "station" and summary["captures"] == 1
    # the drift is measured in grey levels (5 frames averaged: the camera noise adds < 0.5)
    expected = channel_drift(drifted_bg, calibration.background_rgb)
    assert summary["drift_from_calibration_rgb"] == pytest.approx(expected, abs=0.6)
    assert min(expected) > 1.5
    assert flat_stale > 0.015  # the stale background reads the gradient change as slopes
    assert flat_fresh < 0.01
    assert flat_fresh < 0.5 * flat_stale, (flat_fresh, flat_stale)
    assert abs(peak_fresh - 0.4) < abs(peak_stale - 0.4) or abs(peak_fresh - 0.4) < 0.03


def test_capture_is_refused_with_the_pad_loaded_and_reported_once(
        calibration: Any, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="remote_site.agent.background")
    rec = Reconstructor(calibration)
    tracker = BackgroundTracker(rec)
    with SimulatedSensor() as sensor:
        assert not tracker.capture(sensor, force_n=1.0)
        assert not tracker.capture(sensor, force_n=1.0)
    assert tracker.summary()["source"] == "calibration"
    assert tracker.capture_failures == 2
    assert len([r for r in caplog.records if "background capture failed" in r.getMessage()]) == 1
    assert np.array_equal(rec.background_rgb, calibration.background_rgb.astype(np.float32))


def test_capture_without_frames_falls_back_to_the_calibration(calibration: Any) -> None:
    class Silent(SimulatedSensor):
        def read_latest(self, max_age_ms: float = 100.0) -> Any:
            raise DeviceTimeoutError("no frame")

    tracker = BackgroundTracker(Reconstructor(calibration),
                                BackgroundSettings(capture_timeout_s=0.05))
    with Silent() as sensor:
        assert not tracker.capture(sensor, force_n=0.0)
    assert tracker.source == "calibration"


def test_bad_settings_are_config_errors() -> None:
    with pytest.raises(ConfigError):
        BackgroundSettings(frames=0)
    with pytest.raises(ConfigError):
        BackgroundSettings(quiet_s=float("nan"))


# --------------------------------------------------------------------------- refresh


def test_refresh_only_after_a_quiet_stretch(calibration: Any) -> None:
    clock = FakeClock()
    rec = Reconstructor(calibration)
    tracker = BackgroundTracker(rec, BackgroundSettings(frames=3, quiet_s=1.0), clock=clock)
    lifted = calibration.background_rgb.astype(np.float32) * 0.97

    def feed(n: int, force_n: float = 0.0, contact: bool = False) -> list[bool]:
        out = []
        for _ in range(n):
            out.append(tracker.offer(lifted, force_n, contact))
            clock.t += 0.125  # exact in binary: no rounding at the 1 s boundary
        return out

    assert not any(feed(8))  # 0.875 s quiet: not yet
    assert not any(feed(1, contact=True))  # a contact restarts the stretch
    # so does a press: one reading at or above max_force_n + 3 x force_noise_n (0.35 N; a
    # 0.2 N reading is 2 sigma of the arm's force noise, judged by the stretch's median)
    assert not any(feed(5, force_n=1.0))
    refreshed = feed(12)
    assert refreshed.count(True) == 1 and tracker.source == "station"
    assert np.allclose(rec.background_rgb, lifted)
    assert tracker.summary()["since_last_capture_s"] == pytest.approx(0.5)
    assert tracker.summary()["drift_from_calibration_mean"] > 1.0
    assert feed(10).count(True) == 1  # refreshed again after another quiet_s
