"""Runs :class:`~local_site.display.firmware.ArrayTacFirmware` in real time on a link.

:class:`FirmwareEmulator` is the drive board's main loop in a thread: on a fixed tick (2 ms
by default) it runs the link-loss watchdog, then applies the frames that arrived since the
last tick (the MCU latches new commands at its control period; at most
``max_frames_per_tick``, the rest wait for the next tick), advances the plant and sends the
feedback the firmware produces. The watchdog runs first so that a tick the thread reached
late (a starved process) judges the frames that queued meanwhile as a real board's timer
would: a command arriving after the timeout finds the trip latched and is refused. The link
is a :class:`FirmwareTransport`: the other end of a python-can bus
(:class:`CanFirmwareTransport`), of a pty (:class:`PtyFirmwareTransport`) or a TCP port the
host opens as ``socket://host:port`` (:class:`TcpFirmwareTransport`, the board as a process
of its own: ``teletouch board``).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import select
import socket
import threading
import time
from abc import ABC, abstractmethod
from types import TracebackType

import can

from local_site.display import frames as fr
from local_site.display.firmware import ArrayTacFirmware
from local_site.display.serial_framing import (
    LinkDecoderStats,
    LinkFrameDecoder,
    encode_link_frame,
)
from shared.errors import ConfigError, DeviceInitError

__all__ = ["CanFirmwareTransport", "FirmwareEmulator", "FirmwareTransport",
           "PtyFirmwareTransport", "TcpFirmwareTransport"]

log = logging.getLogger(__name__)


class FirmwareTransport(ABC):
    """The board's side of the link."""

    @abstractmethod
    def recv(self, timeout_s: float) -> tuple[int, bytes] | None:
        """Next frame ``(arb_id, payload)``, waiting up to ``timeout_s``; None if none."""

    @abstractmethod
    def send(self, arb_id: int, payload: bytes) -> None:
        """Send one frame; drop it silently when the link is congested (as a board would)."""

    @abstractmethod
    def close(self) -> None:
        """Release the link."""


class CanFirmwareTransport(FirmwareTransport):
    """The board on a python-can bus (``virtual`` for the simulator).

    Args:
        channel: the bus channel.
        interface: python-can interface.
    """

    def __init__(self, channel: str, interface: str = "virtual") -> None:
        try:
            self._bus = can.Bus(interface=interface, channel=channel, fd=True, can_filters=[
                {"can_id": fr.ARB_ID_COMMAND, "can_mask": 0x7FF, "extended": False},
                {"can_id": fr.ARB_ID_SAFE_STATE, "can_mask": 0x7FF, "extended": False}])
        except (can.CanError, OSError, ValueError) as err:
            raise DeviceInitError(f"emulated ArrayTac board: cannot open {interface}:"
                                  f"{channel}: {err}") from err
        self.dropped = 0

    def recv(self, timeout_s: float) -> tuple[int, bytes] | None:
        msg = self._bus.recv(timeout=timeout_s)
        if msg is None or msg.is_error_frame:
            return None
        return msg.arbitration_id, bytes(msg.data)

    def send(self, arb_id: int, payload: bytes) -> None:
        try:
            self._bus.send(can.Message(arbitration_id=arb_id, data=payload, is_fd=True,
                                       bitrate_switch=True, is_extended_id=False), timeout=0.0)
        except can.CanError:
            self.dropped += 1

    def close(self) -> None:
        self._bus.shutdown()


class PtyFirmwareTransport(FirmwareTransport):
    """The board on the master side of a pty (the driver opens the slave path).

    Args:
        master_fd: non-blocking master descriptor; closed by :meth:`close`.
    """

    def __init__(self, master_fd: int) -> None:
        self._fd = master_fd
        self._decoder = LinkFrameDecoder()
        self._pending: collections.deque[tuple[int, bytes]] = collections.deque()
        self.dropped = 0

    @property
    def decoder(self) -> LinkFrameDecoder:
        """The board's stream decoder (its counters)."""
        return self._decoder

    def recv(self, timeout_s: float) -> tuple[int, bytes] | None:
        if not self._pending:
            ready, _, _ = select.select([self._fd], [], [], max(0.0, timeout_s))
            if ready:
                try:
                    data = os.read(self._fd, 4096)
                except (BlockingIOError, InterruptedError):
                    data = b""
                except OSError:  # slave closed (EIO): nothing to read until it reopens
                    time.sleep(min(timeout_s, 0.01))
                    data = b""
                self._pending.extend(self._decoder.feed(data))
        return self._pending.popleft() if self._pending else None

    def send(self, arb_id: int, payload: bytes) -> None:
        try:
            os.write(self._fd, encode_link_frame(arb_id, payload))
        except OSError:  # buffer full (driver not reading) or slave closed
            self.dropped += 1

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self._fd)


