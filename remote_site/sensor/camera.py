"""Real visuotactile camera through OpenCV ``VideoCapture`` (device index, URL or video file).

A GelSight Mini delivers a wide raw image whose border shows the sensor housing; like the
vendor SDK, 1/7 of the height and of the width is cropped off each side and the rest is
resized to 320 x 240. A background thread keeps only the newest frame (lerobot's
``read_latest`` habit); ``read_latest(max_age_ms)`` refuses stale frames.

For tests, ``capture_factory`` replaces ``cv2.VideoCapture`` with any object offering
``isOpened()``, ``read() -> (ok, bgr)`` and ``release()``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from remote_site.sensor.base import SensorFrame, TactileSensor
from shared.devices import ReaderThread
from shared.errors import DeviceInitError, DeviceTimeoutError
from shared.timebase import now_us

__all__ = ["GELSIGHT_MINI_MM_PER_PX", "OpenCVCameraSensor", "crop_and_resize"]

log = logging.getLogger(__name__)

#: GelSight Mini at 320 x 240 after the standard crop
GELSIGHT_MINI_MM_PER_PX = 0.0634


class _Capture(Protocol):
    def isOpened(self) -> bool: ...
    def read(self) -> tuple[bool, Any]: ...
    def release(self) -> None: ...


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
    import cv2

    h, w = bgr.shape[:2]
    top, left = int(h * crop_fraction), int(w * crop_fraction)
    cropped = bgr[top:h - top, left:w - left]
    resized = cv2.resize(cropped, (out_hw[1], out_hw[0]), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(resized[:, :, ::-1])


class OpenCVCameraSensor(TactileSensor):
    """GelSight-style camera read through OpenCV.

    Args:
        source: device index (``0``), stream URL or video file path.
        out_hw: delivered frame size (rows, cols); 240 x 320 for a GelSight Mini.
        mm_per_px: pitch of the delivered frames (0.0634 for a GelSight Mini).
        crop_fraction: border removed on each side before resizing.
        first_frame_timeout_s: how long connect() waits for the first frame.
        capture_factory: builds the capture object (``cv2.VideoCapture`` by default).
    """

    def __init__(self, source: int | str = 0, out_hw: tuple[int, int] = (240, 320),
                 mm_per_px: float = GELSIGHT_MINI_MM_PER_PX, crop_fraction: float = 1.0 / 7.0,
                 first_frame_timeout_s: float = 5.0,
                 capture_factory: Callable[[int | str], _Capture] | None = None) -> None:
        super().__init__(out_hw, mm_per_px)
        if isinstance(source, str) and source.isdigit():
            source = int(source)
        self.source = source
        self.crop_fraction = float(crop_fraction)
        self.first_frame_timeout_s = float(first_frame_timeout_s)
        self._factory = capture_factory
        self._capture: _Capture | None = None
        self._reader: ReaderThread | None = None
        self._lock = threading.Lock()
        self._newest: SensorFrame | None = None
        self._seq = 0
        self.read_error: str | None = None

    def _open_capture(self) -> _Capture:
        if self._factory is not None:
            return self._factory(self.source)
        import cv2

        return cv2.VideoCapture(self.source)

    def _connect(self) -> None:
        try:
            capture = self._open_capture()
        except Exception as err:  # vendor errors of any kind: wrap them
            raise DeviceInitError(f"cannot open camera {self.source!r}: {err}") from err
        if not capture.isOpened():
            capture.release()
            raise DeviceInitError(f"camera {self.source!r} did not open (unplugged, busy or a "
                                  "wrong URL?)")
        self._capture = capture
        self._newest = None
        self.read_error = None
        self._reader = ReaderThread("tactile-camera", lambda: self._read_once(capture))
        self._reader.start()
        deadline = time.monotonic() + self.first_frame_timeout_s
        while self._newest is None and time.monotonic() < deadline:
            if self.read_error is not None:
                break
            time.sleep(0.002)
        if self._newest is None:
            self._disconnect()
            reason = self.read_error or "no data"
            raise DeviceTimeoutError(f"camera {self.source!r} delivered no frame within "
                                     f"{self.first_frame_timeout_s} s ({reason})")

    def _read_once(self, capture: _Capture) -> bool:
        ok, bgr = capture.read()
        if not ok or bgr is None:
            self.read_error = "capture.read() failed (end of stream or device lost)"
            log.warning("camera %r: %s", self.source, self.read_error)
            return False
        if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
            self.read_error = f"unexpected frame {bgr.shape} {bgr.dtype}"
            log.warning("camera %r: %s", self.source, self.read_error)
            return False
        rgb = crop_and_resize(bgr, self.shape_hw, self.crop_fraction)
        with self._lock:
            self._seq += 1
            self._newest = SensorFrame(rgb=rgb, timestamp_us=now_us(), seq=self._seq)
        return True

    def _disconnect(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.stop(timeout_s=2.0)
        if self._capture is not None:
            self._capture.release()
            self._capture = None

    def _latest(self) -> SensorFrame | None:
        with self._lock:
            return self._newest
