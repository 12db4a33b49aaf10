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

The backoff starts afresh only after a connection stayed up for a while
(``reconnect_max_s``, at least 2 s): a relay that welcomes and then closes at once (its rate
limit, say) is retried with growing delays, not flooded. A connection is presumed dead after
``liveness_timeout_s`` of silence, or 2.5 times the ``ping_interval_s`` the relay announced in
its welcome when that is longer (a relay that pings slowly does not make an idle link flap;
for an observer, which is not pinged, its ``stats_interval_s``); a
dead connection is marked down at once and dropped without a close handshake.

Refusals that retrying cannot fix are final: a wrong token (:class:`~shared.errors.AuthError`;
a version-2 token the relay calls expired, :class:`~shared.errors.TokenExpiredError`, only
when this station's wall clock agrees: otherwise one of the clocks is wrong and the link
retries with backoff up to :data:`CLOCK_RETRY_MAX_S`, logging the disagreement at ERROR),
our connection replaced by another one proving our resume secret
(:class:`~shared.errors.ReplacedError`, over WebSocket and raw TCP alike) and a ``hello`` the
relay could never accept (session id, token or name breaking the protocol's rules:
:class:`~shared.errors.InvalidHelloError`, found before connecting). They are logged once and
raised from ``wait_connected``, ``send`` and ``recv``. A role held by another station
(:class:`~shared.errors.RoleTakenError`) is not final: the other may leave, so the link logs
it and keeps retrying (a station never gives up on a transient fault). Nor is a relay
certificate that fails verification (:class:`~shared.errors.TlsCertificateError`): its causes
are often temporary (a certificate swapped while the relay restarts, a station clock wrong at
boot), and the token is never sent over an unverified connection, so retrying is safe. It is
retried with backoff up to 5 s, logged at ERROR at the first failure and then once a minute,
and kept in :attr:`StationLink.last_error`; ``wait_connected`` raises it when an attempt made
while it waits fails on the certificate. Every connection failure is logged once per outage
and kind, then at most once a minute; the relay URL's user information is never shown.

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
import dataclasses
import logging
import math
import random
import ssl
import time
from collections import deque
from collections.abc import AsyncIterator, Callable
from typing import Any
from urllib.parse import unquote

from websockets.exceptions import WebSocketException

