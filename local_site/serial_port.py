"""A pyserial port with its reader thread: the part every serial device driver shares.

The platform's encoder board and the ArrayTac serial link both open a port by URL
(``serial.serial_for_url``: a device, ``loop://``, ``socket://``, a pty), read it from a
daemon thread (:class:`~shared.devices.reader.ReaderThread`) that hands every chunk to a
callback, and close it so that a blocked read
returns at once. Only their byte protocols differ, and those stay in the drivers.

Writes: pyserial 3.5's ``write`` on a device/pty and on ``socket://`` checks its write
timeout *after* a send that already put every byte out, so a writer descheduled for longer
than the timeout (a loaded machine) gets ``SerialTimeoutException('Write timeout')`` for a
frame that went out: the caller would treat a sent command as unsent. Those two backends are
written here on their non-blocking descriptor instead: bytes the kernel took count as
sent, and only bytes it would not take within the timeout make the write fail
(:func:`_write_all`). Other ports (``loop://``, ``spy://``, ...) keep pyserial's own write.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import queue
import select
from collections.abc import Callable

import serial
from serial.urlhandler import protocol_socket

from shared.devices import ReaderThread
from shared.errors import DeviceInitError, DeviceOperationError
from shared.timebase import monotonic_s

__all__ = ["SerialPortReader"]

log = logging.getLogger(__name__)

#: what pyserial (or the descriptor read) may raise while a port is read or closed concurrently
_READ_ERRORS = (serial.SerialException, OSError, TypeError, AttributeError, ValueError)
#: pyserial writes that loop over a non-blocking descriptor and raise a write timeout even
#: after a send that put everything out (pyserial 3.5: ``serialposix.Serial.write`` and
#: ``protocol_socket.Serial.write``); a port whose class overrides them (``spy://``) is
#: left to its own write
_DESCRIPTOR_WRITES = (serial.Serial.write, protocol_socket.Serial.write)
#: what pyserial may raise from a write: loop:// lets ``queue.Full`` out of a full buffer
_WRITE_ERRORS = (serial.SerialException, OSError, queue.Full)
#: the read of pyserial's POSIX port (device, pty): :func:`_read_available` does the same on
#: its descriptor, in one wake-up per burst (None where that module does not exist)
try:
    from serial import serialposix as _serialposix
    _POSIX_READ = _serialposix.Serial.read
except ImportError:  # pragma: no cover - not POSIX
    _POSIX_READ = None
#: the read of pyserial's ``socket://`` port: read here on its socket's descriptor too (POSIX
#: only, where a socket is a descriptor ``os.read`` takes)
_SOCKET_READ = protocol_socket.Serial.read
#: errors of a non-blocking read that mean "nothing yet", as pyserial treats them
_RETRY_ERRNOS = (errno.EAGAIN, errno.EALREADY, errno.EWOULDBLOCK, errno.EINPROGRESS,
                 errno.EINTR)
_READ_CHUNK_BYTES = 4096


def _read_available(port: serial.SerialBase) -> bytes | None:
    """Wait up to the port's timeout for data and return every byte there (one wake-up).

    pyserial's ``read(n)`` returns after ``n`` bytes or its timeout: ``read(1)`` wakes the
    reader for the first byte of a frame and again for the rest, and a larger ``n`` would
    hold a frame back until the timeout. On a POSIX device or pty this does what pyserial's
    read does (select on the descriptor and on its cancel pipe, then read), and on
    ``socket://`` what its read does (select on the socket, then read), but returns
    whatever the kernel holds as soon as anything arrived. Returns None when the port's
    read is neither (the caller uses ``read`` then).

    Raises:
        serial.SerialException: the read failed or the device is gone (ready, no data).
    """
    read = type(port).read
    if _POSIX_READ is None or read not in (_POSIX_READ, _SOCKET_READ):
        return None
    if not port.is_open:
        raise serial.PortNotOpenError()
    try:
        if read is _SOCKET_READ:
            # socket://: pyserial's in_waiting says 1 whenever anything is there, and
            # read(1) then takes one byte per select and recv: a 68-byte board frame cost
            # 68 wake-ups of this loop. Its socket is non-blocking; close() shuts it down,
            # which wakes the select (EOF below).
            fd = port.fileno()
            ready, _, _ = select.select([fd], [], [], port.timeout)
        else:
            fd, abort = port.fd, port.pipe_abort_read_r
            ready, _, _ = select.select([fd, abort], [], [], port.timeout)
            if abort in ready:
                os.read(abort, 1000)
                return b""
        if not ready:
            return b""
        data = os.read(fd, _READ_CHUNK_BYTES)
    except OSError as err:
        if err.errno in _RETRY_ERRNOS:
            return b""
        raise serial.SerialException(f"read failed: {err}") from err
    if not data:
        # as pyserial: a disconnected device is ready to read but returns nothing
        if read is _SOCKET_READ:
            raise serial.SerialException("socket disconnected (the peer closed the connection)")
        raise serial.SerialException("device reports readiness to read but returned no data "
                                     "(device disconnected or multiple access on port?)")
    return data


def _descriptor(port: serial.SerialBase) -> int | None:
    """The port's non-blocking descriptor when its write is one of pyserial's descriptor
    writes (device, pty, ``socket://``), else None."""
    if type(port).write not in _DESCRIPTOR_WRITES:
        return None
    try:
        fd = port.fileno()
        if not isinstance(fd, int) or os.get_blocking(fd):
            return None  # a blocking descriptor (VTIMESerial) would block in os.write
    except (serial.SerialException, OSError, AttributeError):
        return None  # closed: pyserial's own write says so
    return fd


def _write_all(port: serial.SerialBase, data: bytes, timeout_s: float | None) -> int:
    """Write ``data`` to ``port``; return how many bytes went out (all, unless timed out).

    On a device, pty or ``socket://`` port the bytes are written on its non-blocking
    descriptor: every byte the kernel accepted counts as sent, however late this thread
    gets to look at the clock again. The write stops short only when the kernel would not
    take the rest within ``timeout_s`` (a peer that stopped reading, a full buffer); one
    more non-blocking attempt is made at the deadline, so the call returns within
    ``timeout_s`` plus one system call. Other ports use pyserial's ``write``.

    Args:
        port: an open pyserial port.
        data: the bytes.
        timeout_s: how long the write may wait for the port to take bytes (None: forever).

    Raises:
        serial.SerialException | OSError | queue.Full: the write failed.
    """
    fd = _descriptor(port)
    if fd is None:
        port.write(data)  # raises SerialTimeoutException when it took too long
        return len(data)
    view = memoryview(data)
    written = 0
    deadline = math.inf if timeout_s is None else monotonic_s() + timeout_s
    poller: select.poll | None = None
    while True:
        with contextlib.suppress(BlockingIOError):
            written += os.write(fd, view[written:])
        if written == len(data):
            return written
        left_s = deadline - monotonic_s()
        if left_s <= 0:
            return written
        if poller is None:
            poller = select.poll()
            poller.register(fd, select.POLLOUT)
        poller.poll(-1 if math.isinf(left_s) else math.ceil(left_s * 1e3))


class SerialPortReader:
    """Open a serial URL and feed what arrives to ``on_data`` from a daemon thread.

    Args:
        url: pyserial URL or device.
        name: the device's name for messages.
        thread_name: the reader thread's name.
        on_data: called from the reader thread with every non-empty chunk.
        on_error: called from the reader thread when a read fails (not after close()), or
            with a :class:`~shared.errors.DeviceOperationError` when ``on_data`` raised; the
            thread ends then (reopen the port to read on).
        baudrate: line speed.
        timeout_s: read timeout (how often the thread checks for close()).
        write_timeout_s: write timeout, or None to block.
        port: an already-open port to use instead of opening ``url``; it is not closed.
        on_poll: called from the reader thread each time a read of the port comes back
            (with or without data), before ``on_data``: the reader runs.
    """

    def __init__(self, url: str, *, name: str, thread_name: str,
                 on_data: Callable[[bytes], None], on_error: Callable[[BaseException], None],
                 baudrate: int = 921_600, timeout_s: float = 0.05,
                 write_timeout_s: float | None = None,
                 port: serial.SerialBase | None = None,
                 on_poll: Callable[[], None] | None = None) -> None:
        self.url = url
        self.name = name
        self._thread_name = thread_name
        self._on_data = on_data
        self._on_error = on_error
        self._on_poll = on_poll
        self._baudrate = baudrate
        self._timeout_s = timeout_s
        self._write_timeout_s = write_timeout_s
        self._given_port = port
        self._port: serial.SerialBase | None = None
        self._reader: ReaderThread | None = None
        #: when the reader thread last came back from a read of the port (monotonic s; with
        #: or without data: it reads with ``timeout_s``), None before the first
        self.last_read_s: float | None = None

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
            # loop:// wakes its reader with a queue item: Full when its buffer is full (the
            # reader then sees the stop request after its next read)
            with contextlib.suppress(*_WRITE_ERRORS):
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
            written = _write_all(port, data, self._write_timeout_s)
        except _WRITE_ERRORS as err:
            raise DeviceOperationError(f"{self.name}: write failed: {err}") from err
        if written < len(data):
            raise DeviceOperationError(
                f"{self.name}: write timed out: {written} of {len(data)} bytes went out in "
                f"{(self._write_timeout_s or 0.0) * 1e3:.0f} ms (the other end does not "
                "take them)")

    def _read_once(self, port: serial.SerialBase, reader: ReaderThread) -> bool:
        try:
            data = _read_available(port)
            if data is None:
                waiting = port.in_waiting
                data = port.read(waiting if waiting else 1)
        except _READ_ERRORS as err:  # Type/AttributeError: pyserial after a close
            if not reader.stopping:
                self._on_error(err)
            return False
        self.last_read_s = monotonic_s()
        if data:
            try:
                self._on_data(data)
            except Exception as err:  # a bug in a callback must not end the thread unseen
                log.error("%s: handling received bytes failed", self.name, exc_info=True)
                failure = DeviceOperationError(
                    f"{self.name}: handling received bytes failed: {type(err).__name__}: {err}")
                failure.__cause__ = err
                if not reader.stopping:
                    self._on_error(failure)
                return False
        # after the bytes were handled: noted before, a backlog's feedback read after a stall
        # looked older than the poll for a moment, a silent board to a busy sender (review)
        if self._on_poll is not None:
            self._on_poll()
        return True

    def silence_hint(self) -> str:
        """Why a silent port is silent, as far as this side can tell (for error messages):
        whether the reader thread has been reading (the device sent nothing) or has not
        run for a while (a busy host starved it)."""
        last = self.last_read_s
        if last is None:
            return ""
        ago_ms = (monotonic_s() - last) * 1e3
        if ago_ms <= 5.0 * self._timeout_s * 1e3 + 50.0:
            return (f"; the reader thread read the port {ago_ms:.0f} ms ago (the device sent "
                    "nothing)")
        return (f"; the reader thread has not run for {ago_ms:.0f} ms (a busy host starved it, "
                "or it is stuck)")
