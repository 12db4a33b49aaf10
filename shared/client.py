"""The station side of the relay link: asyncio glue over the sans-I/O station session.

:class:`StationLink` connects a station (``local``, ``remote`` or ``observer``) to the relay
over WebSocket (``ws://``, ``wss://``) or length-prefixed TCP (``tcp://``) and keeps it up:
it reconnects with exponential backoff and jitter (0.1 s doubling to 0.5 s by default: a
connection attempt costs little, and fresh data must flow within a second of the relay's
return) and resumes transparently: its hello carries the previous connection's ``resume``
secret, so the relay replaces our old connection if it still holds it. Messages queued while
the link was down are dropped at the next welcome, never delivered late;
``link_down_since`` tells the station how long it has been cut off
so it can go to its safe state (100 ms rule).

The protocol itself (hello/welcome, pong answers, the ``station_rx`` hop stamp, the latest
``stats``, liveness, and the per-stream policy of the send queue and the inbox: latest-wins
for state streams, ordered and bounded for the rest) is
:class:`~shared.protocol.station_session.StationSession`; the sockets are
:mod:`shared.transport`. This module only moves bytes, waits and retries.

Refusals that retrying cannot fix are final: a wrong token (:class:`~shared.errors.AuthError`)
and our connection replaced by another one proving our resume secret
(:class:`~shared.errors.ReplacedError`). They are logged once and raised from
``wait_connected``, ``send`` and ``recv``. A role held by another station
(:class:`~shared.errors.RoleTakenError`) is not final: the other may leave, so the link logs
it and keeps retrying (a station never gives up on a transient fault).

Example::

    async with StationLink("ws://relay:8765/", session="lab1", role="local",
                           token=token) as link:
        await link.wait_connected(timeout_s=5.0)
        await link.send(PlatformState(seq=1, ts_us=now_us(), position_mm=(0.0, 0.0, 0.0)))
        async for msg in link.messages():
            ...
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import ssl
from collections import deque
from collections.abc import AsyncIterator, Callable
from typing import Any

from websockets.exceptions import WebSocketException

from shared.errors import (
    AuthError,
    ConfigError,
    ProtocolError,
    ReplacedError,
    RoleTakenError,
    SessionError,
)
from shared.freshness import ClockView, clock_view_from_stats
from shared.link_settings import (
    StationLinkConfig,
    backoff_delay_s,
    client_tls_context,
    parse_link_url,
)
from shared.protocol import (
    DEFAULT_MAX_MESSAGE_BYTES,
    LATEST_WINS_TYPES,
    ROLES,
    Hello,
    Message,
    Stats,
    Welcome,
)
from shared.protocol.station_session import (
    Failed,
    LinkCounters,
    Refused,
    Rejected,
    StationSession,
    Welcomed,
    refusal_for_close_code,
)
from shared.timebase import monotonic_s, now_us
from shared.transport import Transport, TransportClosed, open_client_transport

__all__ = [
    "LATEST_WINS_TYPES",
    "LinkCounters",
    "StationLink",
    "StationLinkConfig",
    "backoff_delay_s",
    "parse_link_url",
]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- the link


class StationLink:
    """A station's resilient connection to the relay (see the module docstring).

    Args:
        url: ``ws://host:port/``, ``wss://host/path`` or ``tcp://host:port``.
        session: session id (``[A-Za-z0-9][A-Za-z0-9_.-]{0,63}``).
        role: ``local``, ``remote`` or ``observer``.
        token: the session token.
        name: a free label the relay shows in its status.
        reconnect_min_s: first reconnect delay.
        reconnect_max_s: largest reconnect delay.
        reconnect_jitter: fraction of each delay removed at random (0 to 1).
        connect_timeout_s: limit for opening the socket and for hello -> welcome.
        liveness_timeout_s: silence after which a connection is treated as dead.
        max_message_bytes: size limit of one message, both directions.
        send_queue_size: bound of the ordered send queue (``send`` waits when full).
        receive_queue_size: bound of ordered messages waiting in the inbox.
        write_buffer_bytes: bytes the socket may buffer before the link holds back; a small
            value keeps latest-wins effective when the link is slow.
        ssl_context: TLS context for ``wss://`` and ``tls://`` (the system default when
            None); :func:`~shared.link_settings.client_tls_context` makes one for a CA file.
        seed: seed of the backoff jitter (None: random).

    Raises:
        ConfigError: bad URL, role or numeric setting.
    """

    def __init__(self, url: str, *, session: str, role: str, token: str, name: str = "",
                 reconnect_min_s: float = 0.1, reconnect_max_s: float = 0.5,
                 reconnect_jitter: float = 0.5, connect_timeout_s: float = 5.0,
                 liveness_timeout_s: float = 3.0,
                 max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
                 send_queue_size: int = 256, receive_queue_size: int = 1024,
                 write_buffer_bytes: int = 16 * 1024,
                 ssl_context: ssl.SSLContext | None = None, seed: int | None = None) -> None:
        self.scheme, self.host, self.port = parse_link_url(url)
        if role not in ROLES:
            raise ConfigError(f"role must be one of {sorted(ROLES)}, got {role!r}")
        if not 0.0 < reconnect_min_s <= reconnect_max_s:
            raise ConfigError("need 0 < reconnect_min_s <= reconnect_max_s")
        if not 0.0 <= reconnect_jitter <= 1.0:
            raise ConfigError("reconnect_jitter must be in [0, 1]")
        if connect_timeout_s <= 0 or liveness_timeout_s <= 0:
            raise ConfigError("timeouts must be positive")
        if min(send_queue_size, receive_queue_size, max_message_bytes) < 1:
            raise ConfigError("queue sizes and max_message_bytes must be >= 1")
        self.url = url
        self.role = role
        self._session = StationSession(
            Hello(role=role, session=session, token=token, name=name),
            max_message_bytes=max_message_bytes, send_queue_size=send_queue_size,
            receive_queue_size=receive_queue_size,
            connect_timeout_us=round(connect_timeout_s * 1e6),
            liveness_timeout_us=round(liveness_timeout_s * 1e6))
        self._reconnect = (reconnect_min_s, reconnect_max_s, reconnect_jitter)
        self._connect_timeout_s = connect_timeout_s
        self._write_buffer_bytes = max(0, write_buffer_bytes)
        self._ssl_context = ssl_context
        self._rng = random.Random(seed)

        self.counters: LinkCounters = self._session.counters
        self.connected = asyncio.Event()
        #: monotonic time (``shared.timebase.monotonic_s``) the link went down; None when up
        self.link_down_since: float | None = monotonic_s()
        #: monotonic time of the last bytes received from the relay (None: never)
        self.last_received_s: float | None = None
        self.final_error: SessionError | None = None
        #: reconnect delays actually waited, most recent last (for diagnostics and tests)
        self.backoff_history_s: deque[float] = deque(maxlen=64)
        self._readable = asyncio.Event()  # the inbox has messages
        self._rx_room = asyncio.Event()  # the inbox's ordered queue has room
        self._tx_ready = asyncio.Event()  # something to write
        self._tx_room = asyncio.Event()  # the ordered send queue has room
        self._tx_room.set()
        self._task: asyncio.Task[None] | None = None
        #: the open connection while one is up (for :meth:`_write_now`)
        self._transport: Transport | None = None
        #: called with ("tx" | "rx", message, wall-clock us) for every message the station
        #: queues with :meth:`send` or takes with :meth:`recv` (a recorder; must not block)
        self.tap: Callable[[str, Message, int], None] | None = None
        self._closing = False
        self._down_logged = False
        self._clock_view: tuple[Stats, ClockView] | None = None

    @classmethod
    def from_config(cls, config: StationLinkConfig, role: str, **overrides: Any) -> StationLink:
        """Build a link from resolved settings (``overrides`` are extra constructor args).

        Raises:
            ConfigError: bad URL, role or setting.
        """
        if config.ca_file is not None and "ssl_context" not in overrides:
            overrides["ssl_context"] = client_tls_context(config.ca_file)
        return cls(config.url, session=config.session, role=role, token=config.token,
                   name=config.name, reconnect_min_s=config.reconnect_min_s,
                   reconnect_max_s=config.reconnect_max_s,
                   connect_timeout_s=config.connect_timeout_s,
                   liveness_timeout_s=config.liveness_timeout_s,
                   max_message_bytes=config.max_message_bytes, **overrides)

    # ------------------------------------------------------------------ lifecycle

    async def __aenter__(self) -> StationLink:
        self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def start(self) -> None:
        """Start connecting in the background (idempotent). Use :meth:`wait_connected`."""
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(
                self._supervise(), name=f"station-link-{self.role}")

    async def close(self, reason: str = "station closing") -> None:
        """Say ``bye`` if connected (best effort), stop reconnecting and close the socket."""
        if self._closing:
            return
        self._closing = True
        if self.connected.is_set():
            with contextlib.suppress(ProtocolError):
                self._session.send_bye(reason)
                self._tx_ready.set()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self._drained(), 0.5)
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        self.connected.clear()
        self._wake_all()

    async def _drained(self) -> None:
        while self._session.outbox.ordered_count and self.connected.is_set():
            await asyncio.sleep(0.005)

    def _wake_all(self) -> None:
        for event in (self._readable, self._tx_room, self._rx_room):
            event.set()

    async def wait_connected(self, timeout_s: float | None = None) -> Welcome:
        """Wait until the relay has welcomed us.

        Raises:
            AuthError, RoleTakenError: the refusal is final.
            TimeoutError: not connected within ``timeout_s``.
        """
        self._raise_if_unusable()
        self.start()
        task = self._task
        if task is None:  # pragma: no cover - start() always sets it
            raise SessionError("the station link did not start", code="closed")
        waiter = asyncio.ensure_future(self.connected.wait())
        try:
            await asyncio.wait({waiter, task}, timeout=timeout_s,
                               return_when=asyncio.FIRST_COMPLETED)
        finally:
            waiter.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await waiter
        self._raise_if_final()
        if task.done() and not task.cancelled() and task.exception() is not None:
            raise SessionError(f"the station link failed: {task.exception()}",
                               code="closed") from task.exception()
        welcome = self.welcome
        if not self.connected.is_set() or welcome is None:
            raise TimeoutError(f"not connected to {self.url} within {timeout_s} s")
        return welcome

    # ------------------------------------------------------------------ status

    @property
    def welcome(self) -> Welcome | None:
        """The relay's latest ``welcome`` (None before the first connection)."""
        return self._session.welcome

    @property
    def latest_stats(self) -> Stats | None:
        """The relay's latest ``stats``."""
        return self._session.latest_stats

    @property
    def is_connected(self) -> bool:
        """True while a welcomed connection is open."""
        return self.connected.is_set()

    def link_down_for_s(self, now_s: float | None = None) -> float:
        """Seconds since the connection was lost (0.0 while connected)."""
        if self.link_down_since is None:
            return 0.0
        return max(0.0, (monotonic_s() if now_s is None else now_s) - self.link_down_since)

    def silent_for_s(self, now_s: float | None = None) -> float:
        """Seconds since anything arrived from the relay (inf if nothing ever did)."""
        if self.last_received_s is None:
            return float("inf")
        return max(0.0, (monotonic_s() if now_s is None else now_s) - self.last_received_s)

    @property
    def clock_offsets_us(self) -> dict[str, int | None]:
        """Station clock minus relay clock per role, from the latest relay ``stats``."""
        metrics = self.latest_stats.metrics if self.latest_stats is not None else {}
        raw = metrics.get("clock_offset_us", {})
        if not isinstance(raw, dict):
            return {}
        return {str(k): (int(v) if isinstance(v, int | float) and not isinstance(v, bool)
                         else None) for k, v in raw.items()}

    @property
    def clock_view(self) -> ClockView | None:
        """The relay's clock offsets and their error bounds as last received on this
        connection (None before the first ``stats`` of the current connection)."""
        stats, rx_us = self._session.latest_stats, self._session.latest_stats_rx_us
        if stats is None or rx_us is None:
            return None
        cached = self._clock_view
        if cached is None or cached[0] is not stats:
            cached = self._clock_view = (stats, clock_view_from_stats(stats.metrics, rx_us))
        return cached[1]

    @property
    def clock_offset_us(self) -> int | None:
        """This station's clock minus the relay's (None until the relay reports it)."""
        return self.clock_offsets_us.get(self.role)

    # ------------------------------------------------------------------ sending

    async def send(self, msg: Message) -> None:
        """Queue ``msg`` for the relay.

        State streams (``Message.POLICY`` latest-wins) replace any not-yet-sent message of
        the same type; other messages are kept in order, waiting for room when
        ``send_queue_size`` are already pending. Messages still queued when the link comes
        back (sent while it was down) are dropped then, never sent late (counted in
        ``dropped_on_reconnect``). The tap records the message as it was queued (a
        ``platform_state`` or tactile frame that replaced an unsent one carries that one's
        motion stamp: :func:`~shared.protocol.carry_motion`).

        Raises:
            LocalProtocolError: ``msg`` is invalid or larger than ``max_message_bytes``.
            AuthError, RoleTakenError: the link was finally refused.
            SessionError: the link is closed.
        """
        queued = self._session.send(msg)
        self._raise_if_unusable()
        while queued is None:
            self._tx_room.clear()
            await self._tx_room.wait()
            self._raise_if_unusable()
            queued = self._session.send(msg)
        if not self._write_now():
            self._tx_ready.set()
        if self.tap is not None:
            self.tap("tx", queued, now_us())

    def _write_now(self) -> bool:
        """Hand what the session has ready to the socket from the caller's own task, when the
        socket takes it at once: no wake-up of the writer task and none of websockets'
        ``send`` machinery per message (the relay's fast path, ``relay_server/wire.py``).
        The session decides what goes and in which order, as for the writer task.

        Returns:
            False when the writer task must do it: not connected, or earlier writes still
            wait in the socket's buffer (flow control, latest-wins replaces meanwhile).
        """
        transport = self._transport
        if transport is None or not transport.ready():
            return False
        frames = []
        while (data := self._session.next_data(now_us())) is not None:
            frames.append(data)
        if frames:
            self._tx_room.set()
            transport.write_nowait(frames)
        return True

    @property
    def pending_sends(self) -> int:
        """Messages queued but not yet handed to the socket."""
        return self._session.pending_sends

    # ------------------------------------------------------------------ receiving

    async def recv(self, timeout_s: float | None = None) -> Message:
        """Return the next message from the relay (data, ``stats``, ``error``, ``bye``).

        Raises:
            TimeoutError: nothing arrived within ``timeout_s``.
            AuthError, RoleTakenError: the link was finally refused.
            SessionError: the link is closed.
        """
        loop = asyncio.get_running_loop()
        deadline = None if timeout_s is None else loop.time() + timeout_s
        while True:
            msg = self._session.next_message()
            if msg is not None:
                self._rx_room.set()
                if self.tap is not None:
                    self.tap("rx", msg, now_us())
                return msg
            self._readable.clear()
            self._raise_if_unusable()
            remaining = None if deadline is None else deadline - loop.time()
            if remaining is not None and remaining <= 0:
                raise TimeoutError(f"no message within {timeout_s} s")
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._readable.wait(), remaining)

    async def messages(self) -> AsyncIterator[Message]:
        """Yield messages as they arrive until the link is closed.

        Raises:
            AuthError, RoleTakenError: the link was finally refused.
        """
        while True:
            try:
                yield await self.recv()
            except SessionError as err:
                if err is self.final_error:
                    raise
                return

    def _raise_if_final(self) -> None:
        if self.final_error is not None:
            raise self.final_error

    def _raise_if_unusable(self) -> None:
        self._raise_if_final()
        if self._closing:
            raise SessionError("the station link is closed", code="closed")

    # ------------------------------------------------------------------ connection loop

    async def _supervise(self) -> None:
        attempt = 0
        taken_logged = False
        while not self._closing:
            try:
                await self._connect_once()
            except (AuthError, ReplacedError) as err:
                self.final_error = err
                log.error("relay %s refused %s/%s for good (%s: %s); not retrying",
                          self.url, self._session.hello.session, self.role,
                          type(err).__name__, err)
                self._wake_all()
                return
            except RoleTakenError as err:
                self.counters.role_taken_refusals += 1
                if not taken_logged:
                    log.warning("relay %s: %s; another station holds the role, retrying "
                                "until it leaves", self.url, err)
                    taken_logged = True
            except (OSError, TimeoutError, SessionError, ProtocolError,
                    WebSocketException) as err:
                if not self._down_logged:
                    log.warning("link to %s unavailable (%s: %s); retrying with backoff",
                                self.url, type(err).__name__, err)
                    self._down_logged = True
                elif log.isEnabledFor(logging.DEBUG):
                    log.debug("reconnect attempt %d failed: %s", attempt, err)
            if self.link_down_since is None:  # we had been welcomed: start afresh
                attempt, taken_logged = 0, False
            if self._session.connection_lost() or self.connected.is_set():
                self.connected.clear()
                self.link_down_since = monotonic_s()
            if self._closing:
                return
            delay = backoff_delay_s(attempt, min_s=self._reconnect[0],
                                    max_s=self._reconnect[1], jitter=self._reconnect[2],
                                    rng=self._rng)
            self.backoff_history_s.append(delay)
            attempt += 1
            await asyncio.sleep(delay)

    async def _connect_once(self) -> None:
        # asyncio.timeout, not wait_for: on Python 3.11 a wait_for cancelled (the link
        # closing) just as the connection opened drops the opened transport, whose socket
        # then stays open until the garbage collector finds it; cancelled here, the connect
        # itself is interrupted and closes what it opened
        async with asyncio.timeout(self._connect_timeout_s):
            transport = await open_client_transport(
                self.scheme, self.host, self.port, self.url,
                max_message_bytes=self._session.max_message_bytes,
                open_timeout_s=self._connect_timeout_s,
                write_buffer_bytes=self._write_buffer_bytes, ssl_context=self._ssl_context)
        writer: asyncio.Task[None] | None = None
        try:
            await transport.write([self._session.connect(transport.framing, now_us())])
            writer = asyncio.get_running_loop().create_task(self._write_loop(transport))
            self._transport = transport
            await self._read_loop(transport)
        finally:
            self._transport = None
            if writer is not None:
                writer.cancel()
                await asyncio.gather(writer, return_exceptions=True)
            await transport.close()

    async def _read_loop(self, transport: Transport) -> None:
        session = self._session
        while True:
            if session.inbox.ordered_full:  # back-pressure: a slow consumer stops reading
                while session.inbox.ordered_full:
                    self._rx_room.clear()
                    await self._rx_room.wait()
                session.reading_resumed(now_us())
            timeout_s = max(0.0, (session.deadline_us() - now_us()) / 1e6)
            try:
                # asyncio.timeout, not wait_for: no task is created per message received
                async with asyncio.timeout(timeout_s):
                    data = await transport.recv()
            except TimeoutError as err:
                silent = session.check_liveness(now_us())
                if silent is None:
                    continue
                what = "relay silent" if silent.welcomed else "no welcome from the relay"
                raise TimeoutError(f"{what} for {silent.silent_for_us / 1e6:.3g} s") from err
            except TransportClosed as err:
                raise refusal_for_close_code(err.close_code, str(err)) or err from err
            self.last_received_s = monotonic_s()
            session.receive_data(data.encode() if isinstance(data, str) else data, now_us())
            for event in session.events_received():
                if isinstance(event, Welcomed):
                    self.link_down_since = None
                    self._down_logged = False
                    self.connected.set()
                    log.info("connected to %s as %s in session %s", self.url, self.role,
                             event.welcome.session)
                elif isinstance(event, Refused | Failed):
                    raise event.error
                elif isinstance(event, Rejected) and (self.counters.rejected_rx == 1
                                                      or log.isEnabledFor(logging.DEBUG)):
                    log.warning("dropped an invalid message from the relay: %s", event.error)
            if len(session.inbox):
                self._readable.set()
            if not self._write_now():  # pongs, and what was queued while the link was down
                self._tx_ready.set()

    async def _write_loop(self, transport: Transport) -> None:
        try:
            while True:
                data = self._session.next_data(now_us())
                if data is None:
                    self._tx_ready.clear()
                    await self._tx_ready.wait()
                    continue
                self._tx_room.set()
                await transport.write([data])
        except TransportClosed:
            await transport.close()  # ends the read loop too
