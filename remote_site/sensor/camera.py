"""Real visuotactile camera through OpenCV ``VideoCapture`` (device index, URL or video file).

Frames are cropped and sized by a named preset (:mod:`.camera_presets`): ``mini-raw`` for a
GelSight Mini's raw camera (1/7 cropped off each side, resized to 320 x 240; the default),
``mini-recording`` for a recording of the Mini's 320 x 240 output (taken as it is). A
background thread keeps only the newest frame (lerobot's ``read_latest`` habit);
``read_latest(max_age_ms)`` refuses stale frames.

A source behaves like a camera:

* a **video file** is paced at its own frame rate (or ``fps``): frame ``n`` is published
  ``n / fps`` s after the first, stamped with the time it is published, so a consumer sees
  the recording in real time instead of all of it within a second; ``loop=True`` restarts it
  at its end (by reopening it);
* a video file without loop **ends** at its end: reported once (WARNING) and in
  :attr:`health` (``ended``), the only true end; an image of a file that cannot be used is
  skipped and counted (``bad_images``) in its own time (the frames after it are not
  published early);
* a live camera never ends by itself (a station never gives up on a transient fault): an
  image that cannot be used (it failed to decode, or has the wrong shape or type) is
  skipped and counted (``bad_images``), and a failed read (an unplugged camera, a dropped
  stream) releases the device and opens it again after 0.1, 0.2, 0.5, 1 then every 2 s
  (``reopens``); each is reported once per run;
* a source that **stalls** (no new frame for ``stall_timeout_s``: a silent camera, or one
  being reopened) is reported once per silence and counted (``stalls``). None of these
  changes ``read_latest``: its frames just grow old, and the consumer's stale-frame logic
  applies.

Found by an audit: one corrupt image, or one read failure, ended the camera for good, and
nothing reconnected it; and a reader thread abandoned while its read hung (an unplugged
USB camera can block for seconds) later marked the next connection ended. Only the current
connection's reader changes the sensor's state now; an abandoned one ends as its read
returns, before it touches anything (nor does it decode from its capture, released by then).

A live camera is read in two steps where the capture offers them (OpenCV's ``grab`` and
``retrieve``): each image is stamped as it is taken off the device, before its decoding, and
one paced below its own rate (``fps``) decodes only the images it publishes. With OpenCV's
V4L2 capture (a USB camera on Linux) ``retrieve`` does the decoding (MJPEG) or the colour
conversion (YUYV), so the images dropped between cost none of it. With its FFmpeg capture
(``rtsp://``, ``http://`` URLs) ``grab`` decodes and only the colour conversion is saved; a
GStreamer pipeline decodes in its own threads. Never more work than ``read()``, which is
``grab()`` then ``retrieve()``.

For tests, ``capture_factory`` replaces ``cv2.VideoCapture`` with any object offering
``isOpened()``, ``read() -> (ok, bgr)`` and ``release()`` (and optionally ``get(prop)`` for a
file's frame rate, and ``grab()`` with ``retrieve()`` to be read as OpenCV's are).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol, TypeGuard

import numpy as np

from remote_site.sensor.base import SensorFrame, SensorHealth, TactileSensor
from remote_site.sensor.camera_presets import (
    DEFAULT_PRESET,
    GELSIGHT_MINI_MM_PER_PX,
    CameraPreset,
    camera_preset,
    shape_frame,
)
from shared.devices import ReaderThread
from shared.errors import ConfigError, DeviceInitError, DeviceTimeoutError, InputDataError
from shared.timebase import now_us

__all__ = ["GELSIGHT_MINI_MM_PER_PX", "OpenCVCameraSensor", "crop_and_resize"]

log = logging.getLogger(__name__)

#: cv2.CAP_PROP_FPS (kept here so the module imports without OpenCV)
_CAP_PROP_FPS = 5
#: waits before opening a live camera again after a failed read (s); the last repeats
REOPEN_BACKOFF_S = (0.1, 0.2, 0.5, 1.0, 2.0)
#: a live camera's unusable images are taken at most this often (no busy loop)
_BAD_IMAGE_GAP_S = 0.002


class _Capture(Protocol):
    def isOpened(self) -> bool: ...
    def read(self) -> tuple[bool, Any]: ...
    def release(self) -> None: ...


class _GrabCapture(_Capture, Protocol):
    """A capture that takes an image off the device apart from decoding it (OpenCV's)."""

    def grab(self) -> bool: ...
    def retrieve(self) -> tuple[bool, Any]: ...


def _decodes_apart(capture: _Capture) -> TypeGuard[_GrabCapture]:
    return callable(getattr(capture, "grab", None)) and \
        callable(getattr(capture, "retrieve", None))


def crop_and_resize(bgr: np.ndarray, out_hw: tuple[int, int] = (240, 320),
                    crop_fraction: float = 1.0 / 7.0) -> np.ndarray:
    """Crop ``crop_fraction`` of each dimension off every side, resize, convert BGR -> RGB.

    Args:
        bgr: raw (H, W, 3) uint8 frame from OpenCV (BGR order).
        out_hw: output (rows, cols).
        crop_fraction: fraction of the height/width removed on each side.

    Returns:
        (rows, cols, 3) uint8 RGB frame.
    """
    preset = CameraPreset("custom", crop_fraction, out_hw, True, GELSIGHT_MINI_MM_PER_PX)
    return shape_frame(bgr, preset)


def _positive_or_none(value: float | None, name: str) -> float | None:
    if value is None:
        return None
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"camera {name} must be finite and > 0, got {value}")
    return value


