"""Probes of the remote station's devices, for ``teletouch check remote``.

Each probe opens one device through the station's registries (:mod:`remote_site.arm.registry`,
:mod:`remote_site.sensor.registry`), measures what a session relies on and always closes it
again (context manager), within bounded times (:class:`~shared.device_check.CheckSettings`):

* the arm: connects, reads its state (pose, velocity, force, status). It never moves unless
  asked: with ``move=True`` it is lifted ``move_mm`` (+z, away from the tissue) and brought
  back, each motion timed against ``move_timeout_s``; disconnecting halts it;
* the camera: opens, frame rate over ``rate_window_s`` (distinct frames), frame size and
  dtype, and, given a calibration, whether the calibration was made for this frame size and
  pixel pitch (a mismatch would make every height map wrong).

A probe returns a :class:`~shared.device_check.DeviceCheck`; device errors become its one-line
message (:func:`shared.device_check.failure_line`), never an exception.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from remote_site.arm.base import Arm, Vec3
from remote_site.arm.registry import open_arm
from remote_site.sensor.registry import open_sensor
from shared.device_check import CheckReport, CheckSettings, DeviceCheck, failed_check
from shared.errors import ConfigError, DeviceTimeoutError, TeleTouchError
from shared.timebase import monotonic_s

__all__ = ["MIN_FRAME_RATE_HZ", "check_arm", "check_remote", "check_sensor"]

log = logging.getLogger(__name__)

#: tactile frames are sent at up to 60 Hz; below this the camera is unusable
MIN_FRAME_RATE_HZ = 10.0
#: a motion counts as done within this distance of its target
REACHED_MM = 0.1


def _rounded(values: Vec3, digits: int = 3) -> list[float]:
    return [round(float(v), digits) for v in values]


def check_arm(name: str, settings: CheckSettings | None = None, *, move: bool = False,
              **options: Any) -> DeviceCheck:
    """Probe the arm backend ``name``: connect, read its state, and move only if asked.

    Args:
        name: arm backend (``sim``, ``franka``, an entry point or ``module:Class``).
        settings: time bounds and the ``--move`` distance.
        move: lift the pad ``settings.move_mm`` and bring it back.
        **options: backend constructor arguments.

    Returns:
        The result; ``ok`` when the arm connected, reported a state that is not ``fault``,
        and (with ``move``) reached both targets in time.
    """
    cfg = settings or CheckSettings()
    figures: dict[str, Any] = {}
    try:
        arm = open_arm(name, **options)
        with arm:
            reading = arm.state()
            figures.update(position_mm=_rounded(reading.position_mm),
                           velocity_mm_s=_rounded(reading.velocity_mm_s),
                           force_n=round(float(reading.force_n), 3), status=reading.status)
            if reading.status == "fault":
                return DeviceCheck("arm", name, False,
                                   "connected, but the arm reports a fault: clear it on the "
                                   "robot (pilot/desk) and run the check again", figures)
            if move:
                start = reading.position_mm
                up = (start[0], start[1], start[2] + cfg.move_mm)
                figures["move_up_s"] = round(_move_and_wait(arm, up, cfg.move_timeout_s), 3)
                figures["move_back_s"] = round(_move_and_wait(arm, start,
                                                              cfg.move_timeout_s), 3)
                arm.stop()
    except TeleTouchError as err:
        return failed_check("arm", name, err, figures)
    moved = f", moved {cfg.move_mm:g} mm up and back" if move else " (not moved)"
    return DeviceCheck("arm", name, True,
                       f"{figures['status']} at {tuple(figures['position_mm'])} mm, "
                       f"force {figures['force_n']:.2f} N{moved}", figures)


def _move_and_wait(arm: Arm, target_mm: Vec3, timeout_s: float) -> float:
    """Send one target and wait until the pad is there; returns the time it took.

    Raises:
        DeviceTimeoutError: not reached within ``timeout_s`` (the arm is halted first).
    """
    applied = arm.move_to(target_mm)
    start_s = monotonic_s()
    while True:
        position = arm.state().position_mm
        elapsed_s = monotonic_s() - start_s
        if math.dist(position, applied) <= REACHED_MM:
            return elapsed_s
        if elapsed_s > timeout_s:
            arm.stop()
            raise DeviceTimeoutError(f"{arm.name}: did not reach {applied} mm within "
                                     f"{timeout_s:g} s (at {tuple(_rounded(position))} mm)")
        time.sleep(0.005)


def _open_camera_or_source(spec: str, cfg: CheckSettings) -> Any:
    """Build the sensor; camera backends get the connect timeout as first-frame timeout."""
    try:
        return open_sensor(spec, first_frame_timeout_s=cfg.connect_timeout_s)
    except ConfigError:  # a backend without that option (simulator, a lab's own)
        return open_sensor(spec)


def check_sensor(spec: str, settings: CheckSettings | None = None, *,
                 calibration: str | Path | None = None) -> DeviceCheck:
    """Probe the visuotactile sensor ``spec``: opens, frame rate, size, calibration match.

    Args:
        spec: sensor (``sim``, ``camera``, a camera index, URL or video file).
        settings: time bounds.
        calibration: a sensor calibration (``.npz``) to check against the delivered frames.

    Returns:
        The result; ``ok`` when frames arrive at >= 10 Hz as (H, W, 3) uint8 at the
        sensor's declared size and, with ``calibration``, the calibration matches.
    """
    cfg = settings or CheckSettings()
    figures: dict[str, Any] = {}
    try:
        sensor = _open_camera_or_source(spec, cfg)
        with sensor:
            max_age_ms = cfg.read_timeout_s * 1000.0
            first = sensor.read_latest(max_age_ms=max_age_ms)
            start_s, last = monotonic_s(), first
            while monotonic_s() - start_s < cfg.rate_window_s:
                frame = sensor.read_latest(max_age_ms=max_age_ms)
                if frame.seq == last.seq:
                    time.sleep(0.001)
                last = frame
            rate_hz = (last.seq - first.seq) / (monotonic_s() - start_s)
            rgb = last.rgb
            figures.update(frame_rate_hz=round(rate_hz, 1), frame_hw=list(rgb.shape[:2]),
                           channels=int(rgb.shape[2]) if rgb.ndim == 3 else 1,
                           dtype=str(rgb.dtype), mm_per_px=sensor.mm_per_px,
                           mean_intensity=round(float(np.mean(rgb)), 1))
            if rate_hz < MIN_FRAME_RATE_HZ:
                return DeviceCheck("sensor", spec, False,
                                   f"opened but too slow: {rate_hz:.1f} frames/s, the station "
                                   f"needs >= {MIN_FRAME_RATE_HZ:.0f}; check the USB link "
                                   "and the camera's mode", figures)
            if calibration is not None:
                mismatch = _calibration_mismatch(calibration, sensor.shape_hw,
                                                 sensor.mm_per_px, figures)
                if mismatch:
                    return DeviceCheck("sensor", spec, False, f"bad setting: {mismatch}",
                                       figures)
    except TeleTouchError as err:
        return failed_check("sensor", spec, err, figures)
    h, w = figures["frame_hw"]
    calib = ", matches the calibration" if calibration is not None else ""
    return DeviceCheck("sensor", spec, True,
                       f"{figures['frame_rate_hz']:.0f} frames/s, {w}x{h} {figures['dtype']}, "
                       f"{sensor.mm_per_px:g} mm/px{calib}", figures)


def _calibration_mismatch(path: str | Path, shape_hw: tuple[int, int], mm_per_px: float,
                          figures: dict[str, Any]) -> str:
    """Why the calibration at ``path`` does not fit the frames, or "" when it does.

    Raises:
        CalibrationError: the file is missing or unreadable.
    """
    from remote_site.reconstruction.calibration import Calibration

    calib = Calibration.load(path)
    figures.update(calibration_hw=list(calib.shape_hw), calibration_mm_per_px=calib.mm_per_px)
    if tuple(calib.shape_hw) != tuple(shape_hw):
        return (f"calibration {path} is for {calib.shape_hw[1]}x{calib.shape_hw[0]} frames but "
                f"the sensor delivers {shape_hw[1]}x{shape_hw[0]}; recalibrate "
                "(teletouch sensor calibrate)")
    if not np.isclose(calib.mm_per_px, mm_per_px, rtol=1e-3):
        return (f"calibration {path} has {calib.mm_per_px:g} mm/px but the sensor delivers "
                f"{mm_per_px:g} mm/px; recalibrate (teletouch sensor calibrate)")
    return ""


def check_remote(arm: str, sensor: str, settings: CheckSettings | None = None, *,
                 move: bool = False, calibration: str | Path | None = None) -> CheckReport:
    """Probe the remote station's arm and sensor, one after the other.

    Args:
        arm: arm backend name.
        sensor: sensor spec.
        settings: time bounds.
        move: see :func:`check_arm`.
        calibration: see :func:`check_sensor`.

    Returns:
        The report (``exit_code`` 0 when both passed).
    """
    return CheckReport("remote", (check_arm(arm, settings, move=move),
                                  check_sensor(sensor, settings, calibration=calibration)))
