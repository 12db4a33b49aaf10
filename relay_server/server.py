"""The Tele-Touch relay: asyncio glue around the sans-I/O protocol, sessions and ledgers.

Wire behaviour (the contract station clients rely on)
=====================================================

Transports, both on ``--host``:

* WebSocket on ``--port`` (binary messages, one Tele-Touch message each, no compression).
  The same port answers plain HTTP ``GET /status`` (JSON) and ``GET /metrics``
  (Prometheus text); any other plain HTTP request gets 404.
* Raw TCP on ``--tcp-port`` (default ``--port + 1``): each message is a 4-byte big-endian
  length followed by that many msgpack bytes (:mod:`shared.protocol.framing`).

TCP_NODELAY is on for both.

Handshake
---------
1. The client connects and sends ``hello {role, session, token, name}`` within
   ``hello_timeout_s`` (default 5 s). ``role`` is ``local``, ``remote`` or ``observer``.
2. The relay checks the token (explicit per-session table first, else
   ``hex(HMAC-SHA256(secret, session))``; constant-time comparison) and the role.
3. The relay answers ``welcome {session, role, server_time_us, ping_interval_s,
   max_message_bytes}``. Anything the client sent behind its hello in the same read is
   processed after the welcome.

Before ``welcome`` every problem is fatal. The first message must be a ``hello``.

Clock synchronisation
---------------------
Right after ``welcome`` the relay sends each *station* (local/remote, not observers)
``ping_burst`` (default 5) ``clock_ping {ping_id, t0_us}`` spaced ``ping_burst_spacing_s``
(20 ms), then one every ``ping_interval_s`` (default 1 s). ``t0_us`` is stamped when the
ping is written. The station must answer at once with ``clock_pong {ping_id, t0_us (echoed),
t1_us (its receive time), t2_us (its send time)}`` on its own clock. The relay keeps the
last 8 samples and uses the minimum-delay one: ``offset = station clock - relay clock``.
Pongs that answer no outstanding ping (16 are remembered) are ignored. The relay also
answers a ``clock_ping`` from any peer with a ``clock_pong`` (relay clock), so stations
may estimate the offset themselves.

Forwarding
----------
``local`` may send ``platform_state`` and ``arm_command``; ``remote`` may send
``arm_state`` and ``tactile_frame``. Each goes to the other station and to every observer,
with ``["relay", "relay_in", t]`` appended to ``hops`` on receipt and
``["relay", "relay_out", t]`` just before it is written (relay clock).

* ``platform_state``, ``arm_state``, ``tactile_frame``: latest-wins. Per receiving peer and
  stream one slot; a newer message replaces an unsent one (counted as ``latest_wins``).
  With no receiving station the message is dropped (counted as ``no_peer``).
* ``arm_command``: ordered, bounded queue (``ordered_queue_len``, 256). If the receiver's
  queue is full, or there is no receiving station, the sender gets a non-fatal ``error``
  (``queue_full`` / ``no_peer``) naming the seq: never a silent loss.

Each peer has its own writer task, so a slow or dead peer only fills its own queue.

Stats
-----
Every ``stats_interval_s`` (1 s) each peer (stations and observers) receives
``stats {scope: "relay", time_us, metrics}``; the keys of ``metrics`` are documented in
:mod:`relay_server.metrics` (``clock_offset_us {local, remote}``, ``delay_us`` per direction
and leg with p50/p99/max, ``jitter_us``, ``rate_hz``, ``forwarded``, ``drops``,
``queue_depth``, ...). A station may send its own ``stats`` (scope = its role); the relay
keeps the latest and shows it in ``/status`` as ``reported``. Observers may send only
``clock_pong``, ``clock_ping``, ``stats`` and ``bye``; anything else gets ``read_only``.

Errors and close codes
----------------------
An ``error {code, message, fatal}`` is sent first; when ``fatal`` the connection is then
closed (WebSocket close code below; TCP just closes). Each bad connection is logged once
at WARNING, without a traceback.

======================  =====================  =====  =====================================
code                    cause                  close  fatal?
======================  =====================  =====  =====================================
``auth``                missing/wrong token    4001   yes
``role_taken``          second local/remote    4002   yes
``hello_timeout``       no hello in time       4003   yes
``hello_expected``      first message not      1002   yes
                        a hello
``version``             unsupported ``v``      1002   yes
``oversize``            message > limit        1009   yes (TCP cannot resynchronise)
``malformed``           not msgpack / bad      1007   before hello, or a broken TCP
                        length prefix                 length prefix; else per message
``unknown_type``        unknown ``type``       1003   before hello only; else per message
``bad_field``           missing/wrong field    1007   before hello only; else per message
``non_finite``          NaN/Inf                1007   before hello only; else per message
``read_only``           observer sent data     --     per message
``wrong_direction``     e.g. local sent        --     per message
                        tactile_frame
``already_joined``      second hello           --     per message
``too_many_errors``     per-message errors     1008   yes
                        over the budget (20)
``queue_full``          receiver's ordered     --     per message (not the sender's fault,
                        queue is full                 not counted in the budget)
``no_peer``             no receiving station   --     per message (idem)
======================  =====================  =====  =====================================

A ``bye`` from the client closes the connection with 1000. On shutdown (SIGINT/SIGTERM)
the relay sends ``bye {reason: "relay shutting down"}`` and closes with 1001.
WebSocket messages above twice the limit are refused by the WebSocket layer itself
(close 1009 without an ``error``).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import signal
import socket
from collections import Counter
from collections.abc import Awaitable, Callable
from typing import Any

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from relay_server.auth import TokenAuthority, load_token_file
from relay_server.config import RelayConfig
from relay_server.metrics import prometheus_text, session_metrics, session_status
from relay_server.outbox import Outbox, run_writer
from relay_server.session import Peer, Session
from shared.errors import (
    HandshakeTimeoutError,
    MalformedMessageError,
    OversizeError,
    ProtocolError,
    RemoteProtocolError,
    SessionError,
    VersionError,
)
from shared.protocol import (
    Bye,
    ClockPing,
    ClockPong,
    ConnectionFailed,
    DataMessage,
    Error,
    Event,
    Hello,
    Message,
    MessageReceived,
    MessageRejected,
    ProtocolConnection,
    Stats,
    Welcome,
)
from shared.timebase import now_us

__all__ = ["RelayServer", "serve_forever"]

log = logging.getLogger(__name__)

_FATAL_AFTER_HELLO = (VersionError, OversizeError)
_OBSERVER_MAY_SEND = (ClockPong, ClockPing, Stats, Bye)
_CLOSE_TIMEOUT_S = 2.0
_EVENTS_PER_SLICE = 32  # messages handled before yielding, for big TCP chunks
_YIELD_EVERY_S = 0.0002

#: a receive function: the next WebSocket message / TCP chunk, or None at end of stream
Receive = Callable[[], Awaitable[bytes | str | None]]


class _ClientBye(Exception):
    """The client said bye: close normally."""


class _WsLink:
    framing = "ws"

    def __init__(self, ws: ServerConnection) -> None:
        self.ws = ws

    async def write(self, frames: list[bytes]) -> None:
        for data in frames:
            await self.ws.send(data)

    async def close(self, code: int, reason: str) -> None:
        await self.ws.close(code, reason[:120])

    async def receive(self) -> bytes | str | None:
        try:
            return await self.ws.recv()
        except ConnectionClosed:
            return None


class _TcpLink:
    framing = "tcp"

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer

    async def write(self, frames: list[bytes]) -> None:
        self.writer.write(b"".join(frames) if len(frames) > 1 else frames[0])
        await self.writer.drain()

    async def close(self, code: int, reason: str) -> None:
        self.writer.close()
        with contextlib.suppress(OSError, ConnectionError):
            await self.writer.wait_closed()

    async def receive(self) -> bytes | None:
        try:
            data = await self.reader.read(64 * 1024)
        except (ConnectionError, OSError):
            return None
        return data or None


def _set_nodelay(transport: Any) -> None:
    sock = transport.get_extra_info("socket") if transport is not None else None
    if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class RelayServer:
    """The relay: ``await start()``, serve, ``await close()`` (or ``async with``).

    Args:
        config: resolved settings.

    Raises:
        ConfigError: no credentials configured, or an unreadable token file.
    """

    def __init__(self, config: RelayConfig) -> None:
        self.config = config
        tokens = dict(config.tokens)
        if config.token_file is not None:
            tokens.update(load_token_file(config.token_file))
        self.auth = TokenAuthority(tokens, config.secret, allow_any=config.allow_any_token)
        self.sessions: dict[str, Session] = {}
        self.counters: Counter[str] = Counter()
        self._peer_ids = itertools.count(1)
        self._ws_server: Server | None = None
        self._tcp_server: asyncio.Server | None = None
        self._handlers: set[asyncio.Task[Any]] = set()
        self._contexts: set[_ConnContext] = set()
        self._closing = False

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Bind the WebSocket and TCP listeners."""
        cfg = self.config
        if cfg.allow_any_token:
            log.warning("relay accepts ANY token (--allow-any-token): development only")
        self._ws_server = await serve(
            self._ws_handler, cfg.host, cfg.port, compression=None,
            process_request=self._process_http, max_size=2 * cfg.max_message_bytes,
            max_queue=64, write_limit=256 * 1024)
        self._tcp_server = await asyncio.start_server(
            self._tcp_handler, cfg.host, cfg.resolved_tcp_port, limit=2**20)
        log.info("relay listening: ws://%s:%d (status: /status, /metrics), tcp://%s:%d",
                 cfg.host, self.ws_port, cfg.host, self.tcp_port)

    @property
    def ws_port(self) -> int:
        """The bound WebSocket port."""
        if self._ws_server is None:
            raise RuntimeError("relay not started")
        return int(next(iter(self._ws_server.sockets)).getsockname()[1])

    @property
    def tcp_port(self) -> int:
        """The bound TCP port."""
        if self._tcp_server is None:
            raise RuntimeError("relay not started")
        return int(self._tcp_server.sockets[0].getsockname()[1])

    async def close(self) -> None:
        """Say bye to every peer, close all connections and listeners, wait for handlers."""
        self._closing = True
        if self._tcp_server is not None:
            self._tcp_server.close()
        if self._ws_server is not None:
            self._ws_server.close(close_connections=False)
        await asyncio.gather(*(ctx.shutdown() for ctx in list(self._contexts)),
                             return_exceptions=True)
        if self._handlers:
            _, pending = await asyncio.wait(set(self._handlers), timeout=_CLOSE_TIMEOUT_S)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
        if self._ws_server is not None:
            await self._ws_server.wait_closed()
        if self._tcp_server is not None:
            await self._tcp_server.wait_closed()

    async def __aenter__(self) -> RelayServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ------------------------------------------------------------------ HTTP

    def status(self) -> dict[str, Any]:
        """The ``/status`` document: every session with directions and percentiles."""
        return {"time_us": now_us(), "sessions": {sid: session_status(s) for sid, s
                                                  in sorted(self.sessions.items())},
                "counters": dict(self.counters),
                "ports": {"ws": self.ws_port, "tcp": self.tcp_port}}

    def _process_http(self, connection: ServerConnection, request: Request
                      ) -> Response | None:
        path = request.path.split("?", 1)[0]
        if path == "/status":
            body = json.dumps(self.status(), allow_nan=False, indent=1)
            return _http_response(connection, 200, body, "application/json")
        if path == "/metrics":
            return _http_response(connection, 200, prometheus_text(self.sessions,
                                                                   dict(self.counters)),
                                  "text/plain; version=0.0.4; charset=utf-8")
        if "upgrade" not in request.headers.get("Connection", "").lower():
            return _http_response(connection, 404, "Tele-Touch relay: WebSocket endpoint; "
                                  "see /status and /metrics\n", "text/plain; charset=utf-8")
        return None

    # ------------------------------------------------------------------ connections

    async def _ws_handler(self, ws: ServerConnection) -> None:
        _set_nodelay(ws.transport)
        link = _WsLink(ws)
        await self._serve_connection(link, link.receive)

    async def _tcp_handler(self, reader: asyncio.StreamReader,
                           writer: asyncio.StreamWriter) -> None:
        _set_nodelay(writer.transport)
        link = _TcpLink(reader, writer)
        try:
            await self._serve_connection(link, link.receive)
        finally:
            if not writer.is_closing():
                writer.close()
            with contextlib.suppress(OSError, ConnectionError):
                await writer.wait_closed()

    async def _serve_connection(self, link: _WsLink | _TcpLink, receive: Receive) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._handlers.add(task)
        conn = ProtocolConnection("ws" if link.framing == "ws" else "tcp",
                                  self.config.max_message_bytes)
        ctx = _ConnContext(self, link, conn)
        self._contexts.add(ctx)
        try:
            await ctx.run(receive)
        finally:
            self._contexts.discard(ctx)
            if task is not None:
                self._handlers.discard(task)

    def _new_session_peer(self, hello: Hello, link: _WsLink | _TcpLink) -> tuple[Session, Peer]:
        self.auth.check(hello.session, hello.token)
        session = self.sessions.get(hello.session)
        if session is None:
            if len(self.sessions) >= self.config.max_sessions:
                raise SessionError(f"relay is full ({self.config.max_sessions} sessions)",
                                   code="relay_full")
            session = Session(hello.session, self.config.ledger_window)
        peer = Peer(peer_id=next(self._peer_ids), session_id=hello.session, role=hello.role,
                    name=hello.name, transport=link.framing,
                    outbox=Outbox(self.config.ordered_queue_len),
                    window=self.config.ledger_window)
        session.join(peer)
        self.sessions[hello.session] = session
        return session, peer

    def _drop_peer(self, session: Session, peer: Peer) -> None:
        session.leave(peer)
        if session.empty and self.sessions.get(session.session_id) is session:
            del self.sessions[session.session_id]


