"""The CAN FD backend: ArrayTac frames through any python-can interface.

``CanArrayTacDisplay(channel="can0", interface="socketcan")`` in the field,
``interface="virtual"`` in tests and for the simulator. Frames are CAN FD, standard 11-bit
IDs, bit-rate switching on; a reader thread receives feedback (filtered to its ID). A receive
error ends that thread and marks the link broken (:meth:`ArrayTacDisplay._on_link_error`):
the next send raises, and ``connect()`` reopens the bus.
"""

from __future__ import annotations

import logging
from typing import Any

import can

from local_site.display import frames as fr
from local_site.display.base import ArrayTacDisplay
from shared.devices import ReaderThread
from shared.errors import DeviceInitError, DeviceOperationError

__all__ = ["CanArrayTacDisplay"]

log = logging.getLogger(__name__)


class CanArrayTacDisplay(ArrayTacDisplay):
    """ArrayTac drive board on a CAN FD bus.

    Args:
        channel: python-can channel (``can0``, a virtual channel name, ...).
        interface: python-can interface name (``socketcan``, ``pcan``, ``virtual``, ...).
        bitrate: nominal bit rate (ignored by ``virtual``/``socketcan``, which take it from
            the OS).
        data_bitrate: CAN FD data-phase bit rate.
        send_timeout_s: how long ``bus.send`` may block.
        bus_options: extra keyword arguments for :class:`can.Bus`.
        **kwargs: passed to :class:`ArrayTacDisplay`.
    """

    def __init__(self, channel: str = "can0", *, interface: str = "socketcan",
                 bitrate: int = 1_000_000, data_bitrate: int = 5_000_000,
                 send_timeout_s: float = 0.01, bus_options: dict[str, Any] | None = None,
                 **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.channel = channel
        self.interface = interface
        self._bus_options = {"bitrate": bitrate, "data_bitrate": data_bitrate,
                             **(bus_options or {})}
        if interface in ("virtual", "socketcan"):
            self._bus_options.pop("bitrate")
            self._bus_options.pop("data_bitrate")
        self._send_timeout_s = send_timeout_s
        self._bus: can.BusABC | None = None
        self._reader: ReaderThread | None = None

    @property
    def name(self) -> str:
        return f"ArrayTac on {self.interface}:{self.channel}"

    def _connect(self) -> None:
        try:
            self._bus = can.Bus(interface=self.interface, channel=self.channel, fd=True,
                                can_filters=[{"can_id": fr.ARB_ID_FEEDBACK, "can_mask": 0x7FF,
                                              "extended": False}],
                                **self._bus_options)
        except (can.CanError, OSError, ValueError, ImportError) as err:
            raise DeviceInitError(f"{self.name}: cannot open the CAN bus: {err}") from err
        bus = self._bus
        reader = ReaderThread(f"arraytac-rx {self.channel}",
                              lambda: self._receive_once(bus, reader))
        self._reader = reader
        reader.start()

    def _disconnect(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.stop(timeout_s=2.0)
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def _send_frame(self, arb_id: int, payload: bytes) -> None:
        bus = self._bus
        if bus is None:
            raise DeviceOperationError(f"{self.name}: bus is closed")
        msg = can.Message(arbitration_id=arb_id, data=payload, is_extended_id=False,
                          is_fd=True, bitrate_switch=True)
        try:
            bus.send(msg, timeout=self._send_timeout_s)
        except can.CanError as err:
            raise DeviceOperationError(f"{self.name}: send of ID 0x{arb_id:03x} failed: "
                                       f"{err}") from err

    def _receive_once(self, bus: can.BusABC, reader: ReaderThread) -> bool:
        try:
            msg = bus.recv(timeout=0.05)
        except can.CanError as err:
            # the thread ends: recorded, so the display reports a broken link (its sends
            # raise, connect() reopens the bus with a new reader) instead of living on deaf
            if not reader.stopping:
                self._on_link_error(err)
            return False
        if msg is not None and not msg.is_error_frame:
            self._on_frame(msg.arbitration_id, bytes(msg.data))
        self._note_poll()  # the reader runs (silence is judged on its polls), after the frame
        return True
