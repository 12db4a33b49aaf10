"""The Tele-Touch relay: asyncio glue around the sans-I/O peer sessions, sessions and ledgers.

The wire contract (transports, handshake, clock exchange, forwarding policy, stats, errors
and close codes) is ``docs/protocol.md``. Who decides what:

* :class:`~shared.protocol.peer_session.PeerSession`, one per connection: the handshake,
  clock pings and pongs, observer rules, the error budget, the close decisions, and the
  outbox (latest-wins slots and a bounded ordered queue, ``Message.POLICY``);
* :class:`relay_server.session.Session`: routing between the peers of a session, with
  the latency ledgers; :class:`relay_server.auth.TokenAuthority`: tokens;
* :mod:`relay_server.wire`: each socket as an asyncio protocol (WebSocket through
  websockets' Sans-I/O protocol, length-prefixed TCP); received messages are handled in the
  callback that read them;
* this module: listeners (WebSocket on ``port``, which also answers ``GET /status`` and
  ``GET /metrics``; length-prefixed TCP on ``tcp_port``), and per connection the handling of
  what it receives (:meth:`_Connection._received`), direct writes of the forwards, one writer
  task (for a peer whose socket is behind: a slow peer only fills its own outbox) and one
  ticker task (hello timeout, clock pings, the ``stats`` push).

Each bad connection is logged once at WARNING, without a traceback. WebSocket messages
above twice the limit are refused by the WebSocket layer itself (close 1009, no ``error``).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import hmac
import itertools
import json
import logging
import secrets
import signal
import ssl
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from relay_server.auth import TokenAuthority, load_token_file
from relay_server.config import RelayConfig
from relay_server.health import HEALTH_PATH
from relay_server.metrics import prometheus_text, session_metrics, session_status
from relay_server.session import Peer, Session
from relay_server.view import RelayViewHub
from relay_server.wire import Admission, TcpWire, Wire, WsWire
from shared.errors import (
    AuthError,
    ConfigError,
    LimitError,
    ProtocolError,
    ReplacedError,
    SessionError,
)
from shared.loop_watchdog import loop_watchdog
from shared.memlock import MemoryLock, memory_locked
from shared.protocol import Hello, Stats, Welcome
from shared.protocol.peer_session import (
    ClockSampled,
    DataReceived,
    HelloReceived,
    PeerEvent,
    PeerSession,
    PeerSettings,
    StatsReported,
)
from shared.sd_notify import service
from shared.timebase import now_us
from shared.view import ViewAddress, ViewServer, ViewServerConfig, parse_view_address
from shared.view.server import token_authorizer

if TYPE_CHECKING:
    from relay_server.cluster import ClusterLink
    from relay_server.wire import _Responder

__all__ = ["RelayServer", "serve_forever"]

log = logging.getLogger(__name__)

_CLOSE_TIMEOUT_S = 2.0
_LOOPBACK_HOSTS = frozenset({"127.0.0.1", "::1", "localhost"})


class _RedactAuthorization(logging.Filter):
    """websockets logs every request header at DEBUG: hide the status bearer token."""

    def filter(self, record: logging.LogRecord) -> bool:
        if "authorization" in record.getMessage().lower():
            record.msg, record.args = "< Authorization: [redacted]", None
        return True


#: the WebSocket layer's logger (its DEBUG header dump goes through the redaction filter)
_WS_LOG = logging.getLogger("relay_server.websockets")
_WS_LOG.addFilter(_RedactAuthorization())
#: after a fatal error on TCP, read (and discard) the client's input this long before the
#: close, so the error is not destroyed by a reset (less than _CLOSE_TIMEOUT_S)
_TCP_LINGER_S = 1.0
_EVENTS_PER_FLUSH = 32  # messages of one TCP chunk routed before their forwards are written
#: a connection's opening (its TLS handshake and WebSocket upgrade, where it has them) must
#: be done within this time of the accept
_OPEN_TIMEOUT_S = 10.0
#: high-water mark of a WebSocket connection's write buffer
_WS_WRITE_LIMIT = 256 * 1024


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
        self.auth = TokenAuthority(tokens, config.secret, allow_any=config.allow_any_token,
                                   allow_legacy=config.allow_legacy_tokens)
        self.sessions: dict[str, Session] = {}
        self.counters: Counter[str] = Counter()
        self.peer_settings = PeerSettings(
            max_message_bytes=config.max_message_bytes,
            max_hello_bytes=min(config.max_hello_bytes, config.max_message_bytes),
            rate_limit_per_s=config.rate_limit_per_s, rate_limit_burst=config.rate_limit_burst,
            ordered_queue_len=config.ordered_queue_len,
            bad_message_budget=config.bad_message_budget,
            hello_timeout_us=round(config.hello_timeout_s * 1e6),
            ping_interval_us=round(config.ping_interval_s * 1e6), ping_burst=config.ping_burst,
            ping_burst_spacing_us=round(config.ping_burst_spacing_s * 1e6),
            stats_interval_us=round(config.stats_interval_s * 1e6),
            silence_timeout_us=round(config.silence_timeout_s * 1e6))
        self._peer_ids = itertools.count(1)
        self._ws_server: asyncio.Server | None = None
        self._tcp_server: asyncio.Server | None = None
        self._handlers: set[asyncio.Task[Any]] = set()
        #: fire-and-forget tasks (closing replaced connections), kept referenced
        self._background: set[asyncio.Task[Any]] = set()
        self._connections: set[_Connection] = set()
        #: connections with something queued to write directly (see _Connection._queued)
        self._to_flush: dict[_Connection, None] = {}
        self._flush_scheduled = False
        self._per_ip: Counter[str] = Counter()  # open connections per address
        self.tls = _server_tls_context(config)
        self._admission = Admission(per_address=config.max_connections_per_ip,
                                    total=config.max_connections,
                                    open_timeout_s=_OPEN_TIMEOUT_S, tls=self.tls,
                                    on_refused=self._refused_at_accept)
        #: every accepted socket (also those still in the TLS or WebSocket handshake)
        self._wires: set[Wire] = self._admission.wires
        self._closing = False
        #: the observers' live view (``config.view``), started by :meth:`start`
        self.view_hub: RelayViewHub | None = None
        self.view_server: ViewServer | None = None
        #: the link to the other workers of a clustered relay (relay_server.cluster)
        self.cluster: ClusterLink | None = None
        #: the process's memory lock when :func:`serve_forever` runs the relay (``/status``)
        self.memory_lock: MemoryLock | None = None

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Bind the WebSocket and TCP listeners."""
        cfg = self.config
        if cfg.allow_any_token:
            log.warning("relay accepts ANY token (--allow-any-token): development only")
        loop = asyncio.get_running_loop()
        hello_limit = 2 * self.peer_settings.max_hello_bytes

        def ws_wire() -> WsWire:
            return WsWire(self._serve, self._admission, http=self._process_http,
                          serving=lambda: not self._closing, max_size=hello_limit,
                          write_limit=_WS_WRITE_LIMIT, logger=_WS_LOG)

        def tcp_wire() -> TcpWire:
            return TcpWire(self._serve, self._admission, linger_s=_TCP_LINGER_S)

        # plain listeners on both ports: with TLS, each wire runs its handshake itself,
        # once the admission has counted it (see relay_server.wire)
        self._ws_server = await loop.create_server(
            ws_wire, cfg.host, cfg.port, reuse_port=cfg.reuse_port or None)
        self._tcp_server = await loop.create_server(
            tcp_wire, cfg.host, cfg.resolved_tcp_port, reuse_port=cfg.reuse_port or None)
        ws, tcp = ("wss", "tls") if self.tls is not None else ("ws", "tcp")
        log.info("relay listening: %s://%s:%d (status: /status, /metrics), %s://%s:%d",
                 ws, cfg.host, self.ws_port, tcp, cfg.host, self.tcp_port)
        loopback = cfg.host in _LOOPBACK_HOSTS
        if not cfg.status_token:
            # public on a loopback bind only to this host: INFO; reachable from outside: WARNING
            log.log(logging.INFO if loopback else logging.WARNING,
                    "/status and /metrics are public on %s (session ids, peers, latencies): "
                    "set status_token to require 'Authorization: Bearer ...'", cfg.host)
        if self.tls is None and not loopback:
            log.warning("relay serves plain ws:// and tcp:// on %s: tokens and data cross "
                        "the network in clear unless a TLS proxy is in front "
                        "(--tls-cert/--tls-key; docs/security.md)", cfg.host)
        if cfg.view.strip():
            try:
                await self._start_view(parse_view_address(cfg.view))
            except ConfigError:
                await self.close()
                raise

    async def _start_view(self, address: ViewAddress) -> None:
        """Serve the observers' live view (session + observer token per browser)."""
        hub = RelayViewHub()

        def check(session: str, token: str) -> int | None:
            # a v2 observer token only: a legacy token names no role (a station's would
            # open the view); its expiry closes the browser when it passes
            return self.auth.check(session, token, "observer", legacy=False)

        server = ViewServer(None, ViewServerConfig(), source_for=hub.source,
                            authorize=token_authorizer(check, (AuthError,)))
        await server.start(address.host, address.port)
        self.view_hub, self.view_server = hub, server
        log.info("relay live view for observers: http://%s:%d/#session=SESSION&token=TOKEN",
                 address.host, server.port)
        if self.tls is None and not address.is_loopback:
            log.warning("the relay's live view on %s is plain http: observer tokens cross the "
                        "network in clear unless a TLS proxy is in front", address.host)

    @property
    def ws_port(self) -> int:
        """The bound WebSocket port."""
        if self._ws_server is None:
            raise RuntimeError("relay not started")
        return int(self._ws_server.sockets[0].getsockname()[1])

    @property
    def tcp_port(self) -> int:
        """The bound TCP port."""
        if self._tcp_server is None:
            raise RuntimeError("relay not started")
        return int(self._tcp_server.sockets[0].getsockname()[1])

    async def close(self) -> None:
        """Say bye to every peer, close all connections and listeners, wait for handlers."""
        self._closing = True
        if self.view_server is not None:
            await self.view_server.close()
        if self._tcp_server is not None:
            self._tcp_server.close()
        if self._ws_server is not None:
            self._ws_server.close()
        await asyncio.gather(*(conn.shutdown() for conn in list(self._connections)),
                             return_exceptions=True)
        if self._handlers:
            _, pending = await asyncio.wait(set(self._handlers), timeout=_CLOSE_TIMEOUT_S)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
        wires = list(self._wires)  # still in the handshake, or a handler that hung
        for wire in wires:
            wire.abort()
        await asyncio.gather(*(wire.gone(_CLOSE_TIMEOUT_S) for wire in wires))
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
        doc = {"time_us": now_us(), "sessions": {sid: session_status(s) for sid, s
                                                 in sorted(self.sessions.items())},
               "counters": dict(self.counters),
               "ports": {"ws": self.ws_port, "tcp": self.tcp_port}}
        if self.cluster is not None:
            doc["cluster"] = self.cluster.status()
        if self.memory_lock is not None:
            doc["memory_lock"] = self.memory_lock.to_dict()
        return doc

    def _process_http(self, connection: _Responder, request: Request) -> Response | None:
        # a single-valued header given twice (Authorization) is a client's mistake: 400,
        # never an exception out of here (a 500 and a traceback per request)
        if len(request.headers.get_all("Authorization")) > 1:
            self.counters["http_bad_request"] += 1
            return _http_response(connection, 400, "Tele-Touch relay: bad request\n",
                                  "text/plain; charset=utf-8")
        path = request.path.split("?", 1)[0]
        if path == HEALTH_PATH:  # liveness for a container's probe: no token, no figures
            connection.quiet()  # every 30 s: not two INFO lines each time
            return _http_response(connection, 200, "ok\n", "text/plain; charset=utf-8")
        if path in ("/status", "/metrics") and not self._status_allowed(request):
            self.counters["status_unauthorized"] += 1
            response = _http_response(connection, 401, "Tele-Touch relay: /status and "
                                      "/metrics need 'Authorization: Bearer <status_token>'\n",
                                      "text/plain; charset=utf-8")
            response.headers["WWW-Authenticate"] = 'Bearer realm="teletouch-relay"'
            return response
        if path == "/status":
            body = json.dumps(self.status(), allow_nan=False, indent=1)
            return _http_response(connection, 200, body, "application/json")
        if path == "/metrics":
            return _http_response(connection, 200, prometheus_text(self.sessions,
                                                                   dict(self.counters)),
                                  "text/plain; version=0.0.4; charset=utf-8")
        # Connection is a list header: several lines are one list (as websockets reads it)
        if "upgrade" not in ",".join(request.headers.get_all("Connection")).lower():
            return _http_response(connection, 404, "Tele-Touch relay: WebSocket endpoint; "
                                  "see /status, /metrics and /healthz\n",
                                  "text/plain; charset=utf-8")
        return None

    def _status_allowed(self, request: Request) -> bool:
        expected = self.config.status_token
        if not expected:
            return True
        given = ",".join(request.headers.get_all("Authorization"))  # one (checked above)
        scheme, _, token = given.partition(" ")
        return scheme.lower() == "bearer" and hmac.compare_digest(
            token.strip().encode(), expected.encode())

    # ------------------------------------------------------------------ connections

    async def _serve(self, transport: Wire, host: str) -> None:
        """Serve one open connection (a :class:`Wire`'s task) until it ends."""
        task = asyncio.current_task()
        if task is not None:
            self._handlers.add(task)
        conn = _Connection(self, transport)
        self._connections.add(conn)
        self._per_ip[host] += 1
        try:
            refusal = self._connection_limit(host)
            if refusal is not None:
                self.counters["refused_connections"] += 1
                conn.protocol.fail(refusal)
            await conn.run()
        finally:
            self._connections.discard(conn)
            self._per_ip[host] -= 1
            if self._per_ip[host] <= 0:
                del self._per_ip[host]
            if task is not None:
                self._handlers.discard(task)
            await transport.close()

    def _refused_at_accept(self) -> None:
        self.counters["refused_at_accept"] += 1

    def _connection_limit(self, host: str) -> LimitError | None:
        """The refusal of a new connection from ``host`` (already counted), or None."""
        cfg = self.config
        if len(self._connections) > cfg.max_connections:
            return LimitError(f"the relay has {cfg.max_connections} connections open; "
                              "try again later", code="too_many_connections", close_code=1013)
        if self._per_ip[host] > cfg.max_connections_per_ip:
            return LimitError(f"{cfg.max_connections_per_ip} connections from {host} are "
                              "open; try again later", code="too_many_connections",
                              close_code=1013)
        return None

    def flush_soon(self, conn: _Connection) -> None:
        """Write ``conn``'s outbox directly at the next :meth:`flush`: right after the
        batch of messages being routed, or from the event loop when the put came from
        elsewhere (a ticker's ping or stats)."""
        self._to_flush[conn] = None
        if not self._flush_scheduled:
            self._flush_scheduled = True
            asyncio.get_running_loop().call_soon(self._scheduled_flush)

    def _scheduled_flush(self) -> None:
        self._flush_scheduled = False
        self.flush()

    def flush(self) -> None:
        """Write every outbox given to :meth:`flush_soon` since the last flush."""
        if self._to_flush:
            conns, self._to_flush = self._to_flush, {}
            for conn in conns:
                conn.flush_now()

    def _join(self, hello: Hello, conn: _Connection) -> tuple[Session, Peer]:
        if self._closing:
            raise SessionError("relay shutting down", code="shutdown")
        self.auth.check(hello.session, hello.token, hello.role)
        if self.cluster is not None:
            self.cluster.check_role(hello.session, hello.role)
        session = self.sessions.get(hello.session)
        if session is None:
            if len(self.sessions) >= self.config.max_sessions:
                raise SessionError(f"relay is full ({self.config.max_sessions} sessions)",
                                   code="relay_full")
            session = Session(hello.session, self.config.ledger_window)
            session.remote = self.cluster
        peer = Peer(peer_id=next(self._peer_ids), session_id=hello.session, role=hello.role,
                    name=hello.name, transport=conn.transport.framing,
                    outbox=conn.protocol.outbox, window=self.config.ledger_window,
                    clock=conn.protocol.clock, resume_secret=secrets.token_hex(16),
                    evict=conn.evict, request_stats=conn.request_stats)
        replaced = session.join(peer, hello.resume)
        if replaced is not None:
            self.counters["resumed"] += 1
            log.info("session %s: %s reconnected; its previous connection (peer %d) replaced",
                     hello.session, hello.role, replaced.peer_id)
        self.sessions[hello.session] = session
        if self.cluster is not None:
            self.cluster.changed()
        return session, peer

    def _drop_peer(self, session: Session, peer: Peer) -> None:
        session.leave(peer)
        if session.empty and self.sessions.get(session.session_id) is session:
            del self.sessions[session.session_id]
        if self.cluster is not None:
            self.cluster.changed()


