"""The encoder-board backend: the binary protocol of docs/platform_protocol.md over serial.

The port is opened with :func:`serial.serial_for_url`, so a real board is named by its device
(``/dev/ttyUSB0``, ``COM3``) or a URL (``socket://host:port``, ``rfc2217://...``), and a
simulated one by ``loop://`` or a pty path. A reader thread drains the port, feeds the
resynchronising decoder and publishes samples; a serial error ends the thread and is
reported by the next ``read_state()`` as :class:`~shared.errors.DeviceOperationError`.
"""

from __future__ import annotations

import contextlib
import logging
import threading

import serial

from local_site.platform.base import XYZPlatform
from local_site.platform.protocol import BoardInfo, DecoderStats, EncoderFrameDecoder
from shared.errors import DeviceInitError
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
        self._baudrate = baudrate
        self._given_port = port
        self._read_timeout_s = read_timeout_s
        self._port: serial.SerialBase | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._decoder = EncoderFrameDecoder()

    @property
    def name(self) -> str:
        return f"encoder board at {self.url}"

    def _open(self) -> None:
        self._decoder = EncoderFrameDecoder()
        if self._given_port is not None:
            self._port = self._given_port
        else:
            try:
                self._port = serial.serial_for_url(self.url, baudrate=self._baudrate,
                                                   timeout=self._read_timeout_s)
            except (serial.SerialException, OSError, ValueError) as err:
                raise DeviceInitError(f"{self.name}: cannot open: {err}") from err
        self._port.timeout = self._read_timeout_s
        self._stop.clear()
        self._thread = threading.Thread(target=self._reader, name=f"platform-rx {self.url}",
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
        if port is not None and port is not self._given_port:
            try:
                port.close()
            except (serial.SerialException, OSError):
                log.debug("closing %s failed", self.url, exc_info=True)

    def _decoder_stats(self) -> DecoderStats:
        return self._decoder.stats

    def _reader(self) -> None:
        port = self._port
        if port is None:
            return
        decoder = self._decoder
        while not self._stop.is_set():
            try:
                waiting = port.in_waiting
                data = port.read(waiting if waiting else 1)
            except (serial.SerialException, OSError, TypeError, AttributeError) as err:
                # TypeError/AttributeError: pyserial internals after a concurrent close
                if not self._stop.is_set():
                    self._link_failed(err)
                return
            if not data:
                continue
            rx_us = now_us()
            for frame in decoder.feed(data):
                if isinstance(frame, BoardInfo):
                    self._publish_info(frame)
                else:
                    self._publish(frame, rx_us)
