"""Sans-I/O relay-side session: one per connected peer, without sockets or clocks.

The relay's asyncio glue (:mod:`relay_server.server`) moves bytes and passes the time;
everything a single connection decides is here::

    ps = PeerSession("ws", settings, now_us)
    ps.receive_data(data, now_us)
    for event in ps.events_received():   # HelloReceived / DataReceived / StatsReported /
        ...                              # ClockSampled / Closing
    ps.accept(now_us)                    # after auth + join: queue the welcome
    ps.tick(now_us)                      # hello timeout, clock pings; True when stats are due
    frames = ps.data_to_send(clock)      # encodes the outbox, stamps relay_out
    ps.close_code, ps.close_reason       # set once the connection must be closed

It owns the handshake (the first message must be a ``hello``; before ``welcome`` every
problem is fatal), the clock exchange (ping ids, the ``ClockFilter``), the observer
rules, the error budget, the close decisions and the outbox with the per-stream policy.
Routing between peers, authentication and latency ledgers stay in the relay.
"""

from __future__ import annotations

import itertools
import logging
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

from shared.clocksync import ClockFilter, ClockSample, sample_from_timestamps
from shared.errors import (
    HandshakeTimeoutError,
    InputDataError,
    LimitError,
    LocalProtocolError,
    MalformedMessageError,
    OversizeError,
    PeerSilentError,
    ProtocolError,
    RemoteProtocolError,
    SessionError,
    VersionError,
)
from shared.protocol.codec import DEFAULT_MAX_MESSAGE_BYTES, encode
from shared.protocol.connection import (
    Event,
    Framing,
    MessageReceived,
    MessageRejected,
    ProtocolConnection,
)
from shared.protocol.forward import WireMessage, with_hops
from shared.protocol.framing import frame
from shared.protocol.messages import (
    MESSAGE_TYPES,
    Bye,
    ClockPing,
    ClockPong,
    DataMessage,
    Error,
    Hello,
    Message,
    Stats,
    Welcome,
)
from shared.protocol.queues import StreamQueue
from shared.protocol.ratelimit import TokenBucket

__all__ = [
    "FORWARD_ROOM_BYTES",
    "ClockSampled",
    "Closing",
    "DataReceived",
    "HelloReceived",
    "Outbox",
    "PeerEvent",
    "PeerSession",
    "PeerSettings",
    "Pending",
    "StatsReported",
]

log = logging.getLogger(__name__)

_FATAL_AFTER_HELLO = (VersionError, OversizeError)
_OBSERVER_MAY_SEND = (ClockPong, ClockPing, Stats, Bye)
_DATA_MESSAGE_TYPES = frozenset(cls for cls in MESSAGE_TYPES.values()
                                if issubclass(cls, DataMessage))
_MAX_OUTSTANDING_PINGS = 16
#: bytes a data message must leave under ``max_message_bytes`` for the stamps the relay adds
#: when it forwards it: ``relay_in``, ``relay_out`` and, on a clustered relay, ``nats_out``
#: and ``nats_in`` (at most 26 bytes each, and 2 for a longer ``hops`` header); one that does
#: not is refused on receipt (``too_large_to_forward``) rather than dropped when written
FORWARD_ROOM_BYTES = 128
#: a station clock further than this from the relay's (a century, in microseconds) is a
#: client's bug or a hostile pong, not a clock: its sample is refused (``stray_pong``), so
#: an offset never carries the relay's latency figures out of range
_SANE_US = 100 * 365 * 86_400 * 1_000_000

#: called when a forwarded message is encoded: (pending entry, relay_out time) -> None
OnSend = Callable[["Pending", int], None]


# --------------------------------------------------------------------------- outbox


@dataclass(slots=True)
class Pending:
    """One message waiting for a peer.

    Attributes:
        message: the message.
        forwarded: a data message relayed from a station (validated on receipt: encoded
            without re-validation, with ``relay_in``/``relay_out`` hops).
        on_send: accounting callback for forwarded messages, or None.
        build: for messages that carry the time they are written (``clock_ping``,
            ``clock_pong``): called with that time, returns the message to send.
        t_in_us: relay clock when a forwarded message arrived (its ``relay_in`` hop).
        mid_hops: stamps between ``relay_in`` and ``relay_out`` (a clustered relay's NATS
            leg: ``nats_out``, ``nats_in``).
        wire: a forwarded message's bytes as received: sent as they are with the hops
            spliced in (:mod:`shared.protocol.forward`); None: encoded from ``message``.
    """

    message: Message
    forwarded: bool = False
    on_send: OnSend | None = None
    build: Callable[[int], Message] | None = None
    t_in_us: int = 0
    mid_hops: tuple[tuple[str, str, int], ...] = ()
    wire: WireMessage | None = None


