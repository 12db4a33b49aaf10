"""One base class for every visuotactile sensor source (camera, simulator, ...).

The lifecycle (``connect``/``disconnect``, context manager, errors by phase) is
:class:`~shared.devices.base.Device`'s; the public methods here do the state checks,
timeouts and validation, and backends implement three private methods (python-can /
lerobot habit)::

    _connect() -> None            open the device (raise DeviceInitError)
    _disconnect() -> None         release it (must not raise)
    _latest() -> SensorFrame|None the newest frame captured so far, or None

``read_latest(max_age_ms)`` returns the newest frame if it is fresh enough and raises
:class:`~shared.errors.DeviceTimeoutError` otherwise, so a consumer never silently works on
an old image.
"""

from __future__ import annotations

import logging
from abc import abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from shared.devices import Device
from shared.errors import DeviceOperationError, DeviceTimeoutError
from shared.timebase import now_us

__all__ = ["SensorFrame", "SensorHealth", "TactileSensor"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SensorFrame:
    """One RGB image from a tactile sensor.

    Attributes:
        rgb: (H, W, 3) uint8 image, RGB order.
        timestamp_us: capture time (when the image was taken, as well as the source knows:
            a streaming camera stamps its arrival less the device's known latency), wall
            clock microseconds (``shared.timebase.now_us``).
        seq: capture sequence number, increasing by one per captured frame.
        arrival_us: when the image reached this process (the driver received it), same
            clock; None: when it was stamped (a source that captures on demand stamps as its
            read returns). The motion-to-touch ledger's ``remote.sensor_arrival``
            (:attr:`received_us`): a streaming camera's delivery is then a stage of its own.
    """

    rgb: np.ndarray
    timestamp_us: int
    seq: int
    arrival_us: int | None = None

    @property
    def received_us(self) -> int:
        """When the image reached this process: :attr:`arrival_us`, else the stamp."""
        return self.timestamp_us if self.arrival_us is None else self.arrival_us


@dataclass(frozen=True)
class SensorHealth:
    """Whether a source still delivers frames (for status lines and summaries).

    Attributes:
        ended: the source delivered its last frame (a video file without looping, a
            simulator whose stream thread ended); no frame will come any more. A live
            camera never ends: a lost device is reopened (``reopens``).
        stalls: times the source went silent for longer than its stall timeout while
            still running (a live camera that stopped delivering).
        stalled: the source is silent right now.
        loops: times a looped video file restarted.
        reason: why the source ended, or None.
        bad_images: images skipped because they could not be used (failed to decode, the
            wrong shape or type); the stream went on.
        reopens: times a live camera whose read failed (unplugged, a dropped stream) was
            opened again.
    """

    ended: bool = False
    stalls: int = 0
    stalled: bool = False
    loops: int = 0
    reason: str | None = None
    bad_images: int = 0
    reopens: int = 0


class TactileSensor(Device):
    """Abstract visuotactile sensor source.

    Args:
        shape_hw: (rows, cols) of the frames delivered.
        mm_per_px: pixel pitch of the delivered frames on the gel.

    Attributes:
        captures_on_demand: every :meth:`read_latest` captures a new frame now (a renderer,
            a triggered camera); False for a source that streams on its own clock, where
            the newest frame is whatever was captured last (its :meth:`read_latest` must
            then only return the frame it holds, without waiting: the remote station reads
            it on its event loop, then pairs it with the command and the arm pose of the
            frame's ``timestamp_us``).
        notifies_frames: a streaming source that calls :meth:`_frame_arrived` for each new
            frame, so a consumer can take it as it arrives (:attr:`on_frame`) rather than on
            a clock of its own.
        on_frame: set by the consumer of a source that notifies: called with no arguments
            from the source's own thread after each new frame (it must be quick and
            thread-safe, e.g. ``loop.call_soon_threadsafe(event.set)``); None: not called.
    """

    captures_on_demand: bool = False
    notifies_frames: bool = False

    def __init__(self, shape_hw: tuple[int, int], mm_per_px: float) -> None:
        super().__init__()
        self.shape_hw = (int(shape_hw[0]), int(shape_hw[1]))
        self.mm_per_px = float(mm_per_px)
        self.on_frame: Callable[[], None] | None = None

    @property
    def newest_seq(self) -> int | None:
        """The ``seq`` of the frame a streaming source holds (None: none yet), without the
        checks of :meth:`read_latest` (for a source that captures on demand this would
        capture)."""
        frame = self._latest()
        return None if frame is None else frame.seq

    def _frame_arrived(self) -> None:
        """For a source that notifies: a new frame is stored. Calls :attr:`on_frame`; its
        failure (a consumer gone) is logged, never raised into the source's thread."""
        callback = self.on_frame
        if callback is None:
            return
        try:
            callback()
        except Exception as err:  # the consumer's problem, not the camera's
            log.debug("%s: on_frame failed: %s", self.name, err)

    def _after_connect(self) -> None:
        log.info("%s: %dx%d frames, %.4f mm/px", self.name, self.shape_hw[1], self.shape_hw[0],
                 self.mm_per_px)

    def read_latest(self, max_age_ms: float = 100.0) -> SensorFrame:
        """Return the newest frame, if it is at most ``max_age_ms`` old.

        Raises:
            DeviceNotConnectedError: called before connect() or after disconnect().
            DeviceTimeoutError: no frame yet, or the newest one is too old.
            DeviceOperationError: the backend delivered a frame of the wrong size or type.
        """
        self._require_connected()
        with self._operation("frame read"):
            frame = self._latest()
        if frame is None:
            raise DeviceTimeoutError(f"{self.name}: no frame captured yet")
        age_ms = (now_us() - frame.timestamp_us) / 1000.0
        if age_ms > max_age_ms:
            raise DeviceTimeoutError(f"{self.name}: newest frame is {age_ms:.0f} ms "
                                     f"old (max {max_age_ms:.0f} ms)")
        rgb = frame.rgb
        if rgb.dtype != np.uint8 or rgb.shape != (*self.shape_hw, 3):
            raise DeviceOperationError(f"{self.name}: frame {rgb.shape} {rgb.dtype}, "
                                       f"expected {(*self.shape_hw, 3)} uint8")
        return frame

    @property
    def health(self) -> SensorHealth:
        """Whether the source still delivers frames (a renderer never ends or stalls)."""
        return SensorHealth()

    @abstractmethod
    def _latest(self) -> SensorFrame | None:
        """The newest captured frame, or None."""
