"""The station side of the relay link: one asyncio connection that survives outages.

:class:`StationLink` connects a station (``local``, ``remote`` or ``observer``) to the relay
over WebSocket (``ws://``, ``wss://``) or length-prefixed TCP (``tcp://``), says ``hello``,
waits for ``welcome`` and then:

* sends with the same per-stream policy as the relay: state streams (``platform_state``,
  ``tactile_frame``, ``arm_state``) are **latest-wins** while the socket is backed up (one
  pending message per type, the replaced one is counted as dropped); everything else
  (``arm_command``, control) is **ordered** in a bounded queue (``send`` waits for room);
* receives into a bounded inbox with the same policy, so a slow consumer never grows memory;
* answers every ``clock_ping`` with a ``clock_pong`` whose ``t1_us`` is the receive time and
  ``t2_us`` the moment the pong is handed to the socket (``shared.timebase.now_us``);
* appends ``Hop(role, "station_rx", t_us)`` to every received data message, ``t_us`` being
  the time its bytes came off the socket (observers, whose role is not a clock name, do not
  stamp);
* keeps the relay's latest ``stats`` (``latest_stats``, ``clock_offsets_us``);
* reconnects with exponential backoff and jitter (0.1 s doubling to 5 s by default) and
  resumes transparently; ``link_down_since`` tells the station how long it has been cut off
  so it can go to its safe state (100 ms rule). A half-open link is detected by
  ``liveness_timeout_s`` of silence (the relay pings every second).

Refusals that retrying cannot fix are final: a wrong token (:class:`~shared.errors.AuthError`)
and a role held by someone else (:class:`~shared.errors.RoleTakenError`, except within
``role_taken_grace_s`` after our own connection dropped, when the relay may still hold our
old connection). They are logged once and raised from ``wait_connected``, ``send`` and
``recv``.

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
import socket
import ssl
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any, Literal, Protocol
from urllib.parse import urlsplit

from shared.errors import (
    AuthError,
    ConfigError,
    HandshakeTimeoutError,
    ProtocolError,
    RoleTakenError,
    SessionError,
)
from shared.protocol import (
    CLOCKS,
    DEFAULT_MAX_MESSAGE_BYTES,
    ROLES,
    Bye,
    ClockPing,
    ClockPong,
    ConnectionFailed,
    DataMessage,
    Error,
    Hello,
    Message,
    MessageReceived,
    MessageRejected,
    ProtocolConnection,
    Stats,
    Welcome,
    encode,
    frame,
)
from shared.timebase import monotonic_s, now_us

__all__ = [
    "LATEST_WINS_TYPES",
    "LinkCounters",
    "StationLink",
    "StationLinkConfig",
    "backoff_delay_s",
    "parse_link_url",
]

log = logging.getLogger(__name__)

#: message types sent and received latest-wins (stale ones are dropped, never queued)
LATEST_WINS_TYPES = frozenset({"platform_state", "tactile_frame", "arm_state"})
#: ``error.code`` / WebSocket close code -> the refusal it means
_REFUSALS_BY_CODE: dict[str, type[SessionError]] = {
    c.code: c for c in (AuthError, RoleTakenError, HandshakeTimeoutError)}
_REFUSALS_BY_CLOSE: dict[int, type[SessionError]] = {
    c.close_code: c for c in (AuthError, RoleTakenError, HandshakeTimeoutError)}


def backoff_delay_s(attempt: int, *, min_s: float, max_s: float, jitter: float,
                    rng: random.Random) -> float:
    """Delay before reconnect attempt ``attempt`` (0 = first retry).

    The base doubles from ``min_s`` up to ``max_s``; jitter scales it down by a random
    factor in ``[1 - jitter, 1]`` so stations cut off together do not retry in lockstep.

    Args:
        attempt: number of failed attempts since the last good connection, from 0.
        min_s: first delay.
        max_s: largest delay.
        jitter: fraction in [0, 1] of the base that may be taken off at random.
        rng: random source (seedable for tests).

    Returns:
        The delay in seconds, in ``[(1 - jitter) * base, base]``.
    """
    base = min(max_s, min_s * 2.0 ** min(attempt, 60))
    return base * (1.0 - jitter * rng.random())


Scheme = Literal["ws", "wss", "tcp"]


def parse_link_url(url: str) -> tuple[Scheme, str, int]:
    """Split a relay URL into scheme, host and port.

    Args:
        url: ``ws://host[:port][/path]``, ``wss://...`` or ``tcp://host:port``.

    Returns:
        ``(scheme, host, port)``; WebSocket ports default to 80 / 443.

    Raises:
        ConfigError: unknown scheme, missing host, or a TCP URL without a port.
    """
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as err:
        raise ConfigError(f"bad relay URL {url!r}: {err}") from err
    scheme = parts.scheme.lower()
    if scheme not in ("ws", "wss", "tcp"):
        raise ConfigError(f"relay URL {url!r}: scheme must be ws://, wss:// or tcp://")
    if not parts.hostname:
        raise ConfigError(f"relay URL {url!r} has no host")
    if port is None:
        if scheme == "tcp":
            raise ConfigError(f"relay URL {url!r}: tcp:// needs a port")
        port = 443 if scheme == "wss" else 80
    return scheme, parts.hostname, port  # type: ignore[return-value]


@dataclass(frozen=True)
class StationLinkConfig:
    """Link settings of a station: TOML table ``[local.link]`` / ``[remote.link]``.

    Resolve with ``resolve_config(StationLinkConfig, "local.link", ...)``; the token then
    comes best from ``TELETOUCH_LOCAL_LINK_TOKEN`` (an environment file), not the TOML.

    Attributes:
        url: relay URL (``ws://``, ``wss://`` or ``tcp://``).
        session: session id shared by the two stations.
        token: session token.
        name: label shown in the relay's status.
        reconnect_min_s: first reconnect delay.
        reconnect_max_s: largest reconnect delay.
        connect_timeout_s: limit for connect + hello -> welcome.
        liveness_timeout_s: silence after which the connection is treated as dead.
        max_message_bytes: size limit of one message.
    """

    url: str = "ws://127.0.0.1:8765/"
    session: str = "lab1"
    token: str = ""
    name: str = ""
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 5.0
    connect_timeout_s: float = 5.0
    liveness_timeout_s: float = 5.0
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES


@dataclass
class LinkCounters:
    """Traffic counters of one :class:`StationLink` (since it was created)."""

    connects: int = 0
    connection_losses: int = 0
    messages_sent: int = 0
    messages_received: int = 0
    stale_dropped_tx: int = 0
    stale_dropped_rx: int = 0
    rejected_rx: int = 0
    pongs_sent: int = 0


# --------------------------------------------------------------------------- transports


def _retrieve(future: asyncio.Future[Any]) -> None:
    """Mark a finished future's outcome as read, so asyncio does not log it as lost."""
    if not future.cancelled():
        future.exception()


class _LinkClosed(ConnectionError):
    """The transport closed; ``close_code`` is the WebSocket close code if any."""

    def __init__(self, message: str, close_code: int | None = None) -> None:
        super().__init__(message)
        self.close_code = close_code


class _Transport(Protocol):
    framing: Literal["tcp", "ws"]

    async def send(self, data: bytes) -> None: ...

    async def recv(self) -> bytes: ...

    async def close(self) -> None: ...


class _TcpTransport:
    framing: Literal["tcp", "ws"] = "tcp"

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                 write_buffer_bytes: int) -> None:
        self._reader, self._writer = reader, writer
        sock = writer.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        writer.transport.set_write_buffer_limits(high=write_buffer_bytes)

    async def send(self, data: bytes) -> None:
        try:
            self._writer.write(data)
            await self._writer.drain()
        except (OSError, RuntimeError) as err:
            raise _LinkClosed(f"TCP send failed: {err}") from err

    async def recv(self) -> bytes:
        try:
            data = await self._reader.read(65536)
        except OSError as err:
            raise _LinkClosed(f"TCP receive failed: {err}") from err
        if not data:
            raise _LinkClosed("relay closed the TCP connection")
        return data

    async def close(self) -> None:
        self._writer.close()
        with contextlib.suppress(OSError, asyncio.TimeoutError):
            await asyncio.wait_for(self._writer.wait_closed(), 1.0)


