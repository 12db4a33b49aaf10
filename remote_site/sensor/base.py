"""One base class for every visuotactile sensor source (camera, simulator, ...).

The public methods do the state checks, timeouts and validation; backends implement three
private methods (python-can / lerobot habit)::

    _connect() -> None            open the device (raise DeviceInitError)
    _disconnect() -> None         release it (must not raise)
    _latest() -> SensorFrame|None the newest frame captured so far, or None

``read_latest(max_age_ms)`` returns the newest frame if it is fresh enough and raises
:class:`~shared.errors.DeviceTimeoutError` otherwise, so a consumer never silently works on
an old image.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass
from types import TracebackType

import numpy as np

from shared.errors import DeviceNotConnectedError, DeviceOperationError, DeviceTimeoutError
from shared.timebase import now_us

__all__ = ["SensorFrame", "TactileSensor"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SensorFrame:
    """One RGB image from a tactile sensor.

    Attributes:
        rgb: (H, W, 3) uint8 image, RGB order.
        timestamp_us: capture time, wall clock microseconds (``shared.timebase.now_us``).
        seq: capture sequence number, increasing by one per captured frame.
    """

    rgb: np.ndarray
    timestamp_us: int
    seq: int


class TactileSensor(ABC):
    """Abstract visuotactile sensor source.

    Args:
        shape_hw: (rows, cols) of the frames delivered.
        mm_per_px: pixel pitch of the delivered frames on the gel.
    """

    def __init__(self, shape_hw: tuple[int, int], mm_per_px: float) -> None:
        self.shape_hw = (int(shape_hw[0]), int(shape_hw[1]))
        self.mm_per_px = float(mm_per_px)
        self._connected = False

    @property
    def is_connected(self) -> bool:
        """True between :meth:`connect` and :meth:`disconnect`."""
        return self._connected

    def connect(self) -> None:
        """Open the sensor (idempotent).

        Raises:
            DeviceInitError: the backend could not open the device.
        """
        if self._connected:
            return
        self._connect()
        self._connected = True
        log.info("%s connected (%dx%d, %.4f mm/px)", type(self).__name__, self.shape_hw[1],
                 self.shape_hw[0], self.mm_per_px)

    def disconnect(self) -> None:
        """Release the sensor (idempotent, never raises for an already closed sensor)."""
        if not self._connected:
            return
        self._connected = False
        self._disconnect()
        log.info("%s disconnected", type(self).__name__)

    def __enter__(self) -> TactileSensor:
        self.connect()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.disconnect()

    def read_latest(self, max_age_ms: float = 100.0) -> SensorFrame:
        """Return the newest frame, if it is at most ``max_age_ms`` old.

        Raises:
            DeviceNotConnectedError: called before connect() or after disconnect().
            DeviceTimeoutError: no frame yet, or the newest one is too old.
            DeviceOperationError: the backend delivered a frame of the wrong size or type.
        """
        if not self._connected:
            raise DeviceNotConnectedError(f"{type(self).__name__} is not connected")
        frame = self._latest()
        if frame is None:
            raise DeviceTimeoutError(f"{type(self).__name__}: no frame captured yet")
        age_ms = (now_us() - frame.timestamp_us) / 1000.0
        if age_ms > max_age_ms:
            raise DeviceTimeoutError(f"{type(self).__name__}: newest frame is {age_ms:.0f} ms "
                                     f"old (max {max_age_ms:.0f} ms)")
        rgb = frame.rgb
        if rgb.dtype != np.uint8 or rgb.shape != (*self.shape_hw, 3):
            raise DeviceOperationError(f"{type(self).__name__}: frame {rgb.shape} {rgb.dtype}, "
                                       f"expected {(*self.shape_hw, 3)} uint8")
        return frame

    @abstractmethod
    def _connect(self) -> None:
        """Open the device."""

    @abstractmethod
    def _disconnect(self) -> None:
        """Release the device."""

    @abstractmethod
    def _latest(self) -> SensorFrame | None:
        """The newest captured frame, or None."""