class Outbox:
    """Bounded outgoing state of one peer: latest-wins slots and an ordered queue.

    A stalled peer holds at most one entry per state stream and per periodic control
    message (``stats``, ``clock_ping``), plus at most ``ordered_limit`` ordered ones.

    Args:
        ordered_limit: maximum entries of the ordered queue.
        wakeup: called after every put (the glue wakes its writer).
    """

    def __init__(self, ordered_limit: int, wakeup: Callable[[], None] | None = None) -> None:
        self._queue: StreamQueue[Pending] = StreamQueue(ordered_limit)
        self.wakeup = wakeup
        self.closed = False

    def __len__(self) -> int:
        return len(self._queue)

    def _woken(self) -> None:
        if self.wakeup is not None:
            self.wakeup()

    def put_latest(self, key: str, message: DataMessage, t_in_us: int,
                   on_send: OnSend | None = None,
                   mid_hops: tuple[tuple[str, str, int], ...] = (),
                   wire: WireMessage | None = None) -> Pending | None:
        """Put a forwarded ``message`` in slot ``key``; return the unsent entry it replaced."""
        old = self._queue.put_latest(key, Pending(message, True, on_send, None, t_in_us,
                                                  mid_hops, wire))
        self._woken()
        return old

    def held(self, key: str) -> Pending | None:
        """The unsent entry in slot ``key`` that the next :meth:`put_latest` of ``key`` would
        replace, or None."""
        return self._queue.held(key)

    def put_control_latest(self, key: str, message: Message,
                           build: Callable[[int], Message] | None = None) -> bool:
        """Put the relay's own periodic message in slot ``key`` (a fresh one replaces an
        unsent one). Returns True when an unsent message was replaced."""
        old = self._queue.put_latest(key, Pending(message, False, None, build, 0))
        self._woken()
        return old is not None

    def put_ordered(self, message: Message, on_send: OnSend | None = None, *,
                    forwarded: bool = False, force: bool = False,
                    build: Callable[[int], Message] | None = None, t_in_us: int = 0,
                    mid_hops: tuple[tuple[str, str, int], ...] = (),
                    wire: WireMessage | None = None) -> bool:
        """Append to the ordered queue; False (nothing queued) when full and not ``force``."""
        if not self._queue.put_ordered(Pending(message, forwarded, on_send, build, t_in_us,
                                               mid_hops, wire), force=force):
            return False
        self._woken()
        return True

    def take(self) -> list[Pending]:
        """Remove and return everything waiting, in arrival order."""
        return self._queue.take()


# --------------------------------------------------------------------------- events


@dataclass(frozen=True, slots=True)
class HelloReceived:
    """A valid first ``hello``: authenticate and join, then :meth:`PeerSession.accept`."""

    hello: Hello


@dataclass(slots=True)  # not frozen: built once per forwarded message (frozen init is slower)
class DataReceived:
    """A data message from a station, to route; ``t_in_us`` is its arrival time; ``wire``
    its received bytes, to forward as they are (None: encode ``message``)."""

    message: DataMessage
    t_in_us: int
    wire: WireMessage | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True, slots=True)
class StatsReported:
    """The peer sent its own ``stats``."""

    metrics: dict[str, object]


@dataclass(frozen=True, slots=True)
class ClockSampled:
    """A ``clock_pong`` answered one of our pings; the sample is in ``PeerSession.clock``."""

    t0_us: int
    t1_us: int
    sample: ClockSample
    #: the sample revealed a clock step (the filter restarted from it; a ping burst and an
    #: early ``stats`` follow, so the stations learn the new offset within the burst)
    stepped: bool = False
    #: the ping was one of a burst (the offset is being measured: the other stations of the
    #: session need each such sample at once, not at their next periodic ``stats``)
    settling: bool = False