class _WsTransport:
    framing: Literal["tcp", "ws"] = "ws"

    def __init__(self, ws: Any) -> None:
        self._ws = ws

    @staticmethod
    def _closed(err: Exception) -> _LinkClosed:
        rcvd = getattr(err, "rcvd", None)
        code = rcvd.code if rcvd is not None else None
        reason = f" ({rcvd.reason})" if rcvd is not None and rcvd.reason else ""
        return _LinkClosed(f"WebSocket closed with code {code}{reason}", close_code=code)

    async def send(self, data: bytes) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            await self._ws.send(data)
        except ConnectionClosed as err:
            raise self._closed(err) from err

    async def recv(self) -> bytes:
        from websockets.exceptions import ConnectionClosed

        try:
            data = await self._ws.recv()
        except ConnectionClosed as err:
            raise self._closed(err) from err
        if isinstance(data, str):  # text frames are not part of the protocol
            return data.encode()
        return bytes(data)

    async def close(self) -> None:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self._ws.close(), 1.0)


# --------------------------------------------------------------------------- inbox


class _Inbox:
    """Bounded receive buffer: latest-wins per state type, ordered (bounded) for the rest."""

    def __init__(self, max_ordered: int, counters: LinkCounters) -> None:
        self._items: deque[list[Message | None]] = deque()
        self._latest: dict[str, list[Message | None]] = {}
        self._max_ordered = max_ordered
        self._ordered = 0
        self._counters = counters
        self._readable = asyncio.Event()
        self._room = asyncio.Event()
        self._room.set()

    async def put(self, msg: Message) -> None:
        if msg.TYPE in LATEST_WINS_TYPES:
            old = self._latest.get(msg.TYPE)
            if old is not None and old[0] is not None:
                old[0] = None  # superseded before the consumer took it
                self._counters.stale_dropped_rx += 1
            cell: list[Message | None] = [msg]
            self._latest[msg.TYPE] = cell
            self._items.append(cell)
        else:
            while self._ordered >= self._max_ordered:
                self._room.clear()
                await self._room.wait()
            self._ordered += 1
            self._items.append([msg])
        self._readable.set()

    def get_nowait(self) -> Message | None:
        while self._items:
            cell = self._items.popleft()
            msg = cell[0]
            if msg is None:
                continue
            if msg.TYPE in LATEST_WINS_TYPES:
                if self._latest.get(msg.TYPE) is cell:
                    del self._latest[msg.TYPE]
            else:
                self._ordered -= 1
                self._room.set()
            return msg
        self._readable.clear()
        return None

    async def wait_readable(self) -> None:
        await self._readable.wait()

    def wake(self) -> None:
        self._readable.set()


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
        role_taken_grace_s: after a connection loss, keep retrying a ``role_taken`` refusal
            this long (the relay may not yet have noticed our old connection died).
        ssl_context: TLS context for ``wss://`` (the system default when None).
        seed: seed of the backoff jitter (None: random).

    Raises:
        ConfigError: bad URL, role or numeric setting.
    """

    def __init__(self, url: str, *, session: str, role: str, token: str, name: str = "",
                 reconnect_min_s: float = 0.1, reconnect_max_s: float = 5.0,
                 reconnect_jitter: float = 0.5, connect_timeout_s: float = 5.0,
                 liveness_timeout_s: float = 5.0,
                 max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
                 send_queue_size: int = 256, receive_queue_size: int = 1024,
                 write_buffer_bytes: int = 16 * 1024, role_taken_grace_s: float = 10.0,
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
        self._hello = Hello(role=role, session=session, token=token, name=name)
        self._reconnect_min_s = reconnect_min_s
        self._reconnect_max_s = reconnect_max_s
        self._reconnect_jitter = reconnect_jitter
        self._connect_timeout_s = connect_timeout_s
        self._liveness_timeout_s = liveness_timeout_s
        self._max_message_bytes = max_message_bytes
        self._send_queue_size = send_queue_size
        self._write_buffer_bytes = max(0, write_buffer_bytes)
        self._role_taken_grace_s = role_taken_grace_s
        self._ssl_context = ssl_context
        self._rng = random.Random(seed)
        self._stamp_hops = role in CLOCKS

        self.counters = LinkCounters()
        self.connected = asyncio.Event()
        #: monotonic time (``shared.timebase.monotonic_s``) the link went down; None when up
        self.link_down_since: float | None = monotonic_s()
        #: monotonic time of the last bytes received from the relay (None: never)
        self.last_received_s: float | None = None
        self.latest_stats: Stats | None = None
        self.welcome: Welcome | None = None
        self.final_error: SessionError | None = None
        #: reconnect delays actually waited, most recent last (for diagnostics and tests)
        self.backoff_history_s: deque[float] = deque(maxlen=64)

        self._inbox = _Inbox(receive_queue_size, self.counters)
        self._ordered_out: deque[bytes] = deque()
        self._latest_out: dict[str, bytes] = {}
        self._pings: deque[tuple[int, int, int]] = deque(maxlen=16)
        self._tx_ready = asyncio.Event()
        self._tx_room = asyncio.Event()
        self._tx_room.set()
        self._task: asyncio.Task[None] | None = None
        self._closing = False
        self._ever_welcomed = False
        self._down_logged = False

    @classmethod
    def from_config(cls, config: StationLinkConfig, role: str, **overrides: Any) -> StationLink:
        """Build a link from resolved settings (``overrides`` are extra constructor args).

        Raises:
            ConfigError: bad URL, role or setting.
        """
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
                self._ordered_out.append(encode(Bye(reason=reason),
                                                max_message_bytes=self._max_message_bytes))
                self._tx_ready.set()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self._drained(), 0.5)
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        self.connected.clear()
        self._inbox.wake()
        self._tx_room.set()

    async def _drained(self) -> None:
        while self._ordered_out and self.connected.is_set():
            await asyncio.sleep(0.005)

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
        if not self.connected.is_set() or self.welcome is None:
            raise TimeoutError(f"not connected to {self.url} within {timeout_s} s")
        return self.welcome

    # ------------------------------------------------------------------ status

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
    def clock_offset_us(self) -> int | None:
        """This station's clock minus the relay's (None until the relay reports it)."""
        return self.clock_offsets_us.get(self.role)

    # ------------------------------------------------------------------ sending

    async def send(self, msg: Message) -> None:
        """Queue ``msg`` for the relay.

        State streams (:data:`LATEST_WINS_TYPES`) replace any not-yet-sent message of the
        same type; other messages are kept in order, waiting for room when
        ``send_queue_size`` are already pending. Messages sent while the link is down are
        delivered after it comes back (at most one per state type).

        Raises:
            LocalProtocolError: ``msg`` is invalid or larger than ``max_message_bytes``.
            AuthError, RoleTakenError: the link was finally refused.
            SessionError: the link is closed.
        """
        payload = encode(msg, max_message_bytes=self._max_message_bytes)
        self._raise_if_unusable()
        if msg.TYPE in LATEST_WINS_TYPES:
            if self._latest_out.pop(msg.TYPE, None) is not None:
                self.counters.stale_dropped_tx += 1
            self._latest_out[msg.TYPE] = payload
        else:
            while len(self._ordered_out) >= self._send_queue_size:
                self._tx_room.clear()
                await self._tx_room.wait()
                self._raise_if_unusable()
            self._ordered_out.append(payload)
        self._tx_ready.set()

    @property
    def pending_sends(self) -> int:
        """Messages queued but not yet handed to the socket."""
        return len(self._ordered_out) + len(self._latest_out)

    def _next_outgoing(self) -> bytes | None:
        if self._pings:
            ping_id, t0_us, t1_us = self._pings.popleft()
            self.counters.pongs_sent += 1
            return encode(ClockPong(ping_id=ping_id, t0_us=t0_us, t1_us=t1_us, t2_us=now_us()))
        if self._ordered_out:
            payload = self._ordered_out.popleft()
            self._tx_room.set()
            return payload
        if self._latest_out:
            msg_type = next(iter(self._latest_out))
            return self._latest_out.pop(msg_type)
        return None

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
            msg = self._inbox.get_nowait()
            if msg is not None:
                return msg
            self._raise_if_unusable()
            remaining = None if deadline is None else deadline - loop.time()
            if remaining is not None and remaining <= 0:
                raise TimeoutError(f"no message within {timeout_s} s")
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._inbox.wait_readable(), remaining)

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

    async def _open(self) -> _Transport:
        if self.scheme == "tcp":
            reader, writer = await asyncio.open_connection(self.host, self.port)
            return _TcpTransport(reader, writer, self._write_buffer_bytes)
        from websockets.asyncio.client import connect

        kwargs: dict[str, Any] = {}
        if self.scheme == "wss" and self._ssl_context is not None:
            kwargs["ssl"] = self._ssl_context
        ws = await connect(self.url, compression=None, max_size=self._max_message_bytes,
                           ping_interval=None, open_timeout=self._connect_timeout_s,
                           write_limit=self._write_buffer_bytes, proxy=None, **kwargs)
        return _WsTransport(ws)

    async def _supervise(self) -> None:
        attempt = 0
        lost_at: float | None = None
        while not self._closing:
            transport: _Transport | None = None
            try:
                transport = await asyncio.wait_for(self._open(), self._connect_timeout_s)
                conn = ProtocolConnection(transport.framing, self._max_message_bytes)
                await self._handshake(transport, conn)
                attempt, lost_at = 0, None
                await self._serve(transport, conn)
            except (AuthError, RoleTakenError) as err:
                grace = (isinstance(err, RoleTakenError) and lost_at is not None
                         and monotonic_s() - lost_at < self._role_taken_grace_s)
                if not grace:
                    self.final_error = err
                    log.error("relay %s refused %s/%s for good (%s: %s); not retrying",
                              self.url, self._hello.session, self.role, type(err).__name__, err)
                    self._inbox.wake()
                    self._tx_room.set()
                    return
                log.info("relay still holds role %s; retrying", self.role)
            except (OSError, TimeoutError, SessionError, ProtocolError) as err:
                if not self._down_logged:
                    log.warning("link to %s unavailable (%s: %s); retrying with backoff",
                                self.url, type(err).__name__, err)
                    self._down_logged = True
                elif log.isEnabledFor(logging.DEBUG):
                    log.debug("reconnect attempt %d failed: %s", attempt, err)
            except Exception as err:  # websockets handshake errors (InvalidStatus, ...)
                from websockets.exceptions import WebSocketException

                if not isinstance(err, WebSocketException):
                    raise
                if not self._down_logged:
                    log.warning("link to %s unavailable (%s); retrying", self.url, err)
                    self._down_logged = True
            finally:
                if self.connected.is_set():
                    self.connected.clear()
                    self.link_down_since = monotonic_s()
                    self.counters.connection_losses += 1
                    lost_at = self.link_down_since
                if transport is not None:
                    await transport.close()
            if self._closing:
                return
            delay = backoff_delay_s(attempt, min_s=self._reconnect_min_s,
                                    max_s=self._reconnect_max_s,
                                    jitter=self._reconnect_jitter, rng=self._rng)
            self.backoff_history_s.append(delay)
            attempt += 1
            await asyncio.sleep(delay)

    async def _recv_bytes(self, transport: _Transport, timeout_s: float) -> bytes:
        try:
            data = await asyncio.wait_for(transport.recv(), timeout_s)
        except TimeoutError as err:
            raise TimeoutError(f"relay silent for {timeout_s:.3g} s") from err
        except _LinkClosed as err:
            refusal = _REFUSALS_BY_CLOSE.get(err.close_code or 0)
            if refusal is not None:
                raise refusal(str(err)) from err
            raise
        self.last_received_s = monotonic_s()
        return data

    async def _handshake(self, transport: _Transport, conn: ProtocolConnection) -> None:
        conn.send(self._hello)
        for data in conn.data_to_send():
            await transport.send(data)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self._connect_timeout_s
        while True:
            remaining = deadline - loop.time()
            if remaining <= 0:
                raise TimeoutError("no welcome from the relay in time")
            data = await self._recv_bytes(transport, remaining)
            t_rx_us = now_us()
            conn.receive_data(data)
            for event in conn.events_received():
                if isinstance(event, ConnectionFailed):
                    raise event.error
                if isinstance(event, MessageRejected):
                    raise event.error
                msg = event.message
                if isinstance(msg, Welcome):
                    self.welcome = msg
                    self._ever_welcomed = True
                    self.counters.connects += 1
                    self.link_down_since = None
                    self._down_logged = False
                    self.connected.set()
                    log.info("connected to %s as %s in session %s", self.url, self.role,
                             msg.session)
                    return
                if isinstance(msg, Error):
                    refusal = _REFUSALS_BY_CODE.get(msg.code, SessionError)
                    raise refusal(f"relay refused hello: {msg.code}: {msg.message}",
                                  code=msg.code)
                await self._handle(msg, t_rx_us)

    async def _serve(self, transport: _Transport, conn: ProtocolConnection) -> None:
        self._tx_ready.set()  # flush what was queued while the link was down
        writer = asyncio.get_running_loop().create_task(self._write_loop(transport))
        try:
            await self._read_loop(transport, conn, writer)
        finally:
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, _LinkClosed):
                await writer

    async def _write_loop(self, transport: _Transport) -> None:
        while True:
            payload = self._next_outgoing()
            if payload is None:
                self._tx_ready.clear()
                await self._tx_ready.wait()
                continue
            await transport.send(frame(payload) if transport.framing == "tcp" else payload)
            self.counters.messages_sent += 1

    async def _read_loop(self, transport: _Transport, conn: ProtocolConnection,
                         writer: asyncio.Task[None]) -> None:
        while True:
            recv = asyncio.ensure_future(self._recv_bytes(transport, self._liveness_timeout_s))
            try:
                done, _ = await asyncio.wait({recv, writer}, return_when=asyncio.FIRST_COMPLETED)
            except BaseException:  # cancelled (link closing): do not leave recv's error unread
                recv.cancel()
                recv.add_done_callback(_retrieve)
                raise
            if recv not in done:  # the writer died: the socket is gone
                recv.cancel()
                with contextlib.suppress(asyncio.CancelledError, _LinkClosed, TimeoutError):
                    await recv
                writer.result()  # re-raise its error
                raise _LinkClosed("writer stopped")
            data = recv.result()
            t_rx_us = now_us()
            conn.receive_data(data)
            for event in conn.events_received():
                if isinstance(event, MessageReceived):
                    await self._handle(event.message, t_rx_us)
                elif isinstance(event, MessageRejected):
                    self.counters.rejected_rx += 1
                    if self.counters.rejected_rx == 1 or log.isEnabledFor(logging.DEBUG):
                        log.warning("dropped an invalid message from the relay: %s",
                                    event.error)
                else:
                    raise event.error

    async def _handle(self, msg: Message, t_rx_us: int) -> None:
        if isinstance(msg, ClockPing):
            self._pings.append((msg.ping_id, msg.t0_us, t_rx_us))
            self._tx_ready.set()
            return
        if isinstance(msg, ClockPong | Welcome | Hello):
            return
        if isinstance(msg, Stats):
            self.latest_stats = msg
        elif isinstance(msg, DataMessage) and self._stamp_hops:
            msg = msg.with_hop(self.role, "station_rx", t_rx_us)
        elif isinstance(msg, Error) and log.isEnabledFor(logging.DEBUG):
            log.debug("relay error: %s: %s", msg.code, msg.message)
        self.counters.messages_received += 1
        await self._inbox.put(msg)