class TcpFirmwareTransport(FirmwareTransport):
    """The board behind a TCP port; the host's serial driver opens ``socket://host:port``.

    The serial framing of :mod:`local_site.display.serial_framing` on a byte stream, like a
    UART or USB CDC link, so the host needs nothing but a pyserial URL. One host at a time, as
    on a serial port: a new connection replaces the current one (a restarted host whose old
    connection was never closed), and when the host goes away the board runs on and waits for
    the next one. Connecting or disconnecting never moves the pins: the firmware's watchdog
    does, as on a real board whose cable is pulled. Everything runs in the emulator's thread.

    Args:
        host: address to listen on (an emulator belongs on ``127.0.0.1``: any peer that
            connects commands the pins).
        port: TCP port (0: a free one, see :attr:`address`).
        out_buffer_bytes: feedback queued while the host does not read, at most; beyond it
            frames are dropped whole (``dropped``), as a board drops on a congested link.
        send_buffer_bytes: the connection's kernel send buffer (``SO_SNDBUF``): small, so a
            host that stops reading (a frozen station) finds a short backlog of old feedback
            when it resumes, as behind a UART's FIFO, not the megabytes loopback TCP would
            otherwise queue (the host's own receive buffer still holds some).

    Raises:
        DeviceInitError: the port cannot be bound.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, *,
                 out_buffer_bytes: int = 4096, send_buffer_bytes: int = 16384) -> None:
        try:
            self._server = socket.create_server((host, port))
        except OSError as err:
            raise DeviceInitError(f"emulated ArrayTac board: cannot listen on {host}:{port}: "
                                  f"{err}") from err
        self._server.setblocking(False)
        bound = self._server.getsockname()
        self.address: tuple[str, int] = (str(bound[0]), int(bound[1]))
        self._conn: socket.socket | None = None
        self._decoder = LinkFrameDecoder()
        self._retired = LinkDecoderStats()
        self._pending: collections.deque[tuple[int, bytes]] = collections.deque()
        self._out = bytearray()
        self._out_limit = out_buffer_bytes
        self._sndbuf = send_buffer_bytes
        self.dropped = 0
        self.connects = 0
        self.disconnects = 0
        self.replaced = 0

    @property
    def url(self) -> str:
        """The pyserial URL a host opens to reach this board."""
        return f"socket://{self.address[0]}:{self.address[1]}"

    @property
    def decoder(self) -> LinkFrameDecoder:
        """The stream decoder of the current connection (its counters)."""
        return self._decoder

    @property
    def connected(self) -> bool:
        """A host is connected."""
        return self._conn is not None

    def stream_stats(self) -> LinkDecoderStats:
        """The stream counters over every connection so far."""
        now = self._decoder.stats
        old = self._retired
        return LinkDecoderStats(bytes_in=old.bytes_in + now.bytes_in,
                                frames_ok=old.frames_ok + now.frames_ok,
                                bad_frames=old.bad_frames + now.bad_frames,
                                garbage_bytes=old.garbage_bytes + now.garbage_bytes)

    def recv(self, timeout_s: float) -> tuple[int, bytes] | None:
        if self._pending:
            return self._pending.popleft()
        conn = self._conn
        readers = [self._server] if conn is None else [self._server, conn]
        writers = [conn] if conn is not None and self._out else []
        try:
            readable, writable, _ = select.select(readers, writers, [], max(0.0, timeout_s))
        except (OSError, ValueError):  # a descriptor closed under us: drop the connection
            self._drop_connection("select failed")
            return None
        if self._server in readable:
            self._accept()
        if conn is not None and conn is self._conn:
            if conn in writable:
                self._flush()
            if conn in readable:
                self._read(conn)
        return self._pending.popleft() if self._pending else None

    def send(self, arb_id: int, payload: bytes) -> None:
        if self._conn is None:
            self.dropped += 1  # nobody on the line: the bytes are lost, as on a UART
            return
        frame = encode_link_frame(arb_id, payload)
        if len(self._out) + len(frame) > self._out_limit:
            self.dropped += 1  # the host does not read: drop whole frames, never a part
            return
        self._out += frame
        self._flush()

    def close(self) -> None:
        self._drop_connection(None)
        with contextlib.suppress(OSError):
            self._server.close()

    # ------------------------------------------------------------------ internals

    def _accept(self) -> None:
        try:
            conn, peer = self._server.accept()
        except (BlockingIOError, InterruptedError, ConnectionAbortedError):
            return
        except OSError as err:
            log.warning("emulated board: accept failed: %s", err)
            return
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self._sndbuf)
        if self._conn is not None:
            self.replaced += 1
            self._drop_connection("replaced by a new connection")
        self._conn = conn
        self._retire_decoder()  # a new stream: no half frame carries over
        self._pending.clear()
        self.connects += 1
        log.info("emulated board: host connected from %s:%s", peer[0], peer[1])

    def _retire_decoder(self) -> None:
        self._retired = self.stream_stats()
        self._decoder = LinkFrameDecoder()

    def _read(self, conn: socket.socket) -> None:
        try:
            data = conn.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as err:
            self._drop_connection(f"read failed: {err}")
            return
        if not data:
            self._drop_connection("host closed the connection")
            return
        self._pending.extend(self._decoder.feed(data))

    def _flush(self) -> None:
        conn = self._conn
        if conn is None or not self._out:
            return
        try:
            sent = conn.send(self._out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as err:
            self._drop_connection(f"write failed: {err}")
            return
        del self._out[:sent]

    def _drop_connection(self, why: str | None) -> None:
        conn, self._conn = self._conn, None
        self._out.clear()
        if conn is None:
            return
        with contextlib.suppress(OSError):
            conn.close()
        if why is not None:
            self.disconnects += 1
            log.info("emulated board: host gone (%s); the watchdog keeps the pins", why)


class FirmwareEmulator:
    """The emulated board's main loop, in a thread, in real time.

    Args:
        firmware: the firmware (with its plant).
        transport: the board's end of the link; closed by :meth:`stop`.
        tick_s: plant/watchdog/feedback tick.
        max_frames_per_tick: frames taken from the link per tick, at most (an MCU's receive
            FIFO is bounded too); the rest wait in the link for the next tick, so a host
            flooding the link cannot hold off the board's watchdog and feedback.
    """

    def __init__(self, firmware: ArrayTacFirmware, transport: FirmwareTransport, *,
                 tick_s: float = 0.002, max_frames_per_tick: int = 64) -> None:
        if max_frames_per_tick < 1:
            raise ConfigError(f"max_frames_per_tick must be >= 1, got {max_frames_per_tick}")
        self.firmware = firmware
        self.transport = transport
        self._tick_s = tick_s
        self._max_frames = max_frames_per_tick
        #: watchdog trips at a tick the thread reached after longer than the timeout: the
        #: emulator's own lateness may be the cause (its frames may have come in time); a
        #: real board's timer is never late, so these are counted apart
        self.late_tick_trips = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._finger_force_n: float | None = None
        self.error: BaseException | None = None

    def start(self) -> None:
        """Start the board loop."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="arraytac-firmware", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the loop and close the transport (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
            self.transport.close()

    def __enter__(self) -> FirmwareEmulator:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    def set_finger_force(self, force_n: float) -> None:
        """The simulated fingertip's pressing force, applied at the next tick."""
        with self._lock:
            self._finger_force_n = float(force_n)

    def _run(self) -> None:
        fw, link, tick = self.firmware, self.transport, self._tick_s
        clock = time.perf_counter
        next_tick = last_now = clock()
        try:
            while not self._stop.is_set():
                # like the MCU, which latches what arrived at its next control period: the
                # thread sleeps to the tick and takes the frames that came meanwhile (one
                # wake-up per tick, not one per frame; the feedback and the plant see the
                # frames at that tick)
                wait_s = next_tick - clock()
                if wait_s > 0:
                    time.sleep(wait_s)
                now = clock()
                # the MCU's timer fires on time whatever waits in its receive FIFO: after a
                # late tick, a command that queued past the timeout meets the latch (refused)
                away_s, last_now = now - last_now, now
                if fw.run_watchdog(now) and away_s > fw.watchdog_s:
                    self.late_tick_trips += 1
                    if self.late_tick_trips == 1:
                        log.warning("emulated ArrayTac: its watchdog tripped at a tick %.0f ms "
                                    "after the previous one (the emulator was late: the "
                                    "commands may have come in time); counted in "
                                    "late_tick_trips", away_s * 1e3)
                for _ in range(self._max_frames):  # bounded: a flood never starves the tick
                    item = link.recv(0.0)
                    if item is None:
                        break
                    fw.receive(item[0], item[1], now)
                with self._lock:
                    force, self._finger_force_n = self._finger_force_n, None
                if force is not None:
                    fw.plant.set_finger_force(force)
                for arb_id, payload in fw.poll(now):
                    link.send(arb_id, payload)
                next_tick += tick
                if now - next_tick > 10 * tick:  # starved: skip ahead, do not burst
                    next_tick = now + tick
        except Exception as err:  # keep the cause for the owner; the link goes silent
            self.error = err
            log.exception("emulated ArrayTac firmware stopped")