def _http_response(connection: ServerConnection, status: int, body: str,
                   content_type: str) -> Response:
    response = connection.respond(status, body)
    headers = Headers(response.headers)
    del headers["Content-Type"]
    headers["Content-Type"] = content_type
    return Response(response.status_code, response.reason_phrase, headers, response.body)


class _ConnContext:
    """The life of one connection: hello, join, read loop, close. One per connection."""

    def __init__(self, relay: RelayServer, link: _WsLink | _TcpLink,
                 conn: ProtocolConnection) -> None:
        self.relay = relay
        self.cfg = relay.config
        self.link = link
        self.conn = conn
        self.session: Session | None = None
        self.peer: Peer | None = None
        self.writer: asyncio.Task[None] | None = None
        self.ticker: asyncio.Task[None] | None = None
        self.warned = False
        self.where = "?"

    # -------------------------------------------------------------- main flow

    async def run(self, receive: Receive) -> None:
        close_code, reason = 1000, "bye"
        try:
            pending = await self._handshake(receive)
            if pending is None:
                return
            loop = asyncio.get_running_loop()
            last_yield = loop.time()
            self._process(pending, now_us())
            while True:
                data = await receive()
                if data is None:
                    close_code, reason = 1000, "peer closed"
                    break
                t_in = now_us()
                events = self._feed(data)
                for start in range(0, len(events), _EVENTS_PER_SLICE):
                    self._process(events[start:start + _EVENTS_PER_SLICE], t_in)
                    if start + _EVENTS_PER_SLICE < len(events):
                        await asyncio.sleep(0)  # let writers and other sessions run
                # websockets returns buffered messages without suspending: yield now and
                # then so one busy reader cannot starve the writers (fairness, bounded
                # residence time), at most every _YIELD_EVERY_S
                t_now = loop.time()
                if t_now - last_yield > _YIELD_EVERY_S:
                    last_yield = t_now
                    await asyncio.sleep(0)
                if self.peer is not None and self.peer.outbox.closed:
                    close_code, reason = 1001, "relay shutting down"
                    break
        except _ClientBye:
            close_code, reason = 1000, "bye"
        except (ProtocolError, SessionError) as err:
            close_code, reason = err.close_code, err.code
            await self._fatal(err)
        finally:
            await self._teardown(close_code, reason)

    def _feed(self, data: bytes | str) -> list[Event]:
        if isinstance(data, str):  # WebSocket text frame: not our protocol
            return [MessageRejected(MalformedMessageError(
                "text WebSocket messages are not accepted; send binary msgpack"))]
        self.conn.receive_data(data)
        return self.conn.events_received()

    async def _handshake(self, receive: Receive) -> list[Event] | None:
        """Wait for a valid hello, join, start the writer; return events queued behind it."""
        try:
            async with asyncio.timeout(self.cfg.hello_timeout_s):
                while True:
                    data = await receive()
                    if data is None:
                        return None
                    events = self._feed(data)
                    if events:
                        break
        except TimeoutError as err:
            raise HandshakeTimeoutError(
                f"no hello within {self.cfg.hello_timeout_s:g} s") from err
        first, rest = events[0], events[1:]
        if isinstance(first, ConnectionFailed | MessageRejected):
            raise first.error
        if not isinstance(first.message, Hello):
            raise RemoteProtocolError(f"the first message must be a hello, got "
                                      f"{first.message.TYPE}", code="hello_expected")
        hello = first.message
        self.where = f"{hello.role}@{hello.session}"
        if self.relay._closing:
            raise SessionError("relay shutting down", code="shutdown")
        self.session, self.peer = self.relay._new_session_peer(hello, self.link)
        peer = self.peer
        self.writer = asyncio.create_task(
            run_writer(peer.outbox, self.link, self._encode, self.cfg.max_message_bytes, now_us,
                       self._writer_failed),
            name=f"relay-writer-{peer.peer_id}")
        peer.outbox.put_ordered(Welcome(
            session=hello.session, role=hello.role, server_time_us=now_us(),
            ping_interval_s=self.cfg.ping_interval_s,
            max_message_bytes=self.cfg.max_message_bytes), force=True)
        self.ticker = asyncio.create_task(self._tick(), name=f"relay-ticker-{peer.peer_id}")
        self.relay.counters["joined"] += 1
        log.info("joined %s (%s, %s) name=%r", self.where, self.link.framing,
                 peer.peer_id, hello.name)
        return rest

    def _encode(self, msg: Message, validate: bool) -> bytes:
        return self.conn.encode(msg, validate=validate)

    # -------------------------------------------------------------- per message

    def _process(self, events: list[Event], t_in_us: int) -> None:
        peer, session = self.peer, self.session
        if peer is None or session is None:
            return
        for ev in events:
            if isinstance(ev, MessageReceived):
                msg = ev.message
                peer.received += 1
                if isinstance(msg, DataMessage):
                    if peer.role == "observer":
                        self._bad(SessionError(f"observers are read-only; {msg.TYPE} refused",
                                               code="read_only"))
                        continue
                    reply = session.route(peer, msg, t_in_us)
                    if reply is not None:
                        if reply.code == "wrong_direction":
                            self._bad(SessionError(reply.message, code=reply.code))
                        else:
                            self._reply(reply)
                else:
                    self._control(msg, t_in_us)
            elif isinstance(ev, MessageRejected):
                if isinstance(ev.error, _FATAL_AFTER_HELLO):
                    raise ev.error
                self._bad(ev.error)
            else:
                raise ev.error

    def _control(self, msg: Message, t_in_us: int) -> None:
        peer = self.peer
        if peer is None:
            return
        if isinstance(msg, ClockPong):
            if not peer.on_pong(msg, t_in_us):
                self.relay.counters["stray_pong"] += 1
        elif isinstance(msg, ClockPing):
            self._reply(ClockPong(ping_id=msg.ping_id, t0_us=msg.t0_us, t1_us=t_in_us,
                                  t2_us=now_us()))
        elif isinstance(msg, Bye):
            raise _ClientBye
        elif peer.role == "observer" and not isinstance(msg, _OBSERVER_MAY_SEND):
            self._bad(SessionError(f"observers are read-only; {msg.TYPE} refused",
                                   code="read_only"))
        elif isinstance(msg, Stats):
            peer.reported = dict(msg.metrics)
        elif isinstance(msg, Error):
            self.relay.counters["client_errors"] += 1
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s reported error %s: %s", self.where, msg.code, msg.message)
        elif isinstance(msg, Hello):
            self._bad(SessionError("already joined; hello is only valid once",
                                   code="already_joined"))
        else:
            self._bad(SessionError(f"{msg.TYPE} is sent by the relay only",
                                   code="unexpected_type"))

    def _reply(self, msg: Message) -> None:
        if self.peer is not None and not self.peer.outbox.put_ordered(msg):
            self.relay.counters["replies_dropped"] += 1

    def _bad(self, err: ProtocolError | SessionError) -> None:
        """A per-message error: reply, count, close past the budget."""
        peer = self.peer
        if peer is None:
            raise err
        peer.bad_messages += 1
        self.relay.counters[f"bad_{err.code}"] += 1
        if not self.warned:
            self.warned = True
            log.warning("%s %s: %s: %s (error sent, connection kept)", self.link.framing,
                        self.where, err.code, err)
        elif log.isEnabledFor(logging.DEBUG):
            log.debug("%s: %s: %s", self.where, err.code, err)
        if peer.bad_messages > self.cfg.bad_message_budget:
            over = RemoteProtocolError(f"more than {self.cfg.bad_message_budget} bad "
                                       "messages", code="too_many_errors")
            over.close_code = 1008
            raise over
        self._reply(Error(code=err.code, message=str(err), fatal=False))

    # -------------------------------------------------------------- periodic

    async def _tick(self) -> None:
        """Clock pings (burst, then periodic) and the stats push for this peer."""
        peer, session = self.peer, self.session
        if peer is None or session is None:
            return
        cfg = self.cfg
        loop = asyncio.get_running_loop()
        station = peer.role != "observer"
        if station:
            for _ in range(cfg.ping_burst):
                self._ping()
                await asyncio.sleep(cfg.ping_burst_spacing_s)
        next_ping = loop.time() + cfg.ping_interval_s
        next_stats = loop.time() + cfg.stats_interval_s
        while not peer.outbox.closed:
            await asyncio.sleep(max(0.0, min(next_ping if station else next_stats,
                                             next_stats) - loop.time()))
            now = loop.time()
            if station and now >= next_ping:
                self._ping()
                next_ping += cfg.ping_interval_s
                if next_ping < now:
                    next_ping = now + cfg.ping_interval_s
            if now >= next_stats:
                metrics = session_metrics(session, peer.role)
                peer.outbox.put_control_latest("stats", Stats(scope="relay", time_us=now_us(),
                                                              metrics=metrics))
                next_stats += cfg.stats_interval_s
                if next_stats < now:
                    next_stats = now + cfg.stats_interval_s

    def _ping(self) -> None:
        peer = self.peer
        if peer is None:
            return

        def build(t0_us: int) -> ClockPing:
            return ClockPing(ping_id=peer.next_ping(t0_us), t0_us=t0_us)

        peer.outbox.put_control_latest("clock_ping", ClockPing(), build=build)

    # -------------------------------------------------------------- ending

    async def shutdown(self) -> None:
        """Relay shutdown: bye, drain the writer (bounded), close with 1001."""
        if self.peer is not None and self.writer is not None:
            self.peer.outbox.put_ordered(Bye(reason="relay shutting down"), force=True)
            self.peer.outbox.closed = True
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                    await asyncio.shield(self.writer)
        with contextlib.suppress(Exception):
            async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                await self.link.close(1001, "relay shutting down")

    async def _writer_failed(self, err: BaseException) -> None:
        if not isinstance(err, ConnectionClosed | ConnectionError | OSError):
            log.error("%s: writer failed: %r", self.where, err)  # a relay bug, not the peer's
        elif log.isEnabledFor(logging.DEBUG):
            log.debug("%s: write failed: %s", self.where, err)
        if self.peer is not None:
            self.peer.outbox.closed = True
        # unblock the reader so the connection ends
        with contextlib.suppress(Exception):
            await self.link.close(1011, "write failed")

    async def _fatal(self, err: ProtocolError | SessionError) -> None:
        """Log once, send a fatal error (best effort); the caller closes."""
        self.relay.counters[f"fatal_{err.code}"] += 1
        log.warning("%s %s closed: %s: %s (close %d)", self.link.framing, self.where,
                    err.code, err, err.close_code)
        msg = Error(code=err.code, message=str(err), fatal=True)
        if self.peer is not None:
            self.peer.outbox.put_ordered(msg, force=True)
            self.peer.outbox.closed = True
            return
        with contextlib.suppress(Exception):
            async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                await self.link.write([self.conn.encode(msg)])

    async def _teardown(self, close_code: int, reason: str) -> None:
        if self.ticker is not None:
            self.ticker.cancel()
            await asyncio.gather(self.ticker, return_exceptions=True)
        if self.peer is not None and self.session is not None:
            self.relay._drop_peer(self.session, self.peer)
            log.info("left %s (%s)", self.where, reason)
        if self.writer is not None and self.peer is not None:
            self.peer.outbox.closed = True
            self.peer.outbox.wakeup.set()
            try:
                async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                    await self.writer
            except (TimeoutError, asyncio.CancelledError):
                self.writer.cancel()
                await asyncio.gather(self.writer, return_exceptions=True)
        with contextlib.suppress(Exception):
            async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                await self.link.close(close_code, reason)


async def serve_forever(config: RelayConfig,
                        started: Callable[[RelayServer], None] | None = None) -> None:
    """Run a relay until SIGINT or SIGTERM, then shut it down gracefully.

    Args:
        config: resolved settings.
        started: called once the listeners are bound (e.g. to print the ports).
    """
    relay = RelayServer(config)
    await relay.start()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if started is not None:
        started(relay)
    try:
        await stop.wait()
        log.info("relay shutting down")
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        await relay.close()
