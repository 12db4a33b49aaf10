"""Writes through :class:`local_site.serial_port.SerialPortReader` (issue 11).

pyserial 3.5's ``write`` on ``socket://`` and on a device or pty checks its write timeout
*after* a send that already put every byte out, so a writer descheduled past the timeout
gets ``SerialTimeoutException`` for bytes that went out. The wrapper must count such a write
as sent, and still fail a write the other end truly does not take, within the timeout.

Descheduling is made deterministic, not left to load: the write system call is wrapped so
that the thread sleeps well past the write timeout right *after* the kernel took the bytes,
which is exactly what a preempted writer sees.
"""

from __future__ import annotations

import contextlib
import os
import re
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import serial

from local_site.display import frames as fr
from local_site.display.serial_framing import LinkFrameDecoder, encode_link_frame
from local_site.display.serial_link import SerialArrayTacDisplay
from local_site.serial_port import SerialPortReader
from shared.errors import CommandExpiredError, DeviceOperationError
from shared.timebase import monotonic_s
from tests.support import scaled, wait_until

WRITE_TIMEOUT_S = 0.02
#: how long the "descheduled" writer sleeps after its send: far past the write timeout
DESCHEDULED_S = 0.15
FRAME = encode_link_frame(fr.ARB_ID_COMMAND, bytes(range(1, 60)))


class _Peer:
    """The other end of a port: ``url`` to open, ``recv()`` what arrived since last time."""

    url: str

    def recv(self) -> bytes:
        raise NotImplementedError

    def received(self, n: int) -> bytes:
        """Wait for ``n`` bytes and return them."""
        got = bytearray()

        def enough() -> bool:
            got.extend(self.recv())
            return len(got) >= n

        wait_until(enough, 2.0, f"{n} bytes at the peer")
        return bytes(got)


class _TcpPeer(_Peer):
    """A TCP server on 127.0.0.1 with a small receive buffer; accepts on first use."""

    def __init__(self) -> None:
        self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        self.server.bind(("127.0.0.1", 0))
        self.server.listen(1)
        self.conn: socket.socket | None = None
        host, port = self.server.getsockname()
        self.url = f"socket://{host}:{port}"

    def accept(self) -> socket.socket:
        if self.conn is None:
            self.server.settimeout(scaled(2.0))
            self.conn, _ = self.server.accept()
            self.conn.setblocking(False)
        return self.conn

    def recv(self) -> bytes:
        try:
            return self.accept().recv(65536)
        except BlockingIOError:
            return b""

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
        self.server.close()


class _PtyPeer(_Peer):
    """A pseudo-terminal: the port opens the slave's path, the test holds the master."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        os.set_blocking(self.master, False)
        self.url = os.ttyname(self.slave)

    def recv(self) -> bytes:
        try:
            return os.read(self.master, 65536)
        except BlockingIOError:
            return b""

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture(params=["socket", "pty"])
def peer(request: pytest.FixtureRequest) -> Iterator[_TcpPeer | _PtyPeer]:
    p: _TcpPeer | _PtyPeer = _TcpPeer() if request.param == "socket" else _PtyPeer()
    yield p
    p.close()


def _open_port(url: str) -> serial.SerialBase:
    return serial.serial_for_url(url, baudrate=2_000_000, timeout=0.05,
                                 write_timeout=WRITE_TIMEOUT_S)


@contextlib.contextmanager
def _link(peer: _TcpPeer | _PtyPeer, write_timeout_s: float | None = WRITE_TIMEOUT_S) \
        -> Iterator[SerialPortReader]:
    link = SerialPortReader(peer.url, name="test link", thread_name="test-rx",
                            on_data=lambda data: None, on_error=lambda err: None,
                            baudrate=2_000_000, write_timeout_s=write_timeout_s)
    link.open()
    try:
        if isinstance(peer, _TcpPeer):
            peer.accept()
        yield link
    finally:
        link.close()


def _port_fd(link: SerialPortReader) -> int:
    port = link._port
    assert port is not None
    return int(port.fileno())


@pytest.fixture
def deschedule_after_write(monkeypatch: pytest.MonkeyPatch) -> Callable[[int], list[int]]:
    """``deschedule_after_write(fd)``: every ``os.write`` on ``fd`` sleeps DESCHEDULED_S
    after the kernel took its bytes; returns the list of byte counts written on ``fd``."""
    real_write = os.write

    def install(fd: int) -> list[int]:
        counts: list[int] = []

        def write(target: int, data: Any) -> int:
            n = real_write(target, data)
            if target == fd:
                counts.append(n)
                time.sleep(DESCHEDULED_S)
            return n

        monkeypatch.setattr(os, "write", write)
        return counts

    return install


class _SendThenSleep:
    """pyserial's socket, whose ``send`` sleeps DESCHEDULED_S after the kernel took the bytes."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock

    def send(self, data: bytes) -> int:
        n = self._sock.send(data)
        time.sleep(DESCHEDULED_S)
        return n

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)


