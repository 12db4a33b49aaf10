"""The relay's connections as asyncio protocols: bytes in, handled in the same callback.

Each accepted socket is an :class:`asyncio.Protocol` (:class:`TcpWire`, :class:`WsWire`).
What the socket delivers (``data_received``) is parsed and handed to the relay's
connection (:meth:`Wire.receive`) at once: no reader task, no queue of received frames, no
future per message. WebSocket connections run websockets' Sans-I/O protocol
(:class:`websockets.server.ServerProtocol`: the opening handshake, frame parsing and
checks, the close handshake, pongs); TCP connections give their bytes to the length-prefix
parser of :class:`~shared.protocol.connection.ProtocolConnection` (in the relay's
:class:`~shared.protocol.peer_session.PeerSession`). Writes are ``transport.write`` calls,
at most one per peer and event-loop iteration for the forwarded messages
(:meth:`relay_server.server.RelayServer.flush_soon`).

A wire is what the relay's connection sees as its transport: :meth:`Wire.write` (waits for
the socket to take the data: flow control), :meth:`Wire.ready` / :meth:`Wire.write_nowait`
(the direct write), :meth:`Wire.close` and :attr:`Wire.ended`.

Every accepted socket first passes the relay's :class:`Admission`: the openings under way
(accepted, not yet open: a TLS handshake, a WebSocket opening) are bounded per address and in
total, and counted from the accept, before any TLS work; a socket beyond the bounds is
dropped at once. The TLS handshake runs on the accepted socket (``loop.start_tls``) so that
the count can start before it.
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import logging
import math
import ssl
import struct
import time
from collections import Counter
from collections.abc import Callable, Coroutine
from typing import Any, cast

from websockets.exceptions import InvalidState
from websockets.frames import Frame, Opcode
from websockets.http11 import Request, Response
from websockets.protocol import State
from websockets.server import ServerProtocol

try:  # websockets' C helper (its pure-Python one when the extension is not built)
    from websockets.speedups import apply_mask
except ImportError:  # pragma: no cover
    from websockets.utils import apply_mask

from shared.protocol.connection import Framing
from shared.transport import TransportClosed, set_nodelay

__all__ = ["Admission", "Opened", "TcpWire", "Wire", "WsWire"]

log = logging.getLogger(__name__)

#: the relay's handler of an open connection: ``await opened(wire, host)`` until it ends
Opened = Callable[["Wire", str], Coroutine[Any, Any, None]]
#: the relay's answer to an HTTP request on the WebSocket port (None: go on with the upgrade)
HttpHandler = Callable[["_Responder", Request], "Response | None"]

_CLOSE_TIMEOUT_S = 2.0
#: WebSocket close codes of a clean close (bye, shutdown): no lingering needed
_CLEAN_CLOSE_CODES = frozenset({1000, 1001})
#: received bytes handled per callback: a bigger chunk (asyncio reads up to 256 KiB) is
#: handled a slice per event-loop iteration, reading paused, so one busy peer cannot hold
#: the loop (the other sessions' residence time) for thousands of messages at once. Not
#: smaller: pausing and resuming costs two system calls, and at 16 KiB every 19 kB tactile
#: frame paid them (the realistic mix then took 5-10 % more CPU than the old relay)
_SLICE_BYTES = 64 * 1024
#: the header of a server's (unmasked) final binary frame, by payload length
_HEADS = [bytes((0x82, n)) for n in range(126)]
_HEAD16 = struct.Struct("!BBH")
_HEAD64 = struct.Struct("!BBQ")


class Admission:
    """What a relay's listeners share about the sockets they accept.

    ``wires``: every accepted socket not yet gone. The **openings** under way (accepted,
    not yet open: a TLS handshake, a WebSocket opening; each cut after ``open_timeout_s``)
    are counted from the accept, per address and in total. A socket that would make them
    more than ``per_address`` from one address, or ``total`` in all, is dropped at once,
    before any TLS work and without a message: nothing can be said to it before its
    opening. (An *open* connection over the relay's limits gets ``too_many_connections``
    instead: that refusal is the relay's. A plain TCP connection is open at the accept: it
    has no opening to count.) So a flood of unfinished openings from one address holds at
    most ``per_address`` sockets, for at most ``open_timeout_s`` each.

    The drops are logged as a WARNING at most once per ``warn_every_s``, with their count
    since the last one: a flood from many addresses writes a few lines, not one per socket
    or per address.

    Args:
        per_address: the most openings under way from one address.
        total: the most openings under way in all.
        open_timeout_s: the opening (TLS handshake and WebSocket upgrade) must be done
            within this time of the accept.
        tls: the server's TLS context (None: plain sockets).
        on_refused: called for each socket dropped at accept.
        warn_every_s: the least time between two warnings.
        clock: seconds, monotonic (for the warnings' spacing).
    """

    def __init__(self, *, per_address: int, total: int, open_timeout_s: float,
                 tls: ssl.SSLContext | None = None,
                 on_refused: Callable[[], None] | None = None, warn_every_s: float = 60.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.per_address = per_address
        self.total = total
        self.open_timeout_s = open_timeout_s
        self.tls = tls
        self.wires: set[Wire] = set()
        #: openings under way, per address
        self.openings: Counter[str] = Counter()
        self.opening_total = 0
        self._on_refused = on_refused
        self._warn_every_s = warn_every_s
        self._clock = clock
        self._warned_at = -math.inf
        self._unreported = 0  # drops since the last warning

    def admit(self, host: str) -> bool:
        """Count a new socket's opening; False (counted nowhere) when it is beyond a bound."""
        if self.opening_total >= self.total:
            why = f"{self.opening_total} openings are under way in all"
        elif self.openings[host] >= self.per_address:
            why = f"{self.openings[host]} openings from {host} are under way"
        else:
            self.openings[host] += 1
            self.opening_total += 1
            return True
        self._unreported += 1
        now = self._clock()
        if now - self._warned_at >= self._warn_every_s:
            log.warning("%d connection(s) dropped at accept since the last such warning, the "
                        "latest from %s: %s (TLS handshakes or WebSocket openings not "
                        "finished; the relay's refused_at_accept counts them all)",
                        self._unreported, host, why)
            self._warned_at = now
            self._unreported = 0
        if self._on_refused is not None:
            self._on_refused()
        return False

    def release(self, host: str) -> None:
        """An opening admitted by :meth:`admit` is over (open, failed or gone)."""
        self.opening_total -= 1
        self.openings[host] -= 1
        if self.openings[host] <= 0:
            del self.openings[host]


class Wire(asyncio.Protocol, abc.ABC):
    """One accepted connection (the parts TCP and WebSocket share).

    Args:
        opened: run once the connection is open (TCP: at once, or after the TLS handshake;
            WebSocket: after the opening handshake), as a task, until the connection ends.
        admission: the relay's (see :class:`Admission`).
        linger_s: see :class:`TcpWire`.
    """

    framing: Framing
    #: False where the connection is open at the accept (plain TCP): no opening to count
    OPENS_LATER = True

    def __init__(self, opened: Opened, admission: Admission, linger_s: float = 0.0) -> None:
        self._opened = opened
        self._admission = admission
        self._wires = admission.wires
        self._linger_s = linger_s
        #: the stream the connection reads and writes (TLS: above the accepted socket)
        self.transport: asyncio.Transport | None = None
        self._raw: asyncio.Transport | None = None  # the accepted socket
        self._opening = False  # counted among the admission's openings
        self._open_timer: asyncio.TimerHandle | None = None
        self._tls_task: asyncio.Task[None] | None = None  # the TLS handshake
        #: what the TLS layer decrypted before the handshake's task took the stream (the
        #: bytes that came with the client's last handshake message), and its end
        self._early_input: list[bytes] = []
        self._early_eof = False
        self.host = "?"
        #: set when no more input will be handled: the peer closed, the connection was
        #: lost, or :meth:`stop` (the relay decided to close)
        self.ended = asyncio.Event()
        self.task: asyncio.Task[None] | None = None
        self._receiver: Callable[[bytes | str], None] | None = None
        self._early: list[bytes | str] = []  # messages before receive() was called
        self._backlog = bytearray()  # the rest of a big chunk (reading paused meanwhile)
        self._backlog_scheduled = False
        self._lost = asyncio.get_running_loop().create_future()
        self._drain_waiter: asyncio.Future[None] | None = None
        self._paused = False
        self._discard = False  # closing: what the peer still sends is read and dropped
        self._close_lock = asyncio.Lock()

    # ------------------------------------------------------------------ asyncio.Protocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # the accepted socket, a stream transport (read and write): asyncio's, or another
        # event loop's that implements the same interface without subclassing it (uvloop's)
        raw = cast(asyncio.Transport, transport)
        peer = raw.get_extra_info("peername")
        if isinstance(peer, tuple) and peer:
            self.host = str(peer[0])
        admission = self._admission
        if admission.tls is not None or self.OPENS_LATER:
            if not admission.admit(self.host):
                raw.abort()
                return
            self._opening = True
        self._raw = raw
        self._wires.add(self)
        set_nodelay(raw)
        if admission.tls is None:
            self._made(raw)
        else:
            # the TLS layer reads the client's hello, not this protocol (asyncio runs the
            # task before it reads the socket; another event loop need not)
            raw.pause_reading()
            self._tls_task = asyncio.get_running_loop().create_task(
                self._start_tls(raw, admission.tls), name="relay-tls-handshake")
        if self._opening:
            self._open_timer = asyncio.get_running_loop().call_later(
                admission.open_timeout_s, self._open_timed_out)

    async def _start_tls(self, raw: asyncio.Transport, tls: ssl.SSLContext) -> None:
        transport: asyncio.Transport | None = None
        try:
            transport = cast("asyncio.Transport | None", await asyncio.get_running_loop(
                ).start_tls(raw, self, tls, server_side=True,
                            ssl_handshake_timeout=self._admission.open_timeout_s))
        except OSError as err:  # plain bytes, a bad or cut record, timed out, a reset
            log.debug("TLS handshake from %s failed: %r", self.host, err)
        except Exception:
            log.exception("relay bug in the TLS handshake of a connection from %s", self.host)
        finally:
            if transport is None:  # failed, cancelled, or the socket went meanwhile
                raw.abort()
                self.connection_lost(None)
        if transport is None:
            return
        self._made(transport)
        # a client whose close_notify came in the flight of its last handshake message gets
        # no answer to what it sent with it: the TLS layer has closed the stream by now
        early, self._early_input = self._early_input, []
        for data in early:
            self.data_received(data)
        if self._early_eof:
            self.eof_received()

    def _made(self, transport: asyncio.Transport) -> None:
        """The stream to speak on is there (the accepted socket, or TLS above it)."""
        self.transport = transport

    def _open_timed_out(self) -> None:
        if self._opening:
            self.abort()

    def data_received(self, data: bytes) -> None:
        if self.transport is None:  # TLS: decrypted before the handshake's task went on
            self._early_input.append(data)
            return
        if self._discard:
            return
        if self._backlog or len(data) > _SLICE_BYTES:
            self._backlog += data
            if not self._backlog_scheduled:
                self._backlog_scheduled = True
                self._pause_reading()
                self._handle_backlog()
            return
        self._guarded(data)

    def _handle_backlog(self) -> None:
        piece = bytes(self._backlog[:_SLICE_BYTES])
        del self._backlog[:_SLICE_BYTES]
        self._guarded(piece)
        if self._backlog and not self._discard and not self.ended.is_set():
            asyncio.get_running_loop().call_soon(self._handle_backlog)
            return
        self._backlog.clear()
        self._backlog_scheduled = False
        if self.transport is not None and not self.transport.is_closing():
            with contextlib.suppress(RuntimeError):
                self.transport.resume_reading()

    def _pause_reading(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            with contextlib.suppress(RuntimeError):
                self.transport.pause_reading()

    def _guarded(self, data: bytes) -> None:
        """:meth:`_data` that never lets an exception reach asyncio: a relay bug ends this
        connection (1011), not the server."""
        try:
            self._data(data)
        except Exception:
            log.exception("relay bug while handling a connection's input (%s, %s)",
                          self.framing, self.host)
            self.stop()
            self.abort()

    @abc.abstractmethod
    def _data(self, data: bytes) -> None:
        """Parse received bytes (the framing of this wire)."""

    def eof_received(self) -> bool | None:
        if self.transport is None:  # TLS: before the handshake's task went on
            self._early_eof = True
            return False
        self.ended.set()
        return False  # close our side too

    def connection_lost(self, exc: Exception | None) -> None:
        # may come twice for a failed TLS handshake (from its task and from the TLS layer)
        self._end_opening()
        self._wires.discard(self)
        self.ended.set()
        if not self._lost.done():
            self._lost.set_result(None)
        self._wake_drain()

    def pause_writing(self) -> None:
        self._paused = True

    def resume_writing(self) -> None:
        self._paused = False
        self._wake_drain()

    def _wake_drain(self) -> None:
        waiter, self._drain_waiter = self._drain_waiter, None
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    # ------------------------------------------------------------------ to the relay

    def _end_opening(self) -> None:
        if self._open_timer is not None:
            self._open_timer.cancel()
            self._open_timer = None
        if self._opening:
            self._opening = False
            self._admission.release(self.host)

    def _start(self) -> None:
        """The connection is open: run the relay's handler."""
        self._end_opening()
        self.task = asyncio.get_running_loop().create_task(self._opened(self, self.host),
                                                           name="relay-connection")

    def _deliver(self, message: bytes | str) -> None:
        if self.ended.is_set():
            return
        if self._receiver is None:
            self._early.append(message)
        else:
            self._receiver(message)

    def receive(self, receiver: Callable[[bytes | str], None]) -> None:
        """From now on hand every received message (WebSocket) or chunk (TCP) to
        ``receiver``, in the callback that read it (what came before is handed now)."""
        self._receiver = receiver
        early, self._early = self._early, []
        for message in early:
            if self.ended.is_set():
                break
            receiver(message)

    def stop(self) -> None:
        """Handle no more input (the relay is closing this connection)."""
        self.ended.set()

    def abort(self) -> None:
        """Drop the socket at once (also in its TLS handshake)."""
        transport = self.transport or self._raw
        if transport is not None:
            transport.abort()


    # ------------------------------------------------------------------ writing

    def _open(self) -> bool:
        return self.transport is not None and not self.transport.is_closing()

    def ready(self) -> bool:
        """True when :meth:`write_nowait` may be used: open, and the socket took all of
        the earlier writes."""
        transport = self.transport
        return transport is not None and not transport.is_closing() and \
            transport.get_write_buffer_size() == 0 and self._writable()

    def _writable(self) -> bool:
        return True

    @abc.abstractmethod
    def write_nowait(self, frames: list[bytes]) -> None:
        """Hand framed messages to the socket now (see :meth:`ready`)."""

    def set_receive_limit(self, max_bytes: int) -> None:
        """The size limit of received messages from now on (the hello's is over)."""

    @abc.abstractmethod
    async def close(self, code: int = 1000, reason: str = "") -> None:
        """Close (``code`` is a WebSocket close code); never raises."""

    async def write(self, frames: list[bytes]) -> None:
        """Write framed messages and wait until the socket's buffer is under its limit.

        Raises:
            TransportClosed: the connection is gone.
        """
        if not self._open():
            raise TransportClosed("the connection is closed")
        try:
            self.write_nowait(frames)
        except (InvalidState, RuntimeError) as err:
            raise TransportClosed(f"write failed: {err}") from err
        if self._paused:
            waiter = self._drain_waiter
            if waiter is None:
                waiter = self._drain_waiter = asyncio.get_running_loop().create_future()
            await waiter
            if not self._open() and self._lost.done():
                raise TransportClosed("the connection was lost while writing")

    def buffered(self) -> bool:
        """Nothing waits for a reader: input is handled as it arrives."""
        return False

    async def gone(self, timeout_s: float) -> bool:
        """Wait (bounded) until the socket is gone; True when it is."""
        with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
            await asyncio.wait_for(asyncio.shield(self._lost), timeout_s)
        return self._lost.done()

    async def _close_socket(self) -> None:
        """Close the socket and wait (bounded) for it to go; abort it if it does not."""
        if self.transport is None:
            return
        if not self.transport.is_closing():
            self.transport.close()
        if not await self.gone(_CLOSE_TIMEOUT_S):
            self.transport.abort()


class TcpWire(Wire):
    """Length-prefixed TCP: every chunk goes to the relay's connection as it is (its
    :class:`~shared.protocol.connection.ProtocolConnection` parses the frames).

    Args:
        linger_s: on an error close (any code but 1000/1001), half-close and read and
            discard what the peer still sends for up to this long before closing: closing
            a socket with unread input makes the kernel send a reset, and a reset destroys
            the data in flight to the peer (the fatal ``error`` just written).
    """

    framing: Framing = "tcp"
    OPENS_LATER = False

    def _made(self, transport: asyncio.Transport) -> None:
        super()._made(transport)
        self._start()

    def _data(self, data: bytes) -> None:
        self._deliver(data)

    def write_nowait(self, frames: list[bytes]) -> None:
        assert self.transport is not None
        self.transport.write(frames[0] if len(frames) == 1 else b"".join(frames))

    async def close(self, code: int = 1000, reason: str = "") -> None:
        """Close (``code`` only decides the linger); never raises."""
        async with self._close_lock:  # a second closer waits for the first one's linger
            transport = self.transport
            if transport is None:
                return
            if not transport.is_closing() and self._linger_s > 0 and \
                    code not in _CLEAN_CLOSE_CODES:
                await self._linger(transport)
            await self._close_socket()

    async def _linger(self, transport: asyncio.Transport) -> None:
        self._discard = True
        self._backlog.clear()
        with contextlib.suppress(RuntimeError):
            transport.resume_reading()
        deadline = asyncio.get_running_loop().time() + self._linger_s
        while self._paused and not self._lost.done():  # the error out first
            waiter = self._drain_waiter
            if waiter is None:
                waiter = self._drain_waiter = asyncio.get_running_loop().create_future()
            left = deadline - asyncio.get_running_loop().time()
            if left <= 0:
                break
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(asyncio.shield(waiter), left)
        if transport.is_closing():
            return
        if transport.can_write_eof():
            with contextlib.suppress(OSError, RuntimeError):
                transport.write_eof()  # our side is done: the peer reads to EOF
        # discard (data_received drops it) until the peer closes too or the linger ends
        await self.gone(max(0.0, deadline - asyncio.get_running_loop().time()))


#: where a connection's answer and close go when they are routine (a liveness probe every
#: 30 s): not logged below WARNING
_QUIET_LOG = logging.getLogger("relay_server.websockets.quiet")
_QUIET_LOG.setLevel(logging.WARNING)


class _Responder:
    """What the relay's HTTP handler answers with (``respond(status, text)``)."""

    def __init__(self, protocol: ServerProtocol) -> None:
        self._protocol = protocol

    def respond(self, status: int, text: str) -> Response:
        return self._protocol.reject(status, text)

    def quiet(self) -> None:
        """Log this connection's answer and its close only at WARNING and above."""
        self._protocol.logger = _QUIET_LOG


class WsWire(Wire):
    """WebSocket over websockets' Sans-I/O server protocol.

    Args:
        http: answers ``GET /status`` and the like before the upgrade (None: upgrade).
        serving: False once the relay shuts down (then upgrades get 503).
        max_size: the size limit of received messages until :meth:`set_receive_limit`.
        write_limit: the high-water mark of the socket's write buffer.
    """

    framing: Framing = "ws"

    def __init__(self, opened: Opened, admission: Admission, *, http: HttpHandler,
                 serving: Callable[[], bool], max_size: int, write_limit: int,
                 logger: logging.Logger) -> None:
        super().__init__(opened, admission)
        self._http = http
        self._serving = serving
        self._write_limit = write_limit
        self.ws = ServerProtocol(max_size=max_size, logger=logger)
        self._max_size = max_size
        #: received bytes not yet parsed (the fast path: see _data)
        self._inbuf = bytearray()
        #: the fast path is off for good (the connection is closing, or a frame was one
        #: the protocol fails the connection for)
        self._protocol_only = False
        #: the fragments of a message so far (while there are, every frame goes to the
        #: protocol)
        self._fragments: list[bytes] = []
        self._fragment_text = False

    def _made(self, transport: asyncio.Transport) -> None:
        super()._made(transport)
        transport.set_write_buffer_limits(high=self._write_limit)

    def eof_received(self) -> bool | None:
        if self.transport is None:
            return super().eof_received()
        self.ws.receive_eof()
        self._send()
        return super().eof_received()

    def _data(self, data: bytes) -> None:
        """Received bytes. Once the connection is open, a complete, unfragmented, masked
        binary frame within the size limit (every message of a station) is unmasked and
        handed on here, without websockets' frame parser; any other frame (ping, close,
        text, fragments, anything malformed or too long) goes to the Sans-I/O protocol,
        always from a frame boundary, which answers or fails the connection as it would
        have anyway. Closing, everything goes to the protocol."""
        if self._protocol_only or self.ws.state is not State.OPEN or self._mid_frame():
            if self._inbuf:
                data, self._inbuf = bytes(self._inbuf) + data, bytearray()
            self._protocol_data(data)
            return
        buf = self._inbuf
        buf += data
        pos, n = 0, len(buf)
        while n - pos >= 2:
            b0, b1 = buf[pos], buf[pos + 1]
            length, head = b1 & 0x7F, 2
            if length == 126:
                if n - pos < 4:
                    break
                length, head = int.from_bytes(buf[pos + 2:pos + 4], "big"), 4
            elif length == 127:
                if n - pos < 10:
                    break
                length, head = int.from_bytes(buf[pos + 2:pos + 10], "big"), 10
            masked = b1 & 0x80
            if not masked or length > self._max_size:
                self._protocol_only = True  # the protocol fails the connection (1002, 1009)
                break
            head += 4
            end = pos + head + length
            if end > n:
                break  # the rest of the frame is still to come
            if b0 == 0x82 and not self._fragments:  # FIN, no RSV bits, binary
                payload = apply_mask(buf[pos + head:end], buf[pos + head - 4:pos + head])
                pos = end
                self._deliver(payload)
                continue
            frame_bytes = bytes(buf[pos:end])
            pos = end
            self._protocol_data(frame_bytes)
            if self.ws.state is not State.OPEN:
                self._protocol_only = True
                break
        if self._protocol_only:
            rest = bytes(buf[pos:])
            buf.clear()
            if rest:
                self._protocol_data(rest)
        else:
            del buf[:pos]

    def _mid_frame(self) -> bool:
        """True when the protocol holds part of a frame (the bytes that came with the
        opening handshake ended inside one): it parses on until a frame boundary. Also
        when that cannot be told (a websockets release without ``reader.buffer``)."""
        buffer = getattr(getattr(self.ws, "reader", None), "buffer", None)
        return buffer is None or len(buffer) > 0

    def _protocol_data(self, data: bytes) -> None:
        ws = self.ws
        ws.receive_data(data)
        events = ws.events_received()
        self._send()  # pongs, the close handshake, a failure's close frame
        for event in events:
            if isinstance(event, Frame):
                self._frame(event)
            elif isinstance(event, Request):
                self._handshake(event)
        if ws.state is not State.OPEN and ws.state is not State.CONNECTING:
            self.ended.set()  # a close frame came, or the protocol failed the connection

    def _frame(self, frame: Frame) -> None:
        opcode = frame.opcode
        if opcode is Opcode.BINARY or opcode is Opcode.TEXT:
            if frame.fin:
                data = bytes(frame.data)
                self._deliver(data if opcode is Opcode.BINARY
                              else data.decode("utf-8", "replace"))
            else:
                self._fragments = [bytes(frame.data)]
                self._fragment_text = opcode is Opcode.TEXT
        elif opcode is Opcode.CONT:
            self._fragments.append(bytes(frame.data))
            if frame.fin:
                data = b"".join(self._fragments)
                self._fragments = []
                self._deliver(data.decode("utf-8", "replace") if self._fragment_text
                              else data)
        # ping (the protocol queued the pong), pong, close: nothing for the relay

    def _handshake(self, request: Request) -> None:
        ws = self.ws
        response: Response | None
        try:
            response = self._http(_Responder(ws), request)
        except Exception:
            log.exception("relay bug answering an HTTP request")
            response = ws.reject(500, "Tele-Touch relay: internal error\n")
        if response is None:
            response = ws.accept(request)
            if response.status_code == 101 and not self._serving():
                response = ws.reject(503, "Tele-Touch relay: shutting down\n")
        ws.send_response(response)
        self._send()
        if ws.state is State.OPEN:
            self._start()
        elif ws.handshake_exc is not None:
            log.info("WebSocket handshake from %s failed: %s", self.host, ws.handshake_exc)

    def _send(self) -> None:
        """Write what the protocol has to send; an empty item means: end of our stream."""
        transport = self.transport
        if transport is None or transport.is_closing():
            return
        for data in self.ws.data_to_send():
            if data:
                transport.write(data)
            elif transport.can_write_eof():  # the server ends the TCP connection first
                with contextlib.suppress(OSError, RuntimeError):
                    transport.write_eof()
            else:  # TLS: no half-close
                transport.close()
                return

    def _writable(self) -> bool:
        return self.ws.state is State.OPEN

    def write_nowait(self, frames: list[bytes]) -> None:
        """Each frame as one unmasked binary WebSocket frame (the server's), written here:
        what ``send_binary`` and its serializer produce, without their per-frame objects."""
        if self.ws.state is not State.OPEN:
            raise InvalidState(f"WebSocket connection is {self.ws.state.name}")
        self._send()  # whatever the protocol queued (a pong) goes first
        assert self.transport is not None
        out: list[bytes] = []
        for data in frames:
            n = len(data)
            out.append(_HEADS[n] if n < 126 else
                       _HEAD16.pack(0x82, 126, n) if n < 65536 else
                       _HEAD64.pack(0x82, 127, n))
            out.append(data)
        self.transport.write(b"".join(out))

    def set_receive_limit(self, max_bytes: int) -> None:
        """Messages up to ``max_bytes`` from now on (the hello limit is over)."""
        self._max_size = max_bytes
        self.ws.max_message_size = max_bytes

    async def close(self, code: int = 1000, reason: str = "") -> None:
        """The close handshake (``code``, ``reason``), bounded; never raises."""
        async with self._close_lock:
            if self.transport is None:
                return
            if self.ws.state is State.OPEN and not self.transport.is_closing():
                with contextlib.suppress(Exception):
                    self.ws.send_close(code, reason[:120])
                    self._send()
            # the peer's close frame (what it still sends before it is read and dropped)
            # makes the protocol end the stream; the socket goes when the peer closes it
            self.ended.set()
            if not await self.gone(_CLOSE_TIMEOUT_S) and self.transport is not None:
                self.transport.abort()