from shared.errors import (
    AuthError,
    ConfigError,
    InvalidHelloError,
    LocalProtocolError,
    ProtocolError,
    ReplacedError,
    RoleTakenError,
    SessionError,
    TeleTouchError,
    TlsCertificateError,
    TokenExpiredError,
)
from shared.freshness import ClockView, clock_view_from_stats
from shared.link_settings import (
    MAX_LINK_TIMEOUT_S,
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
    encode,
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
from shared.protocol.tokens import v2_fields
from shared.timebase import monotonic_s, now_us
from shared.transport import Transport, TransportClosed, open_client_transport

__all__ = [
    "LATEST_WINS_TYPES",
    "LinkCounters",
    "StationLink",
    "StationLinkConfig",
    "backoff_delay_s",
    "parse_link_url",
    "redact_url",
]

log = logging.getLogger(__name__)

#: a connection counts as having worked (the next backoff starts afresh) once it stayed up
#: this long, or ``reconnect_max_s`` when that is longer
STABLE_CONNECTION_S = 2.0
#: the silence limit is at least this many times the ping interval the relay announces
LIVENESS_PING_INTERVALS = 2.5
#: largest delay between attempts that fail on the relay's TLS certificate
TLS_RETRY_MAX_S = 5.0
#: largest delay between attempts the relay refuses as an expired token that this station's
#: clock says is still valid (one of the clocks is wrong: retried until they agree)
CLOCK_RETRY_MAX_S = 30.0
#: a connection failure already logged in this outage is logged again after this long
REPEAT_LOG_S = 60.0


def redact_url(url: str) -> str:
    """``url`` without its user information (``ws://user:password@host/`` ->
    ``ws://***@host/``), to show it in logs and errors."""
    scheme, sep, rest = url.rpartition("://")
    netloc, slash, path = rest.partition("/")
    if "@" in netloc:
        netloc = "***@" + netloc.rpartition("@")[2]
    return f"{scheme}{sep}{netloc}{slash}{path}"


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
        reconnect_max_s: largest reconnect delay (a relay certificate that fails
            verification is retried up to 5 s apart).
        reconnect_jitter: fraction of each delay removed at random (0 to 1).
        connect_timeout_s: limit for opening the socket and for hello -> welcome.
        liveness_timeout_s: silence after which a connection is treated as dead (raised to
            2.5 times the ping interval a relay announces in its welcome, when longer).
        max_message_bytes: size limit of one message, both directions.
        send_queue_size: bound of the ordered send queue (``send`` waits when full).
        receive_queue_size: bound of ordered messages waiting in the inbox.
        write_buffer_bytes: bytes the socket may buffer before the link holds back; a small
            value keeps latest-wins effective when the link is slow.
        ssl_context: TLS context for ``wss://`` and ``tls://`` (the system default when
            None); :func:`~shared.link_settings.client_tls_context` makes one for a CA file.
        seed: seed of the backoff jitter (None: random).

    Raises:
        ConfigError: bad URL, role or numeric setting (NaN and infinities included).
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
        if not 0.0 < reconnect_min_s <= reconnect_max_s:  # also refuses NaN
            raise ConfigError("need 0 < reconnect_min_s <= reconnect_max_s")
        if not 0.0 <= reconnect_jitter <= 1.0:
            raise ConfigError("reconnect_jitter must be in [0, 1]")
        if not all(math.isfinite(v) for v in (reconnect_min_s, reconnect_max_s,
                                              connect_timeout_s, liveness_timeout_s)):
            raise ConfigError("reconnect delays and timeouts must be finite numbers")
        if connect_timeout_s <= 0 or liveness_timeout_s <= 0:
            raise ConfigError("timeouts must be positive")
        if min(send_queue_size, receive_queue_size, max_message_bytes) < 1:
            raise ConfigError("queue sizes and max_message_bytes must be >= 1")
        #: the relay URL as given (its user information, if any, is a secret)
        self.url = url
        #: the URL as logs and errors show it (no user information)
        self.safe_url = redact_url(url)
        netloc = url.partition("://")[2].partition("/")[0]
        userinfo = netloc.rpartition("@")[0]
        #: user information to blank out of error texts (as written and percent-decoded)
        self._secrets = sorted({userinfo, unquote(userinfo)} - {""}, key=len, reverse=True)
        self.role = role
        self._session = StationSession(
            Hello(role=role, session=session, token=token, name=name),
            max_message_bytes=max_message_bytes, send_queue_size=send_queue_size,
            receive_queue_size=receive_queue_size,
            connect_timeout_us=round(connect_timeout_s * 1e6),
            liveness_timeout_us=round(liveness_timeout_s * 1e6))
        self._reconnect = (reconnect_min_s, reconnect_max_s, reconnect_jitter)
        self._connect_timeout_s = connect_timeout_s
        self._liveness_timeout_s = liveness_timeout_s
        #: the silence limit in use on the current connection (see the module docstring)
        self.liveness_timeout_s = liveness_timeout_s
        self._stable_s = max(STABLE_CONNECTION_S, reconnect_max_s)
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
        #: why the latest connection attempt failed or the latest connection ended, while
        #: the link is down (None once welcomed): a TLS certificate failure stays visible here
        #: while the link retries
        self.last_error: Exception | None = None
        #: monotonic time of :attr:`last_error`
        self.last_error_s: float | None = None
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
        #: queues with :meth:`send` or takes with :meth:`recv`, and for each ``welcome`` (its
        #: ``resume`` secret blanked) as it arrives: a replay starts decoding compact frames
        #: anew there, as the station does (a recorder; must not block)
        self.tap: Callable[[str, Message, int], None] | None = None
        self._closing = False
        #: kinds of failure logged in the current outage, and when each was last logged
        self._failures_logged: dict[str, float] = {}
        self._failures_since_log: dict[str, int] = {}
        self._liveness_logged_s: float | None = None
        #: set (and then replaced by a fresh one) when an attempt fails on the certificate
        self._tls_failed = asyncio.Event()
        self._welcomed_s: float | None = None
        #: how long the connection that just ended had been welcomed (None: it never was)
        self._up_for_s: float | None = None
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
            AuthError, ReplacedError, InvalidHelloError: the link was refused for good
                (:attr:`final_error`).
            TlsCertificateError: an attempt made while waiting failed on the relay's
                certificate (the link goes on retrying: a later call may succeed).
            SessionError: the link is closed or has failed.
            TimeoutError: not connected within ``timeout_s`` (the message names the latest
                failure).
        """
        self._raise_if_unusable()
        self.start()
        task = self._task
        if task is None:  # pragma: no cover - start() always sets it
            raise SessionError("the station link did not start", code="closed")
        tls_failed = self._tls_failed
        waiters = [asyncio.ensure_future(self.connected.wait()),
                   asyncio.ensure_future(tls_failed.wait())]
        try:
            await asyncio.wait({*waiters, task}, timeout=timeout_s,
                               return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiter in waiters:
                waiter.cancel()
            await asyncio.gather(*waiters, return_exceptions=True)
        self._raise_if_final()
        if task.done() and not task.cancelled() and task.exception() is not None:
            raise SessionError(f"the station link failed: {task.exception()}",
                               code="closed") from task.exception()
        welcome = self.welcome
        if self.connected.is_set() and welcome is not None:
            return welcome
        error = self.last_error
        if tls_failed.is_set() and isinstance(error, TlsCertificateError):
            raise error
        latest = "" if error is None else \
            f" (latest failure: {type(error).__name__}: {self._redact(str(error))})"
        raise TimeoutError(f"not connected to {self.safe_url} within {timeout_s} s{latest}")

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
        try:
            while not self._closing:
                tls_failure = clock_disagreement = False
                try:
                    await self._connect_once()
                except TokenExpiredError as err:
                    if self._token_valid_for_s() is None:
                        self._give_up(err)
                        return
                    clock_disagreement = True
                    self._note_failure(err)
                except TlsCertificateError as err:  # an AuthError, but often temporary
                    tls_failure = True
                    self._note_failure(err)
                    self._tls_failed.set()  # wakes the wait_connected calls waiting now
                    self._tls_failed = asyncio.Event()
                except (AuthError, ReplacedError, InvalidHelloError) as err:
                    self._give_up(err)
                    return
                except RoleTakenError as err:
                    self.counters.role_taken_refusals += 1
                    self.last_error, self.last_error_s = err, monotonic_s()
                    if not taken_logged:
                        log.warning("relay %s: %s; another station holds the role, retrying "
                                    "until it leaves", self.safe_url, self._redact(str(err)))
                        taken_logged = True
                except (OSError, TimeoutError, SessionError, ProtocolError,
                        WebSocketException) as err:
                    self._note_failure(err)
                self._mark_down()
                up_s, self._up_for_s = self._up_for_s, None
                if up_s is not None and up_s >= self._stable_s:
                    # the connection had worked: start afresh. Not after a connection that
                    # ended soon after its welcome (a relay closing at once, its rate limit):
                    # that one is retried with growing delays, not at the shortest
                    attempt, taken_logged = 0, False
                    self._failures_logged.clear()
                    self._failures_since_log.clear()
                if self._closing:
                    return
                max_s = self._reconnect[1]
                if tls_failure:
                    max_s = max(max_s, TLS_RETRY_MAX_S)
                if clock_disagreement:
                    max_s = max(max_s, CLOCK_RETRY_MAX_S)
                delay = backoff_delay_s(attempt, min_s=self._reconnect[0], max_s=max_s,
                                        jitter=self._reconnect[2], rng=self._rng)
                self.backoff_history_s.append(delay)
                attempt += 1
                await asyncio.sleep(delay)
        except Exception as err:  # a bug or an unforeseen failure: stop, and say so
            log.exception("the link to %s stopped on an unexpected error", self.safe_url)
            self._give_up(SessionError(
                f"the station link failed: {type(err).__name__}: {self._redact(str(err))}",
                code="closed"), logged=True)
        finally:
            self._mark_down()  # however the loop ends, the link is no longer up

    def _give_up(self, err: SessionError, *, logged: bool = False) -> None:
        """A final refusal: keep it, say it once, wake every waiter."""
        self.final_error = err
        self.last_error, self.last_error_s = err, monotonic_s()
        if not logged:
            what = ("stopped for good" if isinstance(err, InvalidHelloError)
                    else f"refused {self._session.hello.session}/{self.role} for good")
            log.error("relay %s %s (%s: %s); not retrying", self.safe_url, what,
                      type(err).__name__, self._redact(str(err)))
        self._wake_all()

    def _note_failure(self, err: Exception) -> None:
        """A connection attempt failed or a connection ended: keep it in :attr:`last_error`
        and log it, once per outage and kind of failure, then at most every
        :data:`REPEAT_LOG_S` with the number of failures since (never every attempt)."""
        now = monotonic_s()
        self.last_error, self.last_error_s = err, now
        kind = type(err).__name__
        text = self._redact(str(err))
        last = self._failures_logged.get(kind)
        since = self._failures_since_log.get(kind, 0)
        if last is not None and now - last < REPEAT_LOG_S:
            self._failures_since_log[kind] = since + 1
            if log.isEnabledFor(logging.DEBUG):
                log.debug("link to %s: attempt failed (%s: %s)", self.safe_url, kind, text)
            return
        self._failures_logged[kind], self._failures_since_log[kind] = now, 0
        again = "" if last is None else \
            f" (again: {since + 1} such failures in the last {now - last:.0f} s)"
        if isinstance(err, TokenExpiredError):
            valid_s = self._token_valid_for_s()
            log.error("link to %s: %s: %s%s; but by this station's clock the token is valid "
                      "for %.0f s more: one of the two clocks is wrong (check time sync on "
                      "both); retrying with backoff up to %g s", self.safe_url, kind, text,
                      again, valid_s or 0.0, max(self._reconnect[1], CLOCK_RETRY_MAX_S))
        elif isinstance(err, TlsCertificateError):
            log.error("link to %s: %s: %s%s; retrying with backoff up to %g s (the token is "
                      "never sent over an unverified connection)", self.safe_url, kind, text,
                      again, max(self._reconnect[1], TLS_RETRY_MAX_S))
        else:
            log.warning("link to %s unavailable (%s: %s)%s; retrying with backoff",
                        self.safe_url, kind, text, again)

    def _token_valid_for_s(self) -> float | None:
        """How long this station's version-2 token is still valid by its own wall clock
        (None: expired, or not a version-2 token)."""
        fields = v2_fields(self._session.hello.token)
        if fields is None:
            return None
        left_s = fields.expiry_s - time.time()
        return left_s if left_s >= 0 else None

    def _redact(self, text: str) -> str:
        """``text`` without the relay URL's user information."""
        for secret in self._secrets:
            text = text.replace(secret, "***")
        return text

    def _mark_down(self) -> None:
        """The connection is gone, or about to be closed: say so at once (a graceful close
        may take its timeout)."""
        # (a connection the station closes itself, at its stop, is no loss)
        was_open = self._session.connection_lost(lost=not self._closing)
        if was_open or self.connected.is_set():
            self.connected.clear()
            self.link_down_since = monotonic_s()
        if self._welcomed_s is not None:
            self._up_for_s = monotonic_s() - self._welcomed_s
            self._welcomed_s = None

    def _check_hello(self) -> None:
        """Refuse for good a hello the relay could never accept (before connecting).

        Raises:
            InvalidHelloError: the session id, token or name breaks the protocol's rules.
        """
        try:
            encode(self._session.hello, max_message_bytes=self._session.max_message_bytes)
        except LocalProtocolError as err:
            raise self._invalid_hello(err) from err

    def _invalid_hello(self, err: LocalProtocolError) -> InvalidHelloError:
        return InvalidHelloError(
            f"the relay can never accept this station's hello: {err}; fix the link settings "
            "(session, token, name)")

    def _connect_timed_out(self) -> TimeoutError:
        steps = {"tcp": "TCP connect", "tls": "TCP connect and TLS handshake",
                 "ws": "TCP connect and WebSocket handshake",
                 "wss": "TCP connect, TLS and WebSocket handshakes"}[self.scheme]
        return TimeoutError(
            f"no connection to {self.safe_url} within connect_timeout_s = "
            f"{self._connect_timeout_s:g} s (name lookup, {steps})")

    async def _connect_once(self) -> None:
        self._check_hello()
        # asyncio.timeout, not wait_for: on Python 3.11 a wait_for cancelled (the link
        # closing) just as the connection opened drops the opened transport, whose socket
        # then stays open until the garbage collector finds it; cancelled here, the connect
        # itself is interrupted and closes what it opened
        try:
            async with asyncio.timeout(self._connect_timeout_s):
                transport = await open_client_transport(
                    self.scheme, self.host, self.port, self.url,
                    max_message_bytes=self._session.max_message_bytes,
                    open_timeout_s=self._connect_timeout_s,
                    write_buffer_bytes=self._write_buffer_bytes,
                    ssl_context=self._ssl_context)
        except TimeoutError as err:  # asyncio's or websockets' own: both say nothing
            raise self._connect_timed_out() from err
        except (TeleTouchError, OSError, WebSocketException):
            raise
        except Exception as err:  # e.g. a malformed redirect's Location (ValueError): the
            # relay's answer, transient like a refused connection (it ended the link for good)
            raise SessionError(f"cannot open the connection to {self.safe_url}: "
                               f"{type(err).__name__}: {self._redact(str(err))}",
                               code="connect_failed") from err
        writer: asyncio.Task[None] | None = None
        dead = False
        try:
            try:
                hello = self._session.connect(transport.framing, now_us())
            except LocalProtocolError as err:
                raise self._invalid_hello(err) from err
            await transport.write([hello])
            writer = asyncio.get_running_loop().create_task(self._write_loop(transport))
            self._transport = transport
            await self._read_loop(transport)
        except TimeoutError:
            dead = True  # the relay went silent: it would not answer a close handshake
            raise
        finally:
            self._transport = None
            self._mark_down()  # before closing: the close may take its whole timeout
            if writer is not None:
                writer.cancel()
                await asyncio.gather(writer, return_exceptions=True)
            if dead:
                transport.abort()
            else:
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
                # a refusal: by its WebSocket close code, or (raw TCP has none) by the fatal
                # error the relay sent before closing
                raise (refusal_for_close_code(err.close_code, str(err))
                       or session.closing_refusal or err) from err
            self.last_received_s = monotonic_s()
            session.receive_data(data.encode() if isinstance(data, str) else data, now_us())
            for event in session.events_received():
                if isinstance(event, Welcomed):
                    self._welcomed(event.welcome)
                elif isinstance(event, Refused | Failed):
                    raise event.error
                elif isinstance(event, Rejected) and (self.counters.rejected_rx == 1
                                                      or log.isEnabledFor(logging.DEBUG)):
                    log.warning("dropped an invalid message from the relay: %s", event.error)
            if len(session.inbox):
                self._readable.set()
            if not self._write_now():  # pongs, and what was queued while the link was down
                self._tx_ready.set()

    def _welcomed(self, welcome: Welcome) -> None:
        # the relay pings every ping_interval_s: a silence limit shorter than a few of its
        # intervals would declare an idle, healthy connection dead between two pings
        # (bounded as the setting is: a relay announcing an hour must not make a blackholed
        # link go unnoticed for hours; found by review)
        # an observer is not pinged: the relay's stats push is all it hears when the session
        # is quiet (a relay that does not announce it: assumed to push as often as it pings)
        what, interval_s = "pings", welcome.ping_interval_s
        if self.role == "observer" and welcome.stats_interval_s > 0:
            what, interval_s = "sends stats", welcome.stats_interval_s
        liveness_s = max(self._liveness_timeout_s,
                         min(LIVENESS_PING_INTERVALS * interval_s, MAX_LINK_TIMEOUT_S))
        self.liveness_timeout_s = liveness_s
        self._session.liveness_timeout_us = round(liveness_s * 1e6)
        if liveness_s > self._liveness_timeout_s and liveness_s != self._liveness_logged_s:
            self._liveness_logged_s = liveness_s
            log.info("relay %s %s every %g s: the link is presumed dead after %g s of "
                     "silence (liveness_timeout_s %g s is shorter)", self.safe_url, what,
                     interval_s, liveness_s, self._liveness_timeout_s)
        self.link_down_since = None
        self.last_error = self.last_error_s = None
        self._welcomed_s = monotonic_s()
        self.connected.set()
        if self.tap is not None:  # never the resume secret: recordings are shared
            try:
                self.tap("rx", dataclasses.replace(welcome, resume=""), now_us())
            except Exception:  # a recorder's fault must not end the link (it runs here)
                log.exception("the link's tap failed on a welcome; the link goes on")
        log.info("connected to %s as %s in session %s", self.safe_url, self.role,
                 welcome.session)

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