# ---------------------------------------------------------------------- the flaw itself


def test_pyserial_reports_a_write_timeout_for_a_frame_that_went_out(
        peer: _TcpPeer | _PtyPeer, deschedule_after_write: Callable[[int], list[int]],
        monkeypatch: pytest.MonkeyPatch) -> None:
    # why the wrapper exists: if pyserial stops doing this, the wrapper can go
    port = _open_port(peer.url)
    try:
        if isinstance(peer, _TcpPeer):
            peer.accept()
            monkeypatch.setattr(port, "_socket", _SendThenSleep(port._socket))
        else:
            deschedule_after_write(port.fileno())
        with pytest.raises(serial.SerialTimeoutException, match="Write timeout"):
            port.write(FRAME)
        assert peer.received(len(FRAME)) == FRAME, "the 'timed out' frame went out whole"
    finally:
        port.close()


# ---------------------------------------------------------------------- the fix


def test_a_write_descheduled_past_its_timeout_after_the_bytes_went_out_counts_as_sent(
        peer: _TcpPeer | _PtyPeer, deschedule_after_write: Callable[[int], list[int]]) -> None:
    with _link(peer) as link:
        writes = deschedule_after_write(_port_fd(link))
        t0 = monotonic_s()
        link.write(FRAME)  # no error: every byte went out
        assert monotonic_s() - t0 >= DESCHEDULED_S > WRITE_TIMEOUT_S, "not descheduled"
        assert writes == [len(FRAME)]
        link.write(FRAME)
        assert peer.received(2 * len(FRAME)) == 2 * FRAME


def test_a_write_the_other_end_does_not_take_fails_within_the_timeout(
        peer: _TcpPeer | _PtyPeer) -> None:
    # nobody reads the peer: the kernel buffers fill, then the write must give up, saying
    # how much went out, within the timeout (plus scheduling slack), never block for good
    block = bytes(range(1, 256)) * 4096  # 1 MB: more than a small socket's or pty's buffers
    with _link(peer, write_timeout_s=0.05) as link:
        if isinstance(peer, _TcpPeer):
            # a small send buffer (an explicit size also stops Linux from growing it)
            with socket.fromfd(_port_fd(link), socket.AF_INET, socket.SOCK_STREAM) as dup:
                dup.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        t0 = monotonic_s()
        with pytest.raises(DeviceOperationError,
                           match=r"test link: write timed out: \d+ of 1044480 bytes went out "
                                 r"in 50 ms") as err:
            link.write(block)
        elapsed_s = monotonic_s() - t0
        assert elapsed_s >= 0.05, "gave up before the timeout"
        assert elapsed_s < 0.05 + scaled(1.0), f"took {elapsed_s:.3f} s"
        match = re.search(r"(\d+) of", str(err.value))
        assert match is not None
        written = int(match.group(1))
        assert 0 < written < len(block)
        # a small frame into the full buffer fails the same way: none of it went out
        with pytest.raises(DeviceOperationError, match=r"0 of \d+ bytes went out"):
            link.write(FRAME)


def test_a_write_to_a_peer_that_closed_is_a_clear_error() -> None:
    peer = _TcpPeer()
    try:
        with _link(peer) as link:
            assert peer.conn is not None
            peer.conn.close()

            def fails() -> bool:
                try:
                    link.write(FRAME)
                except DeviceOperationError as err:
                    assert "test link: write failed" in str(err)
                    return True
                return False

            wait_until(fails, 2.0, "a write to the closed peer to fail")
    finally:
        peer.close()


