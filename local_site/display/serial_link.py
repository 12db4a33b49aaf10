"""The serial backend: the same ArrayTac payloads, COBS-framed, over any pyserial URL.

For boards reached over USB CDC / UART instead of CAN FD (``/dev/ttyACM0``,
``socket://host:port``, a pty of the simulator). Framing: :mod:`local_site.display.serial_framing`.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from typing import Any

import serial

from local_site.display.base import ArrayTacDisplay
from local_site.display.serial_framing import LinkFrameDecoder, encode_link_frame
from shared.errors import DeviceInitError, DeviceOperationError

__all__ = ["SerialArrayTacDisplay"]

log = logging.getLogger(__name__)


class SerialArrayTacDisplay(ArrayTacDisplay):
    """ArrayTac drive board on a serial link.

    Args:
        url: device path or pyserial URL.
        baudrate: line rate (2 Mbaud carries 1 kHz x 68-byte frames with 3x margin).
        write_timeout_s: how long a write may block.
        **kwargs: passed to :class:`ArrayTacDisplay`.
    """

    def __init__(self, url: str, *, baudrate: int = 2_000_000, write_timeout_s: float = 0.05,
                 **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.url = url
        self._baudrate = baudrate
        self._write_timeout_s = write_timeout_s
        self._port: serial.SerialBase | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.decoder = LinkFrameDecoder()

    @property
    def name(self) -> str:
        return f"ArrayTac on serial {self.url}"

    def _open(self) -> None:
        try:
            self._port = serial.serial_for_url(self.url, baudrate=self._baudrate, timeout=0.05,
                                               write_timeout=self._write_timeout_s)
        except (serial.SerialException, OSError, ValueError) as err:
            raise DeviceInitError(f"{self.name}: cannot open: {err}") from err
        self.decoder = LinkFrameDecoder()
        self._stop.clear()
        self._thread = threading.Thread(target=self._reader, name=f"arraytac-rx {self.url}",
                                        daemon=True)
        self._thread.start()

    def _close(self) -> None:
        self._stop.set()
        port, self._port = self._port, None
        thread, self._thread = self._thread, None
        if port is not None and hasattr(port, "cancel_read"):
            with contextlib.suppress(serial.SerialException, OSError):
                port.cancel_read()
        if thread is not None:
            thread.join(timeout=2.0)
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                log.debug("closing %s failed", self.url, exc_info=True)

    def _send_frame(self, arb_id: int, payload: bytes) -> None:
        port = self._port
        if port is None:
            raise DeviceOperationError(f"{self.name}: port is closed")
        try:
            port.write(encode_link_frame(arb_id, payload))
        except (serial.SerialException, OSError) as err:
            raise DeviceOperationError(f"{self.name}: write failed: {err}") from err

    def _reader(self) -> None:
        port = self._port
        while port is not None and not self._stop.is_set():
            try:
                waiting = port.in_waiting
                data = port.read(waiting if waiting else 1)
            except (serial.SerialException, OSError, TypeError, AttributeError) as err:
                if not self._stop.is_set():
                    log.warning("%s: read failed: %s", self.name, err)
                return
            for arb_id, payload in self.decoder.feed(data) if data else ():
                self._on_frame(arb_id, payload)
