"""The encoder-board backend: the binary protocol of docs/platform_protocol.md over serial.

The port is opened with :func:`serial.serial_for_url`, so a real board is named by its device
(``/dev/ttyUSB0``, ``COM3``) or a URL (``socket://host:port``, ``rfc2217://...``), and a
simulated one by ``loop://`` or a pty path. A reader thread drains the port, feeds the
resynchronising decoder and publishes samples; a serial error (or an error raised while
handling a sample, e.g. by ``sample_listener``) ends the thread and is reported by the next
``read_state()`` as :class:`~shared.errors.DeviceOperationError`.
"""

from __future__ import annotations

import logging

import serial

from local_site.platform.base import XYZPlatform
from local_site.platform.protocol import BoardInfo, DecoderStats, EncoderFrameDecoder
from local_site.serial_port import SerialPortReader
from shared.timebase import now_us

__all__ = ["SerialEncoderPlatform"]

log = logging.getLogger(__name__)


class SerialEncoderPlatform(XYZPlatform):
    """XYZ platform read from the encoder board over any pyserial URL.

    Args:
        url: device path or pyserial URL.
        baudrate: line rate (921600 carries 1 kHz x 26-byte frames with 2x margin; USB CDC
            boards ignore it).
        port: an already-open pyserial port to use instead of opening ``url`` (for
            ``loop://``, where the simulated board and the driver share one port object).
            A port passed in is not closed by ``disconnect()``.
        read_timeout_s: the reader thread's poll period.
        **kwargs: passed to :class:`~local_site.platform.base.XYZPlatform`.
    """

    def __init__(self, url: str, *, baudrate: int = 921_600,
                 port: serial.SerialBase | None = None, read_timeout_s: float = 0.02,
                 **kwargs: object) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.url = url
        self._decoder = EncoderFrameDecoder()
        self._link = SerialPortReader(url, name=self.name, thread_name=f"platform-rx {url}",
                                      on_data=self._on_data, on_error=self._link_failed,
                                      baudrate=baudrate, timeout_s=read_timeout_s, port=port)

    @property
    def name(self) -> str:
        return f"encoder board at {self.url}"

    def _connect(self) -> None:
        decoder = EncoderFrameDecoder()  # a new connection starts at a frame boundary
        decoder.stats = self._decoder.stats  # the counters are totals over all connections
        self._decoder = decoder
        self._link.open(self.url, self.name)

    def _disconnect(self) -> None:
        self._link.close()

    def _decoder_stats(self) -> DecoderStats:
        return self._decoder.stats

    def _silence_hint(self) -> str:
        return self._link.silence_hint()

    def _on_data(self, data: bytes) -> None:
        rx_us = now_us()
        for frame in self._decoder.feed(data):
            if isinstance(frame, BoardInfo):
                self._publish_info(frame)
            else:
                self._publish(frame, rx_us)