@dataclass(frozen=True, slots=True)
class Closing:
    """The connection must be closed once the outbox is flushed."""

    close_code: int
    reason: str


PeerEvent = HelloReceived | DataReceived | StatsReported | ClockSampled | Closing


@dataclass(frozen=True)
class PeerSettings:
    """Per-connection protocol settings of the relay (all times in microseconds).

    ``max_hello_bytes`` bounds what a connection may send before its hello is accepted
    (the TCP framing buffers no more than that); ``rate_limit_per_s`` and
    ``rate_limit_burst`` are the token bucket of received messages after the hello.
    """

    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    max_hello_bytes: int = 64 * 1024
    rate_limit_per_s: float = 5000.0
    rate_limit_burst: int = 10_000
    ordered_queue_len: int = 256
    bad_message_budget: int = 20
    hello_timeout_us: int = 5_000_000
    ping_interval_us: int = 1_000_000
    ping_burst: int = 5
    ping_burst_spacing_us: int = 20_000
    #: a burst goes on past ``ping_burst`` pings while the offset's error bound is wider
    #: than this (a loaded host or path: slow pongs), up to ``settle_max_pings`` in all
    settle_uncertainty_us: int = 10_000
    settle_max_pings: int = 25
    stats_interval_us: int = 1_000_000
    #: a joined station that sends nothing for this long is closed (``silent``); it answers
    #: a ping every ``ping_interval_us``, so only a dead or blackholed connection is this quiet
    silence_timeout_us: int = 10_000_000


# --------------------------------------------------------------------------- session


