"""The serial backend: the same ArrayTac payloads, COBS-framed, over any pyserial URL.

For boards reached over USB CDC / UART instead of CAN FD (``/dev/ttyACM0``,
``socket://host:port``, a pty of the simulator). Framing: :mod:`local_site.display.serial_framing`.
"""

from __future__ import annotations

import logging
from typing import Any

from local_site.display.base import ArrayTacDisplay
from local_site.display.serial_framing import LinkFrameDecoder, encode_link_frame
from local_site.serial_port import SerialPortReader

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
        self.decoder = LinkFrameDecoder()
        self._link = SerialPortReader(url, name=self.name, thread_name=f"arraytac-rx {url}",
                                      on_data=self._on_data, on_error=self._on_read_error,
                                      baudrate=baudrate, timeout_s=0.05,
                                      write_timeout_s=write_timeout_s, on_poll=self._note_poll)

    @property
    def name(self) -> str:
        return f"ArrayTac on serial {self.url}"

    def _connect(self) -> None:
        self.decoder = LinkFrameDecoder()
        self._link.open(self.url, self.name)

    def _disconnect(self) -> None:
        self._link.close()

    def _send_frame(self, arb_id: int, payload: bytes) -> None:
        self._link.write(encode_link_frame(arb_id, payload))

    def _on_data(self, data: bytes) -> None:
        for arb_id, payload in self.decoder.feed(data):
            self._on_frame(arb_id, payload)

    def _on_read_error(self, err: BaseException) -> None:
        # the reader thread ends after this: the link counts as broken until reopened
        self._on_link_error(err)