def _server_tls_context(config: RelayConfig) -> ssl.SSLContext | None:
    """The relay's TLS context from ``tls_cert``/``tls_key`` (None without them).

    Raises:
        ConfigError: unreadable files, or a key that does not match the certificate.
    """
    if config.tls_cert is None or config.tls_key is None:
        return None
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(config.tls_cert, config.tls_key)
    except (OSError, ssl.SSLError) as err:
        raise ConfigError(f"cannot load the relay's TLS certificate {config.tls_cert} / key "
                          f"{config.tls_key}: {err}") from err
    return ctx


def _http_response(connection: _Responder, status: int, body: str,
                   content_type: str) -> Response:
    response = connection.respond(status, body)
    headers = Headers(response.headers)
    del headers["Content-Type"]
    headers["Content-Type"] = content_type
    return Response(response.status_code, response.reason_phrase, headers, response.body)


class _Connection:
    """The life of one connection: reader, writer task, ticker task, teardown."""

    def __init__(self, relay: RelayServer, transport: Wire) -> None:
        self.relay = relay
        self.transport = transport
        self.protocol = PeerSession(transport.framing, relay.peer_settings, now_us(),
                                    relay.counters)
        self.wake = asyncio.Event()
        self.protocol.outbox.wakeup = self._queued
        #: the writer task took frames and is writing them (a direct write must wait)
        self._writing = False
        self.session: Session | None = None
        self.peer: Peer | None = None
        self.writer: asyncio.Task[None] | None = None
        self.ticker: asyncio.Task[None] | None = None

    async def run(self) -> None:
        """Serve until the peer leaves or the protocol decides to close."""
        ps = self.protocol
        self.writer = asyncio.create_task(self._write_loop(), name="relay-writer")
        self._restart_ticker()
        reason = "peer closed"
        try:
            if not ps.closing:
                # received messages are handled in the callback that read them (_received)
                self.transport.receive(self._received)
                await self.transport.ended.wait()
        finally:
            if self.ticker is not None:
                self.ticker.cancel()
                await asyncio.gather(self.ticker, return_exceptions=True)
            if ps.closing:
                reason = ps.close_reason
            await self._teardown(ps.close_code or 1000, reason)

    def _received(self, data: bytes | str) -> None:
        """One WebSocket message or TCP chunk: parse, check, route (see :meth:`_handle`)."""
        ps = self.protocol
        ps.receive_data(data, now_us())
        events = ps.events_received()
        # what they queued for idle peers is written now, every _EVENTS_PER_FLUSH messages
        # (a TCP chunk can hold hundreds: an ordered burst must not fill a queue before
        # the socket takes any of it). Deferring the write to the end of the event-loop
        # iteration, to batch several senders' messages in one write, let a newer state in
        # the same read replace an unsent one (latest-wins drops: 150 in 4 s at 5 sessions,
        # 3 % of the platform states) for a few % of CPU
        if len(events) <= _EVENTS_PER_FLUSH:
            self._handle(events)
            self.relay.flush()
        else:
            for start in range(0, len(events), _EVENTS_PER_FLUSH):
                self._handle(events[start:start + _EVENTS_PER_FLUSH])
                self.relay.flush()
        if ps.closing:
            self.transport.stop()

    def _handle(self, events: list[PeerEvent]) -> None:
        ps, peer, session = self.protocol, self.peer, self.session
        for ev in events:
            if isinstance(ev, DataReceived):
                if peer is None or session is None:
                    continue
                reply = session.route(peer, ev.message, ev.t_in_us, ev.wire)
                if reply is not None and reply.code == "wrong_direction":
                    ps.reject(SessionError(reply.message, code=reply.code))
                    continue  # refused: not the session's data, not shown in the view
                if self.relay.view_hub is not None:
                    self.relay.view_hub.observe(session, ev.message, ev.t_in_us)
                if reply is not None:
                    ps.reply(reply)
            elif isinstance(ev, HelloReceived):
                self._accept(ev.hello)
                peer, session = self.peer, self.session
            elif isinstance(ev, ClockSampled) and peer is not None:
                peer.record_clock_exchange(ev.t0_us, ev.t1_us, ev.sample.delay_us)
                if ev.stepped:
                    self._restart_ticker()  # the burst starts now
                # while this station's offset is being (re)measured, every sample goes to
                # everyone in the session at once: the other station needs it to age-check
                # what it receives and would otherwise wait for its periodic stats (1 s)
                if session is not None and (ev.stepped or ev.settling):
                    for other in (*session.stations.values(), *session.observers.values()):
                        if other.request_stats is not None:
                            other.request_stats()
            elif isinstance(ev, StatsReported) and peer is not None:
                peer.reported = ev.metrics
        if peer is not None:
            peer.received, peer.bad_messages = ps.received, ps.bad_messages

    def _accept(self, hello: Hello) -> None:
        try:
            self.session, self.peer = self.relay._join(hello, self)
        except (ProtocolError, SessionError) as err:
            self.protocol.fail(err)
            return
        cfg = self.relay.config
        self.relay.counters["joined"] += 1
        log.info("joined %s (%s, %s) name=%r", self.protocol.where, self.transport.framing,
                 self.peer.peer_id, hello.name)
        self.protocol.accept(Welcome(session=hello.session, role=hello.role,
                                     server_time_us=now_us(),
                                     ping_interval_s=cfg.ping_interval_s,
                                     max_message_bytes=cfg.max_message_bytes,
                                     resume=self.peer.resume_secret,
                                     stats_interval_s=cfg.stats_interval_s), now_us())
        # the hello limit is over: full size now (WebSocket; TCP's parser is the session's)
        self.transport.set_receive_limit(2 * cfg.max_message_bytes)
        self._restart_ticker()  # the schedule changed: pings and stats instead of the timeout
        # what the peer sent behind its hello has been processed by accept()
        self._handle(self.protocol.events_received())

    def _restart_ticker(self) -> None:
        if self.ticker is not None:
            self.ticker.cancel()
        self.ticker = asyncio.create_task(self._tick_loop(), name="relay-ticker")

    async def _tick_loop(self) -> None:
        ps = self.protocol
        while not ps.closing:
            await asyncio.sleep(max(0.0, (ps.next_tick_us() - now_us()) / 1e6))
            if ps.tick(now_us()) and self.session is not None and self.peer is not None:
                ps.send_stats(Stats(scope="relay", time_us=now_us(),
                                    metrics=session_metrics(self.session, self.peer.role)))

    def _queued(self) -> None:
        """Something was put in the outbox. When the writer task is idle and the socket
        took everything before (the common case), the relay writes it directly once the
        current batch of received messages is routed (:meth:`RelayServer.flush`: no task
        switch per forwarded message, and several messages for this peer in one write);
        else the writer task is woken: it waits for the socket (flow control) while newer
        state messages replace unsent ones in their latest-wins slots."""
        if self._writing or self.protocol.outbox.closed or not self.transport.ready():
            self.wake.set()
        else:
            self.relay.flush_soon(self)

    def flush_now(self) -> None:
        """Write what the outbox holds without waiting (see :meth:`_queued`)."""
        if self._writing or self.protocol.outbox.closed or not self.transport.ready():
            self.wake.set()
            return
        try:
            frames = self.protocol.data_to_send(now_us)
            if frames:
                self.transport.write_nowait(frames)
        except Exception as err:  # not expected once ready(): handled as a failed write
            # (a relay bug while encoding included: what was taken from the outbox is lost,
            # so the peer is closed; the other peers of this flush are written all the same)
            log.error("%s: direct write failed: %r", self.protocol.where, err)
            self.protocol.outbox.closed = True
            self.wake.set()
            task = asyncio.get_running_loop().create_task(
                self.transport.close(1011, "write failed"))
            self.relay._background.add(task)
            task.add_done_callback(self.relay._background.discard)

    async def _write_loop(self) -> None:
        ps, outbox = self.protocol, self.protocol.outbox
        try:
            while True:
                await self.wake.wait()
                self.wake.clear()
                self._writing = True
                frames = ps.data_to_send(now_us)
                if frames:
                    await self.transport.write(frames)
                self._writing = False
                if outbox.closed and not len(outbox):
                    break
        except asyncio.CancelledError:
            raise
        except Exception as err:  # transport failures of any kind end this peer only
            if not isinstance(err, ConnectionError | OSError):
                log.error("%s: writer failed: %r", ps.where, err)  # a relay bug
            elif log.isEnabledFor(logging.DEBUG):
                log.debug("%s: write failed: %s", ps.where, err)
            outbox.closed = True
            await self.transport.close(1011, "write failed")  # unblocks the reader
            return
        if ps.closing:
            await self.transport.close(ps.close_code or 1000, ps.close_reason)

    def request_stats(self) -> None:
        """Push ``stats`` at once (see :meth:`PeerSession.stats_soon`)."""
        self.protocol.stats_soon(now_us())
        self._restart_ticker()

    def evict(self) -> None:
        """A newer connection of the same station replaced this one: tell it (if it still
        listens) and close. The peer is already out of its session."""
        self.session, self.peer = None, None  # the teardown must not drop the new peer
        self.protocol.fail(ReplacedError("a newer connection of this station resumed the "
                                         "session"))
        self.wake.set()
        # a silent (blackholed) socket may never drain the writer: close it regardless
        task = asyncio.get_running_loop().create_task(
            self.transport.close(ReplacedError.close_code, "replaced"))
        self.relay._background.add(task)
        task.add_done_callback(self.relay._background.discard)

    async def shutdown(self) -> None:
        """Relay shutdown: bye, drain the writer (bounded), close with 1001."""
        self.protocol.shutdown()
        self.wake.set()
        if self.writer is not None:
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                    await asyncio.shield(self.writer)
        await self.transport.close(1001, "relay shutting down")

    async def _teardown(self, close_code: int, reason: str) -> None:
        if self.peer is not None and self.session is not None:
            self.relay._drop_peer(self.session, self.peer)
            log.info("left %s (%s)", self.protocol.where, reason)
        if self.writer is not None:
            self.protocol.outbox.closed = True
            self.wake.set()
            try:
                async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                    await self.writer
            except (TimeoutError, asyncio.CancelledError):
                self.writer.cancel()
                await asyncio.gather(self.writer, return_exceptions=True)
        await self.transport.close(close_code, reason)


