"""A pyserial port with its reader thread: the part every serial device driver shares.

The platform's encoder board and the ArrayTac serial link both open a port by URL
(``serial.serial_for_url``: a device, ``loop://``, ``socket://``, a pty), read it from a
daemon thread (:class:`~shared.devices.reader.ReaderThread`) that hands every chunk to a
callback, and close it so that a blocked read
returns at once. Only their byte protocols differ, and those stay in the drivers.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable

import serial

from shared.devices import ReaderThread
from shared.errors import DeviceInitError, DeviceOperationError

__all__ = ["SerialPortReader"]

log = logging.getLogger(__name__)

#: what pyserial may raise while a port is read or closed concurrently
_READ_ERRORS = (serial.SerialException, OSError, TypeError, AttributeError)


class SerialPortReader:
    """Open a serial URL and feed what arrives to ``on_data`` from a daemon thread.

    Args:
        url: pyserial URL or device.
        name: the device's name for messages.
        thread_name: the reader thread's name.
        on_data: called from the reader thread with every non-empty chunk.
        on_error: called from the reader thread when a read fails (not after close()).
        baudrate: line speed.
        timeout_s: read timeout (how often the thread checks for close()).
        write_timeout_s: write timeout, or None to block.
        port: an already-open port to use instead of opening ``url``; it is not closed.
    """

    def __init__(self, url: str, *, name: str, thread_name: str,
                 on_data: Callable[[bytes], None], on_error: Callable[[BaseException], None],
                 baudrate: int = 921_600, timeout_s: float = 0.05,
                 write_timeout_s: float | None = None,
                 port: serial.SerialBase | None = None) -> None:
        self.url = url
        self.name = name
        self._thread_name = thread_name
        self._on_data = on_data
        self._on_error = on_error
        self._baudrate = baudrate
        self._timeout_s = timeout_s
        self._write_timeout_s = write_timeout_s
        self._given_port = port
        self._port: serial.SerialBase | None = None
        self._reader: ReaderThread | None = None

    @property
    def is_open(self) -> bool:
        """True between open() and close()."""
        return self._port is not None

    def open(self, url: str | None = None, name: str | None = None) -> None:
        """Open the port and start the reader thread.

        Args:
            url: open this URL instead of the one given at construction (a simulated
                device learns its pty path only when it opens).
            name: the device's name for messages, if it changed with the URL.

        Raises:
            DeviceInitError: the URL cannot be opened.
        """
        self.url = url or self.url
        self.name = name or self.name
        if self._given_port is not None:
            port = self._given_port
        else:
            try:
                port = serial.serial_for_url(self.url, baudrate=self._baudrate,
                                             timeout=self._timeout_s,
                                             write_timeout=self._write_timeout_s)
            except (serial.SerialException, OSError, ValueError) as err:
                raise DeviceInitError(f"{self.name}: cannot open: {err}") from err
        port.timeout = self._timeout_s
        self._port = port
        reader = ReaderThread(self._thread_name, lambda: self._read_once(port, reader))
        self._reader = reader
        reader.start()

    def close(self) -> None:
        """Stop the reader thread and close the port (a given port is left open)."""
        port, self._port = self._port, None
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.request_stop()
        if port is not None and hasattr(port, "cancel_read"):
            with contextlib.suppress(serial.SerialException, OSError):
                port.cancel_read()
        if reader is not None:
            reader.join(timeout_s=2.0)
        if port is not None and port is not self._given_port:
            try:
                port.close()
            except (serial.SerialException, OSError):
                log.debug("closing %s failed", self.url, exc_info=True)

    def write(self, data: bytes) -> None:
        """Write bytes to the port.

        Raises:
            DeviceOperationError: the port is closed or the write failed.
        """
        port = self._port
        if port is None:
            raise DeviceOperationError(f"{self.name}: port is closed")
        try:
            port.write(data)
        except (serial.SerialException, OSError) as err:
            raise DeviceOperationError(f"{self.name}: write failed: {err}") from err

    def _read_once(self, port: serial.SerialBase, reader: ReaderThread) -> bool:
        try:
            waiting = port.in_waiting
            data = port.read(waiting if waiting else 1)
        except _READ_ERRORS as err:  # Type/AttributeError: pyserial after a close
            if not reader.stopping:
                self._on_error(err)
            return False
        if data:
            self._on_data(data)
        return True
