"""The no-contact background of the remote station: captured at start, refreshed when idle.

A real gel's illumination drifts between calibration day and a session (LEDs, exposure,
temperature), and the reconstruction divides every frame by the background: a stale one
reads as slopes everywhere. So the station

* **captures** the background at start, before any press (the arm is at its home pose, pad
  lifted): the mean of ``frames`` distinct sensor frames, refused if the arm already feels a
  force;
* **refreshes** it while the pad is known to be out of contact: arm force below
  ``max_force_n`` *and* no reconstructed contact, both for ``quiet_s``; the mean of the last
  ``frames`` such frames replaces the background (:meth:`Reconstructor.set_background`);
* **reports** its drift from the calibration's background: the mean absolute difference per
  channel (R, G, B, grey levels), and the time since the last capture.

The calibration's background is only the fallback: used until the first capture, and when
a capture fails (reported once). :meth:`BackgroundTracker.offer` runs in the pipeline's
worker thread, the one that reconstructs, so the swap never races a reconstruction.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from remote_site.reconstruction.reconstructor import Reconstructor
from remote_site.sensor.base import TactileSensor
from shared.errors import ConfigError, DeviceError, InputDataError
from shared.timebase import monotonic_s

__all__ = ["BackgroundSettings", "BackgroundTracker", "channel_drift"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BackgroundSettings:
    """When and how the station captures its background.

    Attributes:
        frames: distinct sensor frames averaged per capture.
        quiet_s: out of contact for this long before a refresh (and between refreshes).
        max_force_n: arm force below this counts as "pad lifted".
        capture_timeout_s: longest wait for the start capture's frames.
        max_frame_age_ms: a frame older than this is not used.
    """

    frames: int = 5
    quiet_s: float = 2.0
    max_force_n: float = 0.05
    capture_timeout_s: float = 2.0
    max_frame_age_ms: float = 100.0

    def __post_init__(self) -> None:
        if not (isinstance(self.frames, int) and 1 <= self.frames <= 100):
            raise ConfigError(f"background frames must be an integer in [1, 100], got "
                              f"{self.frames!r}")
        for name in ("quiet_s", "max_force_n", "capture_timeout_s", "max_frame_age_ms"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"background {name} must be finite and > 0, got {value!r}")


def channel_drift(background: np.ndarray, reference: np.ndarray) -> list[float]:
    """Mean absolute difference per channel (grey levels) between two RGB images.

    Raises:
        InputDataError: the images differ in shape.
    """
    a, b = np.asarray(background, np.float64), np.asarray(reference, np.float64)
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
        raise InputDataError(f"cannot compare backgrounds of shapes {a.shape} and {b.shape}")
    return [float(v) for v in np.abs(a - b).mean(axis=(0, 1))]


class BackgroundTracker:
    """Keeps the reconstructor's background fresh (see the module docstring).

    Args:
        reconstructor: its background is replaced; its calibration's is the reference.
        settings: capture and refresh rules.
        clock: monotonic seconds (tests pass a fake one).
    """

    def __init__(self, reconstructor: Reconstructor, settings: BackgroundSettings | None = None,
                 clock: Any = monotonic_s) -> None:
        self.reconstructor = reconstructor
        self.settings = settings or BackgroundSettings()
        self._clock = clock
        self._reference = np.asarray(reconstructor.calibration.background_rgb, np.float32)
        self._quiet: deque[np.ndarray] = deque(maxlen=self.settings.frames)
        self._quiet_since_s: float | None = None
        self.source = "calibration"
        self.captures = 0
        self.capture_failures = 0
        self.last_capture_s: float | None = None
        self.drift_rgb: list[float] = [0.0, 0.0, 0.0]

    def _use(self, background: np.ndarray, now_s: float) -> bool:
        try:
            self.reconstructor.set_background(background)
        except InputDataError as err:
            self._failed(f"unusable background: {err}")
            return False
        self.drift_rgb = channel_drift(self.reconstructor.background_rgb, self._reference)
        self.source = "station"
        self.captures += 1
        self.last_capture_s = now_s
        return True

    def _failed(self, why: str) -> None:
        self.capture_failures += 1
        if self.capture_failures == 1:
            log.warning("background capture failed (%s): keeping the %s background", why,
                        self.source)
        elif log.isEnabledFor(logging.DEBUG):
            log.debug("background capture failed (%s)", why)

    def capture(self, sensor: TactileSensor, force_n: float) -> bool:
        """Capture the background now: the mean of ``frames`` distinct sensor frames.

        Call it before any press, with the arm at its home pose.

        Args:
            sensor: the connected sensor.
            force_n: the arm's current force (a force means the pad touches something).

        Returns:
            True when the capture is in use; False (reported once) when the pad is not
            free, the sensor delivers too few frames in time, or the frames are unusable.
        """
        s = self.settings
        if not force_n < s.max_force_n:
            self._failed(f"arm force {force_n:.3f} N at start: the pad is not lifted")
            return False
        frames: list[np.ndarray] = []
        last_seq: int | None = None
        deadline = time.monotonic() + s.capture_timeout_s
        while len(frames) < s.frames and time.monotonic() < deadline:
            try:
                frame = sensor.read_latest(s.max_frame_age_ms)
            except DeviceError:
                time.sleep(0.005)
                continue
            if frame.seq != last_seq:
                last_seq = frame.seq
                frames.append(frame.rgb.astype(np.float32))
            else:
                time.sleep(0.002)
        if len(frames) < s.frames:
            self._failed(f"{len(frames)} of {s.frames} frames within {s.capture_timeout_s} s")
            return False
        if not self._use(np.mean(frames, axis=0), self._clock()):
            return False
        log.info("background captured at start (%d frames): drift from the calibration's "
                 "R %.1f G %.1f B %.1f grey levels", len(frames), *self.drift_rgb)
        return True

    def offer(self, rgb: np.ndarray, force_n: float, contact: bool) -> bool:
        """Consider one processed frame for a refresh.

        Args:
            rgb: the sensor frame just reconstructed.
            force_n: the arm's force when it was taken.
            contact: whether the reconstruction found contact in it.

        Returns:
            True when this frame completed a refresh.
        """
        now = self._clock()
        if contact or not force_n < self.settings.max_force_n:
            self._quiet.clear()
            self._quiet_since_s = None
            return False
        if self._quiet_since_s is None:
            self._quiet_since_s = now
        self._quiet.append(rgb)
        quiet_for = now - self._quiet_since_s
        since_last = math.inf if self.last_capture_s is None else now - self.last_capture_s
        if (len(self._quiet) < self.settings.frames or quiet_for < self.settings.quiet_s
                or since_last < self.settings.quiet_s):
            return False
        mean = np.mean(np.stack(self._quiet).astype(np.float32), axis=0)
        if not self._use(mean, now):
            return False
        if log.isEnabledFor(logging.DEBUG):
            log.debug("background refreshed: drift R %.1f G %.1f B %.1f", *self.drift_rgb)
        return True

    def summary(self) -> dict[str, Any]:
        """Source, drift from the calibration's background and age (plain JSON values)."""
        age = None if self.last_capture_s is None else max(0.0, self._clock()
                                                           - self.last_capture_s)
        return {"source": self.source, "captures": self.captures,
                "capture_failures": self.capture_failures,
                "drift_from_calibration_rgb": list(self.drift_rgb),
                "drift_from_calibration_mean": float(np.mean(self.drift_rgb)),
                "since_last_capture_s": age}