#: gen-0 collection every this many allocations (Python's default is 700), gen 1 every 50 of
#: those, gen 2 every 1,000 gen-1 runs: a forwarded message allocates a few objects, and with
#: the defaults the relay's tail latency was its garbage collector's pauses
_GC_THRESHOLDS = (50_000, 50, 1_000)


def _tune_gc_for_latency() -> None:
    """Freeze what start-up allocated and collect rarely (the relay process only).

    Objects that live as long as the process (modules, settings, listeners) are moved out of
    the collector's way (``gc.freeze``) and collections run less often, so that forwarding is
    not paused by sweeps of them: in a paired run the relay's added p99 at one session went from
    1.8-6.2 ms to 1.0-1.4 ms (the previous release: 1.1-1.6 ms), with the same p50.
    """
    gc.collect()
    gc.freeze()
    gc.set_threshold(*_GC_THRESHOLDS)


async def serve_forever(config: RelayConfig,
                        started: Callable[[RelayServer], None] | None = None) -> None:
    """Run a relay until SIGINT or SIGTERM, then shut it down gracefully. While it serves,
    a stuck event loop ends this process (``hang_timeout_s``, :mod:`shared.loop_watchdog`):
    run it in a process of its own, not in a test runner's.

    Args:
        config: resolved settings.
        started: called once the listeners are bound (e.g. to print the ports).
    """
    with memory_locked(config.lock_memory) as memory_lock:
        relay = RelayServer(config)
        relay.memory_lock = memory_lock
        await _serve(relay, config, started)


async def _serve(relay: RelayServer, config: RelayConfig,
                 started: Callable[[RelayServer], None] | None) -> None:
    await relay.start()
    if config.nats_url:
        from relay_server.cluster import ClusterLink

        relay.cluster = ClusterLink(config, relay.sessions, relay.counters,
                                    lambda: {"ws": relay.ws_port, "tcp": relay.tcp_port})
        try:
            await relay.cluster.start()
        except BaseException:
            await relay.close()
            raise
    _tune_gc_for_latency()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if started is not None:
        started(relay)
    try:
        # systemd (Type=notify): ready now; its watchdog pinged from this loop until the stop;
        # this loop stuck for hang_timeout_s: stacks written, exit 1 (to be restarted)
        async with service(f"relay serving: WebSocket port {relay.ws_port}, TCP port "
                           f"{relay.tcp_port}"), loop_watchdog(config.hang_timeout_s):
            await stop.wait()
        log.info("relay shutting down")
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        await relay.close()
        if relay.cluster is not None:
            await relay.cluster.close()