class PeerSession:
    """Protocol state of one relay connection (see the module docstring).

    Args:
        framing: ``"tcp"`` or ``"ws"``.
        settings: limits, budget and periods.
        now_us: the time the connection was accepted (starts the hello timeout).
        counters: relay-wide counters to add to (``bad_<code>``, ``fatal_<code>``,
            ``stray_pong``, ``client_errors``, ``replies_dropped``).
    """

    def __init__(self, framing: Framing, settings: PeerSettings, now_us: int,
                 counters: Counter[str] | None = None) -> None:
        self.framing: Framing = framing
        self.settings = settings
        self.counters: Counter[str] = Counter() if counters is None else counters
        self.outbox = Outbox(settings.ordered_queue_len)
        self.clock = ClockFilter()
        self.hello: Hello | None = None
        self.received = 0
        self.bad_messages = 0
        self.close_code: int | None = None
        self.close_reason = ""
        self._conn = ProtocolConnection(framing, settings.max_message_bytes, keep_wire=True)
        self._conn.set_receive_limit(min(settings.max_hello_bytes, settings.max_message_bytes))
        self._forward_limit = settings.max_message_bytes - FORWARD_ROOM_BYTES
        self._bucket = TokenBucket(settings.rate_limit_per_s, settings.rate_limit_burst, now_us)
        self._over_rate = 0  # messages refused in the current over-rate episode
        self._rate_used = 0  # messages since the bucket was last read
        self._rate_free = self._bucket.tokens // 2  # half the tokens at that reading
        self._rate_warned = False
        self._events: list[PeerEvent] = []
        self._held: list[tuple[Event, int]] | None = None  # between hello and accept()
        self._joined = False
        self._observer = False
        self._warned = False
        self._pings: OrderedDict[int, int] = OrderedDict()
        self._ping_ids = itertools.count()
        self._hello_deadline_us = now_us + settings.hello_timeout_us
        self._next_ping_us: int | None = None
        self._last_rx_us = now_us
        self._next_stats_us: int | None = None
        self._burst_left = 0
        self._burst_sent = 0
        self._burst_ping_ids: set[int] = set()
        self._burst_ping_queued = False  # the ping queued (built when sent) is a burst's

    @property
    def where(self) -> str:
        """``role@session`` for logs (``?`` before the hello)."""
        return "?" if self.hello is None else f"{self.hello.role}@{self.hello.session}"

    @property
    def closing(self) -> bool:
        """True once a close was decided."""
        return self.close_code is not None

    # ------------------------------------------------------------------ input

    def receive_data(self, data: bytes | bytearray | memoryview | str, now_us: int) -> None:
        """Take received bytes (TCP: any chunk; WebSocket: one message, text refused)."""
        if self.closing:
            return
        previous_rx_us, self._last_rx_us = self._last_rx_us, now_us
        if isinstance(data, str):  # WebSocket text frame: not our protocol
            events: list[Event] = [MessageRejected(MalformedMessageError(
                "text WebSocket messages are not accepted; send binary msgpack"))]
        else:
            self._conn.receive_data(data)
            events = self._conn.events_received()
        if self._joined and events:
            # the hot path is a counter: the bucket is only consulted once the messages
            # since its last reading exceed half the tokens it had then
            self._rate_used += len(events)
            if self._rate_used > self._rate_free:
                events = self._settle_rate(events, previous_rx_us, now_us)
        for event in events:
            if self.closing:
                return
            if self._held is not None:
                self._held.append((event, now_us))
            elif self.hello is None:
                self._first(event)
            else:
                self._process(event, now_us)

    def _settle_rate(self, events: list[Event], earlier_by_us: int,
                     now_us: int) -> list[Event]:
        """Charge the bucket for the messages counted since its last reading; return the
        events it still allows (only this chunk's can be refused: the earlier ones fitted
        in half the tokens of the last reading).

        The earlier ones are charged as if all had come at ``earlier_by_us`` (the previous
        chunk), this chunk's at ``now_us``: none earlier than it came, so the idle time
        before them is not credited past the cap and the bucket grants no more than an
        exact one (``burst + rate * T`` over any time ``T``). Not knowing how the earlier
        ones were spread, it can be stricter than an exact bucket, by at most their number
        (half the tokens of the last reading): what a steady stream under the rate, or a
        backlog of up to half the burst on it, never meets."""
        earlier, self._rate_used = self._rate_used - len(events), 0
        if earlier > 0:
            self._bucket.take(earlier, earlier_by_us)
        refused = len(events) - self._bucket.take(len(events), now_us)
        tokens = self._bucket.tokens
        self._rate_free = tokens // 2
        if refused:
            self._rate_exceeded(refused)
            return events[:len(events) - refused]
        if self._over_rate and tokens * 2 >= self._bucket.burst:
            self._over_rate = 0  # calm again (half the bucket back): the episode is over
        return events

    def _rate_exceeded(self, refused: int) -> None:
        """Messages over the rate limit are discarded; the first of an episode gets a
        non-fatal ``rate_limited`` error, more than a burst of them closes the connection.
        An episode ends when the bucket is half full again."""
        self.counters["rate_limited"] += refused
        s = self.settings
        first = self._over_rate == 0
        self._over_rate += refused
        if self._over_rate > s.rate_limit_burst:
            self.fail(LimitError(f"over {s.rate_limit_per_s:g} messages/s for more than "
                                 f"{s.rate_limit_burst} messages", code="rate_limited"))
            return
        if first:
            message = (f"over {s.rate_limit_per_s:g} messages/s (burst "
                       f"{s.rate_limit_burst}): {refused} message(s) discarded")
            if not self._rate_warned:
                self._rate_warned = True
                log.warning("%s %s: rate_limited: %s", self.framing, self.where, message)
            self.reply(Error(code="rate_limited", message=message, fatal=False))

    def events_received(self) -> list[PeerEvent]:
        """Return and clear the events produced so far."""
        events, self._events = self._events, []
        return events

    def _first(self, event: Event) -> None:
        if not isinstance(event, MessageReceived):
            self.fail(event.error)
        elif not isinstance(event.message, Hello):
            self.fail(RemoteProtocolError(f"the first message must be a hello, got "
                                          f"{event.message.TYPE}", code="hello_expected"))
        else:
            self.hello = event.message
            self._observer = event.message.role == "observer"
            self._held = []
            self._events.append(HelloReceived(event.message))

    def accept(self, welcome: Welcome, now_us: int) -> None:
        """The relay admitted the peer: queue ``welcome``, start pings and stats, then
        process what the peer sent behind its hello."""
        self.outbox.put_ordered(welcome, force=True)
        self._joined = True
        self._conn.set_receive_limit(self.settings.max_message_bytes)
        s = self.settings
        if welcome.role != "observer" and s.ping_burst:
            # stats wait for the burst; then periodic pings and stats start together
            self._start_burst(now_us)
        else:
            if welcome.role != "observer":
                self._next_ping_us = now_us + s.ping_interval_us
            self._next_stats_us = now_us + s.stats_interval_us
        held, self._held = self._held or [], None
        for event, t_in_us in held:
            if self.closing:
                break
            self._process(event, t_in_us)

    def _process(self, event: Event, t_in_us: int) -> None:
        # the hot path first: a data message from a station (exact type checks, no ABC)
        if type(event) is MessageReceived and type(event.message) in _DATA_MESSAGE_TYPES:
            self.received += 1
            if self._observer:
                self.reject(SessionError(f"observers are read-only; {event.message.TYPE} "
                                         "refused", code="read_only"))
            elif event.size > self._forward_limit:
                self._no_room(event.message, event.size)  # type: ignore[arg-type]
            else:
                self._events.append(DataReceived(event.message, t_in_us,  # type: ignore[arg-type]
                                                 event.wire))
            return
        if isinstance(event, MessageRejected):
            if isinstance(event.error, _FATAL_AFTER_HELLO):
                self.fail(event.error)
            else:
                self.reject(event.error)
            return
        if not isinstance(event, MessageReceived):
            self.fail(event.error)
            return
        msg = event.message
        self.received += 1
        observer = self._observer
        if isinstance(msg, DataMessage):
            if observer:
                self.reject(SessionError(f"observers are read-only; {msg.TYPE} refused",
                                         code="read_only"))
            elif event.size > self._forward_limit:
                self._no_room(msg, event.size)
            else:
                self._events.append(DataReceived(msg, t_in_us, event.wire))
        elif isinstance(msg, ClockPong):
            self._on_pong(msg, t_in_us)
        elif isinstance(msg, ClockPing):
            ping_id, t0_us = msg.ping_id, msg.t0_us
            self.reply(ClockPong(ping_id=ping_id, t0_us=t0_us, t1_us=t_in_us),
                       build=lambda t2: ClockPong(ping_id=ping_id, t0_us=t0_us,
                                                  t1_us=t_in_us, t2_us=t2))
        elif isinstance(msg, Bye):
            self._close(1000, "bye")
        elif observer and not isinstance(msg, _OBSERVER_MAY_SEND):
            self.reject(SessionError(f"observers are read-only; {msg.TYPE} refused",
                                     code="read_only"))
        elif isinstance(msg, Stats):
            self._events.append(StatsReported(dict(msg.metrics)))
        elif isinstance(msg, Error):
            self.counters["client_errors"] += 1
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s reported error %s: %s", self.where, msg.code, msg.message)
        elif isinstance(msg, Hello):
            self.reject(SessionError("already joined; hello is only valid once",
                                     code="already_joined"))
        else:
            self.reject(SessionError(f"{msg.TYPE} is sent by the relay only",
                                     code="unexpected_type"))

    def _no_room(self, msg: DataMessage, size: int) -> None:
        """A data message too close to the size limit for the relay's stamps: refused now,
        with a per-message error naming it, rather than dropped once stamped. Not counted
        against the bad-message budget (like ``queue_full``): a valid message from a
        station whose sender allows the whole limit, not a broken one."""
        self.counters["too_large_to_forward"] += 1
        self.reply(Error(code="too_large_to_forward", fatal=False, stream=msg.TYPE,
                         seq=msg.seq, message=(
                             f"{msg.TYPE} seq {msg.seq} not forwarded: its {size} bytes "
                             f"leave less than {FORWARD_ROOM_BYTES} bytes under "
                             f"max_message_bytes ({self.settings.max_message_bytes}) for the "
                             "relay's stamps")))

    # ------------------------------------------------------------------ clock exchange

    def _start_burst(self, now_us: int) -> None:
        self._burst_left, self._burst_sent, self._next_ping_us = \
            self.settings.ping_burst, 0, now_us

    def _ping(self, t0_us: int) -> ClockPing:
        ping_id = next(self._ping_ids)
        self._pings[ping_id] = t0_us
        if self._burst_ping_queued:
            self._burst_ping_queued = False
            self._burst_ping_ids.add(ping_id)
        while len(self._pings) > _MAX_OUTSTANDING_PINGS:
            self._burst_ping_ids.discard(self._pings.popitem(last=False)[0])
        return ClockPing(ping_id=ping_id, t0_us=t0_us)

    def _settled(self, now_us: int) -> bool:
        """The burst may end: the offset's bound is narrow enough, or enough was tried."""
        s = self.settings
        if self._burst_sent >= max(s.settle_max_pings, s.ping_burst):
            return True
        bound = self.clock.uncertainty_us(now_us)
        return bound is not None and bound <= s.settle_uncertainty_us

    def _on_pong(self, pong: ClockPong, t3_us: int) -> None:
        t0 = self._pings.pop(pong.ping_id, None)
        settling = pong.ping_id in self._burst_ping_ids
        self._burst_ping_ids.discard(pong.ping_id)
        if t0 is None or t0 != pong.t0_us or abs(pong.t1_us - t0) > _SANE_US \
                or abs(pong.t2_us - t3_us) > _SANE_US:
            self.counters["stray_pong"] += 1
            return
        try:
            sample = sample_from_timestamps(t0, pong.t1_us, pong.t2_us, t3_us)
            stepped = self.clock.add(sample)
        except InputDataError:
            self.counters["stray_pong"] += 1
            return
        if stepped:
            self.counters["clock_steps"] += 1
            log.warning("%s: clock step detected (offset now %.0f us); re-measuring",
                        self.where, sample.offset_us)
            if self.settings.ping_burst:
                self._start_burst(t3_us)
        self._events.append(ClockSampled(t0, pong.t1_us, sample, stepped, settling))

    def stats_soon(self, now_us: int) -> None:
        """Push ``stats`` at the next tick (a station's clock changed: all must know)."""
        if self._joined and self._next_stats_us is not None:
            self._next_stats_us = min(self._next_stats_us, now_us)

    # ------------------------------------------------------------------ time

    def next_tick_us(self) -> int:
        """When :meth:`tick` next has something to do."""
        if not self._joined:  # waiting for the hello, or for accept() after it
            return self._hello_deadline_us + (0 if self.hello is None
                                              else self.settings.hello_timeout_us)
        times = [t for t in (self._next_ping_us, self._next_stats_us) if t is not None]
        return min(times)

    def tick(self, now_us: int) -> bool:
        """Apply the hello timeout and queue due clock pings.

        Returns:
            True when a ``stats`` push is due (the relay builds it: :meth:`send_stats`).
        """
        if self.closing:
            return False
        if not self._joined:
            if self.hello is None and now_us >= self._hello_deadline_us:
                timeout_s = self.settings.hello_timeout_us / 1e6
                self.fail(HandshakeTimeoutError(f"no hello within {timeout_s:g} s"))
            return False
        s = self.settings
        if not self._observer and now_us - self._last_rx_us > s.silence_timeout_us:
            # checked at least at every ping (ping_interval_us): late by at most one interval
            self.fail(PeerSilentError(f"nothing received for "
                                      f"{(now_us - self._last_rx_us) / 1e6:.1f} s"))
            return False
        if self._next_ping_us is not None and now_us >= self._next_ping_us:
            self._burst_ping_queued = self._burst_left > 0
            self.outbox.put_control_latest("clock_ping", ClockPing(), build=self._ping)
            if self._burst_left > 0:
                self._burst_sent += 1
            if self._burst_left == 1 and not self._settled(now_us):
                # slow pongs (a loaded host or path): the bound is still wide; measure on
                # rather than wait a whole ping interval for the next sample
                self._next_ping_us = now_us + s.ping_burst_spacing_us
            elif self._burst_left > 1:
                self._burst_left -= 1
                self._next_ping_us = now_us + s.ping_burst_spacing_us
            elif self._burst_left == 1:  # the burst is over
                self._burst_left = 0
                self._next_ping_us = now_us + s.ping_burst_spacing_us + s.ping_interval_us
                # the first stats right after the burst: the stations need the offsets to
                # age-check what they receive, and they refuse to act before they have them
                self._next_stats_us = now_us + s.ping_burst_spacing_us
            else:
                self._next_ping_us += s.ping_interval_us
                if self._next_ping_us < now_us:
                    self._next_ping_us = now_us + s.ping_interval_us
        if self._next_stats_us is not None and now_us >= self._next_stats_us:
            self._next_stats_us += s.stats_interval_us
            if self._next_stats_us < now_us:
                self._next_stats_us = now_us + s.stats_interval_us
            return True
        return False

    # ------------------------------------------------------------------ output

    def send_stats(self, stats: Stats) -> None:
        """Queue the relay's periodic ``stats`` (replaces an unsent one)."""
        self.outbox.put_control_latest("stats", stats)

    def reply(self, msg: Message, build: Callable[[int], Message] | None = None) -> None:
        """Queue a control reply to the peer (counted when the ordered queue is full)."""
        if not self.outbox.put_ordered(msg, build=build):
            self.counters["replies_dropped"] += 1

    def reject(self, err: ProtocolError | SessionError, *, stream: str | None = None,
               seq: int | None = None) -> None:
        """A per-message error: reply with a non-fatal ``error`` (naming the data message
        ``stream``/``seq`` when given), close past the budget."""
        if not self._joined:
            self.fail(err)
            return
        self.bad_messages += 1
        self.counters[f"bad_{err.code}"] += 1
        if not self._warned:
            self._warned = True
            log.warning("%s %s: %s: %s (error sent, connection kept)", self.framing,
                        self.where, err.code, err)
        elif log.isEnabledFor(logging.DEBUG):
            log.debug("%s: %s: %s", self.where, err.code, err)
        budget = self.settings.bad_message_budget
        if self.bad_messages > budget:
            over = RemoteProtocolError(f"more than {budget} bad messages",
                                       code="too_many_errors")
            over.close_code = 1008
            self.fail(over)
            return
        self.reply(Error(code=err.code, message=str(err), fatal=False, stream=stream, seq=seq))

    def fail(self, err: ProtocolError | SessionError) -> None:
        """A fatal error: log once, queue a fatal ``error``, then close with its code."""
        if self.closing:
            return
        self.counters[f"fatal_{err.code}"] += 1
        log.warning("%s %s closed: %s: %s (close %d)", self.framing, self.where, err.code,
                    err, err.close_code)
        self.outbox.put_ordered(Error(code=err.code, message=str(err), fatal=True,
                                      reason=getattr(err, "reason", None)), force=True)
        self._close(err.close_code, err.code)

    def shutdown(self) -> None:
        """The relay is stopping: queue ``bye`` and close with 1001."""
        if self.closing:
            return
        if self._joined:
            self.outbox.put_ordered(Bye(reason="relay shutting down"), force=True)
        self._close(1001, "relay shutting down")

    def _close(self, close_code: int, reason: str) -> None:
        self.close_code, self.close_reason = close_code, reason
        self.outbox.closed = True
        self._events.append(Closing(close_code, reason))

    def data_to_send(self, clock: Callable[[], int]) -> list[bytes]:
        """Encode and frame everything waiting, in arrival order.

        Forwarded data messages get their ``relay_in`` and ``relay_out`` hops, the latter
        read from ``clock`` just before encoding, and their ``on_send`` callback; one
        that grew past the size limit is skipped (counted ``forward_too_large``). One
        received with its bytes (``Pending.wire``) is sent as those bytes with the hops
        spliced in, not re-encoded.

        Args:
            clock: the relay clock in microseconds (read once per timed message).
        """
        tcp = self.framing == "tcp"
        limit = self.settings.max_message_bytes
        frames: list[bytes] = []
        for pending in self.outbox.take():
            msg = pending.message
            if pending.forwarded:
                t_out = clock()
                hops = (("relay", "relay_in", pending.t_in_us), *pending.mid_hops,
                        ("relay", "relay_out", t_out))
                # the sender's bytes with the stamps spliced in, when they allow it
                spliced = None if pending.wire is None else with_hops(pending.wire, hops)
                if spliced is not None:
                    data = spliced
                else:
                    try:
                        data = encode(msg, validate=False, max_message_bytes=limit,
                                      extra_hops=hops)
                    except LocalProtocolError:
                        data = b""
                if not data or len(data) > limit:
                    # refused on receipt when it left no room for the stamps: only one the
                    # relay encoded anew (not the sender's bytes) can still grow past it
                    self.counters["forward_too_large"] += 1
                    if log.isEnabledFor(logging.DEBUG):
                        log.debug("forwarded %s too large after hops", msg.TYPE)
                    continue
                if pending.on_send is not None:
                    pending.on_send(pending, t_out)
            else:
                if pending.build is not None:
                    msg = pending.build(clock())
                data = encode(msg, max_message_bytes=limit)
            frames.append(frame(data) if tcp else data)
        return frames
