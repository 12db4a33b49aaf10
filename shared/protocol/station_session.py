"""Sans-I/O station session: the client side of the relay protocol, without sockets or clocks.

One :class:`StationSession` lives as long as a station's link and spans its connections.
The asyncio glue (:mod:`shared.client`) only moves bytes and passes the time::

    session = StationSession(hello, max_message_bytes=..., send_queue_size=...,
                             receive_queue_size=..., liveness_timeout_us=...)
    sock.send(session.connect("tcp", now_us))        # the hello
    session.receive_data(chunk, now_us)              # bytes from the relay
    for event in session.events_received(): ...      # Welcomed / Refused / Failed / Rejected
    session.send(PlatformState(...))                 # queued with the stream's policy
    data = session.next_data(now_us)                 # one framed message to write, or None
    session.check_liveness(now_us)                   # LinkSilent when the relay went quiet

The session owns the handshake (hello, then welcome or a refusal), the answers to the
relay's ``clock_ping`` (``t1`` = receive time, ``t2`` = the time the pong is handed out by
:meth:`next_data`), the ``station_rx`` hop stamp, the latest ``stats``, the liveness
decision and the per-stream policy of the send queue and the inbox (``Message.POLICY``).
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from shared.errors import (
    AuthError,
    HandshakeTimeoutError,
    ProtocolError,
    RemoteProtocolError,
    ReplacedError,
    RoleTakenError,
    SessionError,
    TokenExpiredError,
)
from shared.protocol.codec import DEFAULT_MAX_MESSAGE_BYTES, encode
from shared.protocol.connection import (
    ConnectionFailed,
    Framing,
    MessageRejected,
    ProtocolConnection,
)
from shared.protocol.framing import frame
from shared.protocol.messages import (
    CLOCKS,
    Bye,
    ClockPing,
    ClockPong,
    DataMessage,
    Error,
    Hello,
    Message,
    Stats,
    StreamPolicy,
    TactileCompact,
    Welcome,
    carried_kind,
    carry_motion,
)
from shared.protocol.queues import StreamQueue

__all__ = [
    "Failed",
    "LinkCounters",
    "LinkSilent",
    "Refused",
    "Rejected",
    "StationEvent",
    "StationSession",
    "Welcomed",
    "latest_slot",
    "refusal_for_close_code",
]

log = logging.getLogger(__name__)

_REFUSALS = (AuthError, RoleTakenError, HandshakeTimeoutError, ReplacedError)
_REFUSALS_BY_CODE: dict[str, type[SessionError]] = {c.code: c for c in _REFUSALS}
_REFUSALS_BY_CLOSE: dict[int, type[SessionError]] = {c.close_code: c for c in _REFUSALS}
_MAX_PENDING_PONGS = 16


def latest_slot(msg: Message) -> str | None:
    """The latest-wins slot ``msg`` takes in a station's send queue and inbox (None: it
    goes in order). A ``tactile_compact`` key frame has a slot of its own: a newer key frame
    replaces an older one that still waits (each is whole), a delta never replaces it, and
    the queue stays bounded without ever making the sender wait. The relay keeps key frames
    in order instead (:func:`~shared.protocol.is_latest_wins`): its re-send of a key frame
    to a late joiner counts on knowing which one a peer was given."""
    if msg.POLICY is not StreamPolicy.LATEST_WINS:
        return None
    if isinstance(msg, TactileCompact) and msg.key:
        return msg.TYPE + "/key"
    return msg.TYPE


def _supersede(msg: Message, slot: str, waiting: Callable[[str], Message | None]
               ) -> tuple[Message, list[str]]:
    """``msg`` as it replaces what ``waiting`` (slot -> the message waiting there, or None)
    holds in its slot and, for a key frame, in its stream's delta slot too (the key frame is
    newer and whole: it shows that delta's movements first); and those other slots, which
    the caller empties. Each replaced message hands its start on (:func:`carry_motion`)."""
    others = []
    for held_slot in (slot, msg.TYPE) if slot != msg.TYPE else (slot,):
        held = waiting(held_slot)
        if held is not None:
            msg = carry_motion(held, msg)
            if held_slot != slot:
                others.append(held_slot)
    return msg, others


def _refusal_class(msg: Error) -> type[SessionError] | None:
    """The refusal a fatal ``error`` means (an expired token is ``auth`` with ``reason``
    ``expired``), or None."""
    if msg.code == AuthError.code and msg.reason == TokenExpiredError.reason:
        return TokenExpiredError
    return _REFUSALS_BY_CODE.get(msg.code)


def refusal_for_close_code(close_code: int | None, reason: str) -> SessionError | None:
    """The refusal a WebSocket close code means (4001 auth, ...), or None."""
    cls = _REFUSALS_BY_CLOSE.get(close_code or 0)
    return None if cls is None else cls(reason)


@dataclass
class LinkCounters:
    """Traffic counters of one station link (since it was created)."""

    connects: int = 0
    connection_losses: int = 0
    messages_sent: int = 0
    messages_received: int = 0
    stale_dropped_tx: int = 0
    stale_dropped_rx: int = 0
    #: messages queued while no connection was open, dropped at the next welcome
    #: (data queued before an outage is stale: never delivered late)
    dropped_on_reconnect: int = 0
    rejected_rx: int = 0
    pongs_sent: int = 0
    #: hellos refused because another station held our role (retried)
    role_taken_refusals: int = 0


@dataclass(frozen=True, slots=True)
class Welcomed:
    """The relay accepted the hello: the connection is open."""

    welcome: Welcome


@dataclass(frozen=True, slots=True)
class Refused:
    """The relay refused the hello (``error`` before ``welcome``)."""

    error: SessionError


@dataclass(frozen=True, slots=True)
class Failed:
    """The connection is unusable (broken stream, bad message before welcome)."""

    error: ProtocolError


@dataclass(frozen=True, slots=True)
class Rejected:
    """One invalid message from the relay was dropped; the connection goes on."""

    error: RemoteProtocolError


@dataclass(frozen=True, slots=True)
class LinkSilent:
    """Nothing arrived for longer than the timeout: the connection is presumed dead."""

    silent_for_us: int
    welcomed: bool


StationEvent = Welcomed | Refused | Failed | Rejected | LinkSilent


class StationSession:
    """Protocol state of a station's link to the relay (see the module docstring).

    Args:
        hello: the hello sent at every connection.
        max_message_bytes: size limit of one message, both directions.
        send_queue_size: bound of the ordered send queue.
        receive_queue_size: bound of ordered messages waiting in the inbox.
        connect_timeout_us: time from :meth:`connect` to ``welcome``.
        liveness_timeout_us: silence after which an open connection is presumed dead.
    """

    def __init__(self, hello: Hello, *, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
                 send_queue_size: int = 256, receive_queue_size: int = 1024,
                 connect_timeout_us: int = 5_000_000,
                 liveness_timeout_us: int = 5_000_000) -> None:
        self.hello = hello
        self.role = hello.role
        self.max_message_bytes = max_message_bytes
        self.connect_timeout_us = connect_timeout_us
        self.liveness_timeout_us = liveness_timeout_us
        self.counters = LinkCounters()
        #: encoded messages waiting for the relay (what waits when a connection is welcomed
        #: was queued while the link was down: it is dropped then, never delivered late)
        self.outbox: StreamQueue[bytes] = StreamQueue(send_queue_size)
        #: per carried stream (:func:`carried_kind`), the newest message queued and its
        #: bytes: the message a newer one replaces while those bytes still wait in the
        #: outbox (:func:`carry_motion`)
        self._queued_latest: dict[str, tuple[bytes, Message]] = {}
        #: received messages waiting for the station
        self.inbox: StreamQueue[Message] = StreamQueue(receive_queue_size)
        self.welcome: Welcome | None = None
        self.latest_stats: Stats | None = None
        #: when :attr:`latest_stats` arrived (our clock, us)
        self.latest_stats_rx_us: int | None = None
        self._stamp_hops = hello.role in CLOCKS
        self._conn: ProtocolConnection | None = None
        self._open = False
        self._pongs: deque[tuple[int, int, int]] = deque(maxlen=_MAX_PENDING_PONGS)
        self._events: list[StationEvent] = []
        self._last_rx_us = 0
        #: the refusal the relay announced on the current connection after its welcome (a
        #: fatal ``error`` with a refusal's code, ``replaced``): the connection ends with it.
        #: Over WebSocket the close code says the same (:func:`refusal_for_close_code`); raw
        #: TCP has no close codes, so the glue raises this when the connection closes
        self.closing_refusal: SessionError | None = None

    # ------------------------------------------------------------------ connection

    @property
    def is_open(self) -> bool:
        """True between ``welcome`` and :meth:`connection_lost`."""
        return self._open

    def connect(self, framing: Framing, now_us: int) -> bytes:
        """Start a new connection; return the (framed) hello to write first."""
        self._conn = ProtocolConnection(framing, self.max_message_bytes)
        self._open = False
        self._pongs.clear()
        self._events.clear()
        self._last_rx_us = now_us
        self.closing_refusal = None
        return self._conn.encode(self.hello)

    def connection_lost(self, *, lost: bool = True) -> bool:
        """The socket is gone; return True if the connection had been welcomed.

        Args:
            lost: count it in ``connection_losses`` (False: the station closed it itself).
        """
        was_open, self._open, self._conn = self._open, False, None
        if was_open and lost:
            self.counters.connection_losses += 1
        return was_open

    def check_liveness(self, now_us: int) -> LinkSilent | None:
        """Return :class:`LinkSilent` when the deadline passed (welcome or liveness)."""
        silent = now_us - self._last_rx_us
        limit = self.liveness_timeout_us if self._open else self.connect_timeout_us
        if self._conn is not None and silent >= limit:
            return LinkSilent(silent, self._open)
        return None

    def reading_resumed(self, now_us: int) -> None:
        """The glue paused reading (full inbox) and reads again: silence counts from now."""
        self._last_rx_us = max(self._last_rx_us, now_us)

    def deadline_us(self) -> int:
        """When :meth:`check_liveness` fires if nothing arrives before."""
        limit = self.liveness_timeout_us if self._open else self.connect_timeout_us
        return self._last_rx_us + limit

    # ------------------------------------------------------------------ receiving

    def receive_data(self, data: bytes | bytearray | memoryview, now_us: int) -> None:
        """Take bytes from the relay (TCP: any chunk; WebSocket: one message)."""
        conn = self._conn
        if conn is None:
            return
        self._last_rx_us = now_us
        conn.receive_data(data)
        for event in conn.events_received():
            if isinstance(event, ConnectionFailed):
                self._fail(event.error)
                return
            if isinstance(event, MessageRejected):
                if not self._open:
                    self._fail(event.error)
                    return
                self.counters.rejected_rx += 1
                self._events.append(Rejected(event.error))
                continue
            msg = event.message
            if not self._open:
                if isinstance(msg, Welcome):
                    self.welcome, self._open = msg, True
                    self.counters.connects += 1
                    stale = len(self.outbox)
                    if stale:
                        self.outbox.clear()
                        self.counters.dropped_on_reconnect += stale
                    # offsets of the previous connection describe another clock exchange
                    self.latest_stats = self.latest_stats_rx_us = None
                    # our next hello proves we are this connection, so the relay can replace
                    # it if it still holds it when we come back (session resumption)
                    self.hello = dataclasses.replace(self.hello, resume=msg.resume)
                    self._events.append(Welcomed(msg))
                    continue
                if isinstance(msg, Error):
                    refusal = _refusal_class(msg) or SessionError
                    self._events.append(Refused(refusal(
                        f"relay refused hello: {msg.code}: {msg.message}", code=msg.code)))
                    self._conn = None
                    return
            self._handle(msg, now_us)

    def _fail(self, error: ProtocolError) -> None:
        self._events.append(Failed(error))
        self._conn = None

    def _handle(self, msg: Message, now_us: int) -> None:
        if isinstance(msg, ClockPing):
            self._pongs.append((msg.ping_id, msg.t0_us, now_us))
            return
        if isinstance(msg, ClockPong | Welcome | Hello):
            return
        if isinstance(msg, Stats):
            self.latest_stats, self.latest_stats_rx_us = msg, now_us
        elif isinstance(msg, DataMessage) and self._stamp_hops:
            msg = msg.with_hop(self.role, "station_rx", now_us)
        elif isinstance(msg, Error):
            refusal = _refusal_class(msg) if msg.fatal else None
            if refusal is not None and self.closing_refusal is None:
                self.closing_refusal = refusal(
                    f"relay closed the connection: {msg.code}: {msg.message}")
            if log.isEnabledFor(logging.DEBUG):
                log.debug("relay error: %s: %s", msg.code, msg.message)
        self.counters.messages_received += 1
        slot = latest_slot(msg)
        if slot is None:  # the glue stops reading while the inbox is full: a soft bound
            self.inbox.put_ordered(msg, force=True)
            return
        # never read: the newer one shows first what the replaced one showed
        msg, others = _supersede(msg, slot, self.inbox.held)
        for other in others:
            self.inbox.discard(other)
            self.counters.stale_dropped_rx += 1
        if self.inbox.put_latest(slot, msg) is not None:
            self.counters.stale_dropped_rx += 1

    def events_received(self) -> list[StationEvent]:
        """Return and clear the events produced by :meth:`receive_data`."""
        events, self._events = self._events, []
        return events

    def next_message(self) -> Message | None:
        """Take the oldest message of the inbox, or None."""
        return self.inbox.pop()

    # ------------------------------------------------------------------ sending

    def send(self, msg: Message) -> Message | None:
        """Queue ``msg`` with its stream's policy.

        A latest-wins message replaces an unsent one of its slot (:func:`latest_slot`;
        counted in ``stale_dropped_tx``) and then travels as
        :func:`~shared.protocol.carry_motion` makes it (a ``platform_state`` or a tactile
        frame starts where the replaced one started). A ``tactile_compact`` key frame has a
        slot of its own: it replaces an unsent key frame and also an unsent delta, which it
        shows first. An ordered message is refused when the queue is full.

        Returns:
            The message as it was queued (what a recording of the link must show), or None,
            with nothing queued, when the ordered queue is full.

        Raises:
            LocalProtocolError: ``msg`` is invalid or larger than ``max_message_bytes``.
        """
        slot = latest_slot(msg)
        if slot is None:
            payload = encode(msg, max_message_bytes=self.max_message_bytes)
            return msg if self.outbox.put_ordered(payload) else None
        msg, others = _supersede(msg, slot, self._unsent)
        payload = encode(msg, max_message_bytes=self.max_message_bytes)  # may refuse it
        for other in others:
            self.outbox.discard(other)
            self.counters.stale_dropped_tx += 1
        if self.outbox.put_latest(slot, payload) is not None:
            self.counters.stale_dropped_tx += 1
        if carried_kind(msg) is not None:  # only these are ever carried: keep no other
            self._queued_latest[slot] = (payload, msg)
        return msg

    def _unsent(self, slot: str) -> Message | None:
        """The message whose bytes still wait in the outbox's slot ``slot``, or None."""
        queued = self._queued_latest.get(slot)
        return queued[1] if queued is not None and self.outbox.held(slot) is queued[0] \
            else None

    def send_bye(self, reason: str) -> None:
        """Queue a ``bye`` even if the ordered queue is full."""
        self.outbox.put_ordered(encode(Bye(reason=reason),
                                       max_message_bytes=self.max_message_bytes), force=True)

    @property
    def pending_sends(self) -> int:
        """Messages queued but not yet handed out by :meth:`next_data`."""
        return len(self.outbox)

    def next_data(self, now_us: int) -> bytes | None:
        """The next framed message to write (pongs first), or None.

        Nothing is handed out before ``welcome``. A pong's ``t2_us`` is ``now_us``.
        """
        if not self._open or self._conn is None:
            return None
        if self._pongs:
            ping_id, t0_us, t1_us = self._pongs.popleft()
            self.counters.pongs_sent += 1
            self.counters.messages_sent += 1
            return self._conn.encode(ClockPong(ping_id=ping_id, t0_us=t0_us, t1_us=t1_us,
                                               t2_us=now_us))
        payload = self.outbox.pop()
        if payload is None:
            return None
        self.counters.messages_sent += 1
        return frame(payload) if self._conn.framing == "tcp" else payload