def test_a_write_on_a_closed_link_is_a_clear_error(peer: _TcpPeer | _PtyPeer) -> None:
    with _link(peer) as link:
        pass
    with pytest.raises(DeviceOperationError, match="test link: port is closed"):
        link.write(FRAME)


def test_loop_port_keeps_pyserials_write_and_a_full_buffer_is_a_clear_error() -> None:
    received = bytearray()
    release = threading.Event()

    def on_data(data: bytes) -> None:
        received.extend(data)
        release.wait()  # stalls the reader thread: nothing drains the loop's buffer

    link = SerialPortReader("loop://", name="loop link", thread_name="loop-rx",
                            on_data=on_data, on_error=lambda err: None, baudrate=2_000_000,
                            write_timeout_s=WRITE_TIMEOUT_S)
    link.open()
    try:
        link.write(FRAME)
        wait_until(lambda: received, 2.0, "the frame to loop back")
        assert FRAME.startswith(received)  # the reader thread now waits in on_data
        # pyserial's loop:// lets queue.Full out of a full buffer: it becomes our error
        with pytest.raises(DeviceOperationError, match="loop link: write failed"):
            for _ in range(200):  # 200 frames > the loop's 4096-byte buffer
                link.write(FRAME)
    finally:
        release.set()
        link.close()


# ---------------------------------------------------------------------- through the display


def _pins(h_mm: float) -> np.ndarray:
    return np.full(16, h_mm)


def test_display_counts_a_descheduled_command_sent_and_still_refuses_an_expired_one(
        peer: _TcpPeer | _PtyPeer, deschedule_after_write: Callable[[int], list[int]]) -> None:
    display = SerialArrayTacDisplay(peer.url, write_timeout_s=WRITE_TIMEOUT_S,
                                    require_feedback=False, disconnect_mode=None)
    try:
        display.connect()
        if isinstance(peer, _TcpPeer):
            peer.accept()
        writes = deschedule_after_write(_port_fd(display._link))
        applied = display.send_command(_pins(1.0), not_after_s=monotonic_s() + 10.0)
        assert applied.sent and applied.seq == 1
        # the deadline is checked before the bytes are written: an expired command is
        # refused and nothing goes out
        with pytest.raises(CommandExpiredError, match="past its deadline; not sent"):
            display.send_command(_pins(2.0), not_after_s=monotonic_s() - 0.001)
        assert len(writes) == 1
        decoder = LinkFrameDecoder()
        frames: list[tuple[int, bytes]] = []

        def one_frame() -> bool:
            frames.extend(decoder.feed(peer.recv()))
            return len(frames) >= 1

        wait_until(one_frame, 2.0, "the command at the board")
        arb_id, payload = frames[0]
        assert arb_id == fr.ARB_ID_COMMAND
        assert fr.decode_command(payload).seq == 1
    finally:
        display.disconnect()


def test_display_on_a_peer_that_stopped_reading_fails_within_the_timeout_and_still_closes(
        peer: _TcpPeer | _PtyPeer) -> None:
    # the safe behaviour of a stuck link: the command fails with a clear error within the
    # write timeout (the display loop then reopens the display, the board's own watchdog
    # parks the pins), and disconnect's best-effort safe state does not hang either
    timeout_s = 0.05
    display = SerialArrayTacDisplay(peer.url, write_timeout_s=timeout_s,
                                    require_feedback=False, disconnect_mode="flat")
    display.connect()
    try:
        if isinstance(peer, _TcpPeer):
            peer.accept()
            with socket.fromfd(_port_fd(display._link), socket.AF_INET,
                               socket.SOCK_STREAM) as dup:
                dup.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        with pytest.raises(DeviceOperationError,
                           match=r"ArrayTac on serial .*: write timed out: \d+ of \d+ bytes"):
            for i in range(100_000):  # ~6.8 MB of commands: far more than any buffer
                t0 = monotonic_s()
                display.send_command(_pins(1.0 + (i % 2)))
        assert monotonic_s() - t0 < timeout_s + scaled(1.0)
    finally:
        t0 = monotonic_s()
        display.disconnect()
        assert monotonic_s() - t0 < timeout_s + scaled(2.0)
