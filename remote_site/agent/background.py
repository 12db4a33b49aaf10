"""The no-contact background of the remote station: captured at start, refreshed when idle.

A real gel's illumination drifts between calibration day and a session (LEDs, exposure,
temperature), and the reconstruction divides every frame by the background: a stale one
reads as slopes everywhere. So the station

* **captures** the background at start, before any press (the arm is at its home pose, pad
  lifted): the mean of ``frames`` distinct sensor frames, refused if the arm's force reading
  is a press (at or above ``press_force_n``) or if the mean shows contact against the
  calibration's background (the force reading alone let a background taken during a press
  in: every lifted frame then read as contact against it, and it was never replaced);
* **refreshes** it while the pad is known to be out of contact: no reconstructed contact,
  no force reading at or above ``press_force_n``, and the *median* force of the last
  ``quiet_s`` below ``max_force_n``, for ``quiet_s``; the mean of the last ``frames`` such
  frames replaces the background (:meth:`Reconstructor.set_background`). The median, not
  every reading: with the arm's force noise (0.1 N rms per reading for a Franka-class
  joint-torque estimate, ``remote_site/agent/world.py``) some reading of 2 s exceeded
  0.05 N, and the background was never refreshed;
* **recovers** from a background in use that makes the lifted gel read as contact: a frame
  with contact but no press force is checked against the calibration's background (at most
  once per ``quiet_s``, and only while a station background is in use); if it shows no
  contact there, such frames count as quiet and their
  mean (checked the same way) replaces the background;
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
        max_force_n: the median arm force over the last ``quiet_s`` below this counts as
            "pad lifted". The median of n readings of noise sigma scatters by ~1.25 sigma /
            sqrt(n): with ``force_noise_n`` 0.1 N and 2 s of frames at 25-80 frames/s
            (n = 50-160), 0.011-0.018 N, so a lifted pad's median stays below 0.05 N unless
            the force reading has an offset of about 0.05 N or more (tare the arm).
        force_noise_n: rms noise of one force reading (default: the simulated Franka-class
            estimate's, 0.1 N; about 0.01 N for a wrist force/torque sensor). One reading at
            or above ``press_force_n = max_force_n + 3 x force_noise_n`` is a press: it
            refuses the start capture and restarts the quiet stretch.
        capture_timeout_s: longest wait for the start capture's frames.
        max_frame_age_ms: a frame older than this is not used.
    """

    frames: int = 5
    quiet_s: float = 2.0
    max_force_n: float = 0.05
    force_noise_n: float = 0.1
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
        if not (math.isfinite(self.force_noise_n) and self.force_noise_n >= 0):
            raise ConfigError(f"background force_noise_n must be finite and >= 0, got "
                              f"{self.force_noise_n!r}")

    @property
    def press_force_n(self) -> float:
        """One force reading at or above this is a press (3 sigma of the noise above
        ``max_force_n``)."""
        return self.max_force_n + 3.0 * self.force_noise_n


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
        #: (time, force) of the quiet stretch's frames over the last quiet_s
        self._forces: deque[tuple[float, float]] = deque()
        #: the background in use makes the lifted gel read as contact (see _is_background)
        self._suspect = False
        self._next_check_s = -math.inf
        #: (the background in use, whether it shows contact against the calibration's)
        self._bg_checked: tuple[np.ndarray, bool] | None = None
        self.source = "calibration"
        self.captures = 0
        self.capture_failures = 0
        self.last_capture_s: float | None = None
        self.drift_rgb: list[float] = [0.0, 0.0, 0.0]

    def _contact_against_calibration(self, rgb: np.ndarray) -> str | None:
        """None if ``rgb`` shows no contact against the calibration's background (full
        resolution), else why it cannot be a no-contact frame."""
        try:
            hm = self.reconstructor.height_map(rgb, background=self._reference)
        except InputDataError as err:
            return f"is not usable ({err})"
        if hm.contact:
            return (f"shows contact against the calibration's background (up to "
                    f"{hm.max_height_mm:.2f} mm over {hm.mask.mean():.1%} of the frame)")
        return None

    def _use(self, background: np.ndarray, now_s: float, check: bool = False) -> bool:
        if check:
            why = self._contact_against_calibration(background)
            if why is not None:
                self._failed(f"the frames' mean {why}: the pad is not free, or the sensor "
                             "changed since its calibration (recalibrate)")
                return False
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
            force_n: the arm's current force reading (a press refuses the capture).

        Returns:
            True when the capture is in use; False (reported once) when the pad is not
            free (a press force, or the frames' mean shows contact against the calibration's
            background), the sensor delivers too few frames in time, or the frames are
            unusable. The calibration's background stays in use; a refresh replaces it.
        """
        s = self.settings
        if not force_n < s.press_force_n:
            self._failed(f"arm force {force_n:.3f} N at start (a press: >= "
                         f"{s.press_force_n:.2f} N): the pad is not lifted")
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
        # not checked against the calibration's background: a gel whose lighting or surface
        # changed since calibration day reads as contact against it, and refusing its own
        # background left it so for the whole session (found by review); one taken during
        # a press is replaced once the pad is lifted (offer)
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
        s = self.settings
        if not force_n < s.press_force_n or (contact and not self._is_background(rgb, now)):
            self._restart()
            return False
        if self._quiet_since_s is None:
            self._quiet_since_s = now
        self._quiet.append(rgb)
        self._forces.append((now, force_n))
        while now - self._forces[0][0] > s.quiet_s:
            self._forces.popleft()
        quiet_for = now - self._quiet_since_s
        since_last = math.inf if self.last_capture_s is None else now - self.last_capture_s
        if len(self._quiet) < s.frames or quiet_for < s.quiet_s or since_last < s.quiet_s:
            return False
        if not float(np.median([f for _, f in self._forces])) < s.max_force_n:
            return False  # leaning on something, or the force reading has an offset
        recent = [f for t, f in self._forces if now - t <= s.quiet_s / 4]
        if not float(np.median(recent)) < s.max_force_n:
            return False  # a slow press under way: the stretch's median lags it by ~1 s
        mean = np.mean(np.stack(self._quiet).astype(np.float32), axis=0)
        if not self._use(mean, now, check=self._suspect):
            self._restart()
            return False
        if self._suspect:
            log.warning("background replaced: the one in use made the lifted gel read as "
                        "contact (taken during a press?)")
            self._suspect = False
        elif log.isEnabledFor(logging.DEBUG):
            log.debug("background refreshed: drift R %.1f G %.1f B %.1f", *self.drift_rgb)
        return True

    def _restart(self) -> None:
        """A press or a contact: the quiet stretch starts again."""
        self._quiet.clear()
        self._forces.clear()
        self._quiet_since_s = None
        self._suspect = False

    def _is_background(self, rgb: np.ndarray, now: float) -> bool:
        """Whether the contact a frame shows with no press force comes from the background in
        use: the frame shows none against the calibration's (so never while that is the one
        in use). Checked at most once per ``quiet_s`` while the answer is no; a yes holds
        until the next press or refresh."""
        if self._suspect:
            return True
        if self.source != "station" or now < self._next_check_s:
            return False
        self._next_check_s = now + self.settings.quiet_s
        # only a background that itself shows contact against the calibration's is suspect
        # (checked once per background): a light touch on a gel that changed since
        # calibration day must not replace a good one (found by review)
        bg = self.reconstructor.background_rgb
        if self._bg_checked is None or self._bg_checked[0] is not bg:
            self._bg_checked = (bg, self._contact_against_calibration(bg) is not None)
        self._suspect = self._bg_checked[1] and self._contact_against_calibration(rgb) is None
        return self._suspect

    def summary(self) -> dict[str, Any]:
        """Source, drift from the calibration's background and age (plain JSON values)."""
        age = None if self.last_capture_s is None else max(0.0, self._clock()
                                                           - self.last_capture_s)
        return {"source": self.source, "captures": self.captures,
                "capture_failures": self.capture_failures,
                "drift_from_calibration_rgb": list(self.drift_rgb),
                "drift_from_calibration_mean": float(np.mean(self.drift_rgb)),
                "since_last_capture_s": age}