class OpenCVCameraSensor(TactileSensor):
    """GelSight-style camera read through OpenCV.

    Args:
        source: device index (``0``), stream URL or video file path.
        preset: crop / size preset (``mini-raw``: raw Mini camera, the default;
            ``mini-recording``: an already cropped 320 x 240 recording).
        out_hw: delivered frame size (rows, cols); the preset's when None.
        mm_per_px: pitch of the delivered frames; the preset's when None.
        crop_fraction: border removed on each side before resizing; the preset's when None.
        fps: publish frames at this rate; None: a video file's own rate, a live camera
            unpaced (it paces itself). A video file waits until each frame is due; a live
            camera drops the frames it delivers in between (held, they would age).
        loop: restart a video file at its end.
        stall_timeout_s: no new frame for this long counts as a stall.
        first_frame_timeout_s: how long connect() waits for the first frame.
        capture_factory: builds the capture object (``cv2.VideoCapture`` by default).
        latency_ms: how long before its arrival here an image was taken (exposure, the
            camera's and the USB stack's buffering), when known for the device: frames are
            stamped that much before they arrive, so the station pairs each with the command
            and the arm pose of its time, and ages it as what it is. 0 (the default): stamped
            at arrival, an upper bound on the image's time. Not measured here for any preset.
            Arrival is when the image is taken off the device (``grab``, before decoding) where
            the capture offers ``grab`` and ``retrieve``; when ``read()`` returns otherwise.

    Raises:
        ConfigError: an unknown preset, a non-positive rate / timeout, or a negative or
            non-finite latency.
    """

    notifies_frames = True  # each frame as it arrives (the station takes it then)

    def __init__(self, source: int | str = 0, preset: str = DEFAULT_PRESET,
                 out_hw: tuple[int, int] | None = None, mm_per_px: float | None = None,
                 crop_fraction: float | None = None, fps: float | None = None,
                 loop: bool = False, stall_timeout_s: float = 1.0,
                 first_frame_timeout_s: float = 5.0,
                 capture_factory: Callable[[int | str], _Capture] | None = None,
                 latency_ms: float = 0.0) -> None:
        base = camera_preset(preset)
        self.preset = CameraPreset(
            base.name,
            base.crop_fraction if crop_fraction is None else float(crop_fraction),
            base.out_hw if out_hw is None else (int(out_hw[0]), int(out_hw[1])),
            base.resize, base.mm_per_px if mm_per_px is None else float(mm_per_px))
        super().__init__(self.preset.out_hw, self.preset.mm_per_px)
        if isinstance(source, str) and source.isdigit():
            source = int(source)
        self.source = source
        self.crop_fraction = self.preset.crop_fraction
        self.fps = _positive_or_none(fps, "fps")
        self.loop = bool(loop)
        self.stall_timeout_s = float(_positive_or_none(stall_timeout_s, "stall_timeout_s") or 1.0)
        self.first_frame_timeout_s = float(first_frame_timeout_s)
        self._factory = capture_factory
        latency_ms = float(latency_ms)
        if not (math.isfinite(latency_ms) and latency_ms >= 0):
            raise ConfigError(f"camera latency_ms must be finite and >= 0, got {latency_ms}")
        self._latency_us = round(latency_ms * 1000.0)
        self._capture: _Capture | None = None
        self._reader: ReaderThread | None = None
        self._wake = threading.Event()
        self._lock = threading.Lock()
        self._newest: SensorFrame | None = None
        self._seq = 0
        self._period_s: float | None = None
        self._next_due_s: float | None = None
        self._file = False  # whether the source is a video file (known at connect)
        self._health = SensorHealth()
        self._bad_run = False  # the last image was bad (one warning per run of them)
        self._bad_since = 0.0  # when the run of bad images began (monotonic s)
        self._reopen_tries = 0  # tries to open the camera again since its last frame
        self.read_error: str | None = None

    @property
    def is_file(self) -> bool:
        """True when the source is a video file on disk (paced, loopable)."""
        return isinstance(self.source, str) and "://" not in self.source and Path(
            self.source).is_file()

    @property
    def health(self) -> SensorHealth:
        """Ended / stalled state of the source (see the module docstring)."""
        with self._lock:
            self._check_stall()
            return self._health

    def _open_capture(self) -> _Capture:
        if self._factory is not None:
            return self._factory(self.source)
        import cv2

        return cv2.VideoCapture(self.source)

    def _file_fps(self, capture: _Capture) -> float | None:
        get = getattr(capture, "get", None)
        if get is None:
            return None
        try:
            fps = float(get(_CAP_PROP_FPS))
        except (TypeError, ValueError):
            return None
        return fps if math.isfinite(fps) and 0 < fps <= 1000 else None

    def _connect(self) -> None:
        try:
            capture = self._open_capture()
        except Exception as err:  # vendor errors of any kind: wrap them
            raise DeviceInitError(f"cannot open camera {self.source!r}: {err}") from err
        if not capture.isOpened():
            capture.release()
            raise DeviceInitError(f"camera {self.source!r} did not open (unplugged, busy or a "
                                  "wrong URL?)")
        self._period_s = None
        self._file = self.is_file  # once: a file renamed while it plays stays a file
        if self.fps is not None:
            self._period_s = 1.0 / self.fps
        elif self._file:
            fps = self._file_fps(capture)
            if fps is None:
                capture.release()
                raise DeviceInitError(f"video file {self.source!r} does not state its frame "
                                      "rate: give one (fps option, --sensor-fps)")
            self._period_s = 1.0 / fps
        if self._period_s is not None:
            log.info("camera %r: paced at %.2f frames/s%s", self.source, 1.0 / self._period_s,
                     ", looped" if self.loop else "")
        self._capture = capture
        self._newest = None
        self._next_due_s = None
        self._health = SensorHealth()
        self._bad_run = False
        self._reopen_tries = 0
        self.read_error = None
        self._wake.clear()
        self._reader = ReaderThread("tactile-camera", self._read_once)
        self._reader.start()
        deadline = time.monotonic() + self.first_frame_timeout_s
        while self._newest is None and time.monotonic() < deadline:
            if self._health.ended or not self._reader.is_alive:
                break
            time.sleep(0.002)
        if self._newest is None:
            self._disconnect()
            reason = self.read_error or "no data"
            raise DeviceTimeoutError(f"camera {self.source!r} delivered no frame within "
                                     f"{self.first_frame_timeout_s} s ({reason})")

    def _restart(self) -> bool:
        """Reopen a looped video file at its start; False when that fails."""
        old, self._capture = self._capture, None
        if old is not None:
            old.release()
        try:
            capture = self._open_capture()
        except Exception as err:  # vendor errors of any kind: report them as the end
            log.debug("camera %r: reopening failed: %s", self.source, err)
            return False
        if not capture.isOpened():
            capture.release()
            return False
        self._capture = capture
        with self._lock:
            self._health = replace(self._health, loops=self._health.loops + 1)
        return True

    def _current(self) -> bool:
        """Whether the calling reader thread is this connection's (not one abandoned by a
        disconnect while its read hung, whose late result must not touch the new one)."""
        reader = self._reader
        return reader is not None and reader.is_current_thread

    def _end(self, reason: str) -> bool:
        if not self._current():
            return False
        if self._bad_run:  # the images before the end were skipped: say why
            reason = f"{reason}, after images that were skipped: {self.read_error}"
        self.read_error = reason
        with self._lock:
            self._health = replace(self._health, ended=True, reason=reason)
        if not self._wake.is_set():  # not a disconnect in progress
            log.warning("camera %r ended: %s; no new frame will come (the station keeps its "
                        "stale-frame behaviour)", self.source, reason)
        return False

    def _bad_image(self, reason: str) -> bool:
        """An image that cannot be used: skipped and counted; the stream goes on. A live
        camera that gives nothing but such images for ``stall_timeout_s`` is taken as lost
        (opened again), and bad images come at most every ``_BAD_IMAGE_GAP_S`` (found by
        review: a device returning empty images at once made a busy loop, never reopened)."""
        if not self._current():
            return False
        self.read_error = reason
        with self._lock:
            self._health = replace(self._health, bad_images=self._health.bad_images + 1)
        now = time.monotonic()
        if not self._bad_run:
            log.warning("camera %r: an image was skipped (%s); skipping such images until a "
                        "good one comes", self.source, reason)
            self._bad_run, self._bad_since = True, now
        if self._file:  # its image keeps its time: the frames after it are not early
            return self._wait_until_due()
        if now - self._bad_since > self.stall_timeout_s:
            return self._lost(f"no usable image for {now - self._bad_since:.1f} s")
        return not self._wake.wait(_BAD_IMAGE_GAP_S)

    def _lost(self, reason: str) -> bool:
        """A live camera's read failed (unplugged, a dropped stream): release it and open it
        again, waiting :data:`REOPEN_BACKOFF_S` between tries, until it opens or the sensor
        stops (False). Its frames age meanwhile (a stall)."""
        if not self._current():
            return False
        if self._bad_run:  # the images before were skipped: say why
            reason = f"{reason}, after images that were skipped: {self.read_error}"
        self.read_error = reason
        if not self._reopen_tries:  # once per outage: it lasts until a frame comes
            log.warning("camera %r: %s; opening it again until it delivers", self.source,
                        reason)
        old, self._capture = self._capture, None
        if old is not None:
            old.release()
        while not self._wake.wait(
                REOPEN_BACKOFF_S[min(self._reopen_tries, len(REOPEN_BACKOFF_S) - 1)]):
            self._reopen_tries += 1  # the waits grow until a frame comes, not until it opens
            if not self._current():
                return False
            try:
                capture = self._open_capture()
            except Exception as err:  # vendor errors of any kind: try again
                log.debug("camera %r: opening failed: %s", self.source, err)
                continue
            if not capture.isOpened():
                capture.release()
                continue
            if not self._current():  # disconnected meanwhile: not ours to keep
                capture.release()
                return False
            self._capture = capture
            self._bad_run = False  # a new run of bad images, if any, starts on this one
            with self._lock:
                self._health = replace(self._health, reopens=self._health.reopens + 1)
            log.info("camera %r opened again (try %d)", self.source, self._reopen_tries)
            return True
        return False  # the sensor stops

    def _read_once(self) -> bool:
        try:
            return self._read_step()
        except Exception as err:  # a backend's own error (cv2.error, ...): one bad image
            # (found by review: it ended the reader thread, the camera stalled for good)
            return self._bad_image(f"the capture raised {type(err).__name__}: {err}")

    def _read_step(self) -> bool:
        capture = self._capture
        if capture is None or not self._current():
            return False
        # a live camera paced to fps drops images (a file waits instead: see _publish)
        live_period = None if self._file else self._period_s
        if not self._file and _decodes_apart(capture):
            return self._read_live(capture, live_period)
        ok, bgr = capture.read()
        read_us = now_us()  # a live camera's image arrived (before this station's crop)
        if not self._current():  # abandoned by a disconnect while it read
            return False
        looping = self.loop and self._file and self._newest is not None
        if (not ok or bgr is None) and looping and self._restart() and self._capture:
            ok, bgr = self._capture.read()
        if not ok or bgr is None:
            if self._file:
                return self._end("end of the video file")
            return self._lost("capture.read() failed (device lost or end of stream)")
        if live_period is not None and not self._due_now(live_period):
            return True  # frames between are dropped, not held
        return self._publish(bgr, read_us)

    def _read_live(self, capture: _GrabCapture, period: float | None) -> bool:
        """A live camera in two steps: the image is taken off the device (``grab``) and
        stamped, then decoded (``retrieve``). Paced to ``fps`` (``period``), only the due
        images are decoded; those between are dropped, not held and not decoded."""
        ok = capture.grab()
        read_us = now_us()  # the image arrived (before its decoding and this station's crop)
        if not self._current():  # abandoned by a disconnect while it grabbed
            return False
        if not ok:
            return self._lost("capture.grab() failed (device lost or end of stream)")
        if period is not None and not self._due_now(period):
            return True
        ok, bgr = capture.retrieve()
        if not ok or bgr is None:
            return self._bad_image("capture.retrieve() failed (the image could not be "
                                   "decoded)")
        return self._publish(bgr, read_us)

    def _publish(self, bgr: Any, read_us: int) -> bool:
        """Shape an image read at ``read_us`` and make it the newest frame (a video file's
        after its pacing wait); False when the source ends or the sensor stops."""
        if not isinstance(bgr, np.ndarray) or bgr.ndim != 3 or bgr.shape[2] != 3 \
                or bgr.dtype != np.uint8:
            return self._bad_image(f"unexpected frame {getattr(bgr, 'shape', None)} "
                                   f"{getattr(bgr, 'dtype', type(bgr).__name__)}")
        if bgr.size == 0:
            return self._bad_image(f"an empty image {bgr.shape}")
        try:
            rgb = shape_frame(bgr, self.preset)
        except InputDataError as err:
            return self._bad_image(str(err))
        if self._period_s is not None and self._file and not self._wait_until_due():
            return False
        # a live camera's image arrived at the read; a file's plays the camera: it arrives
        # when it is released, after its pacing wait
        arrival_us = now_us() if self._file else read_us
        with self._lock:
            if not self._current():
                return False
            if self._reopen_tries or self._health.stalled:  # said once, after either
                log.info("camera %r delivers frames again", self.source)
                self._health = replace(self._health, stalled=False)
            self._bad_run = False
            self._reopen_tries = 0
            self.read_error = None  # the last problem is over (read_error is the current one)
            self._seq += 1
            self._newest = SensorFrame(rgb=rgb, timestamp_us=arrival_us - self._latency_us,
                                       seq=self._seq, arrival_us=arrival_us)
        self._frame_arrived()
        return True

    def _due_now(self, period: float) -> bool:
        """A live camera paced to ``fps``: whether the frame just read is due (the schedule
        then moves on). One that is not is dropped rather than held until due: held, it
        would reach the station a period old (a stale image stamped as a fresh one, or
        one refused as too old)."""
        now = time.monotonic()
        due = self._due_s(now, period)
        if due > now:
            return False
        self._next_due_s = due + period
        return True

    def _due_s(self, now: float, period: float) -> float:
        """When the next frame is due: on schedule, or now when more than a frame behind (a
        slow decoder, a gap in a live stream): no burst to catch up."""
        due = now if self._next_due_s is None else self._next_due_s
        return now if due < now - period else due

    def _wait_until_due(self) -> bool:
        """Sleep until the next frame is due (a video file's real-time pacing); False if
        stopping."""
        period = self._period_s
        if period is None:
            return True
        now = time.monotonic()
        due = self._due_s(now, period)
        if due > now and self._wake.wait(due - now):
            return False
        self._next_due_s = due + period
        return True

    def _check_stall(self) -> None:
        """Under the lock: mark a stall once when the newest frame is too old."""
        h = self._health
        if h.ended or h.stalled or self._newest is None:
            return
        age_s = (now_us() - self._newest.received_us) / 1e6  # since it arrived
        if age_s > self.stall_timeout_s:
            self._health = replace(h, stalls=h.stalls + 1, stalled=True)
            log.warning("camera %r stalled: no new frame for %.1f s (stall %d)", self.source,
                        age_s, h.stalls + 1)

    def _disconnect(self) -> None:
        reader, self._reader = self._reader, None
        self._wake.set()
        if reader is not None:
            reader.request_stop()
            reader.stop(timeout_s=2.0)
        if self._capture is not None:
            self._capture.release()
            self._capture = None

    def _latest(self) -> SensorFrame | None:
        with self._lock:
            self._check_stall()
            return self._newest
