"""Sessions, peers and latency accounting of the relay (no I/O here).

A :class:`Session` holds at most one ``local`` and one ``remote`` peer and any number of
observers, and one :class:`DirectionStats` per direction (``local_to_remote``,
``remote_to_local``). :meth:`Session.route` applies the per-stream policy; the writer
task calls back when a forwarded message is actually written, which closes the books on
its relay residence time and end-to-end estimate.
"""

from __future__ import annotations

import hmac
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from shared.clocksync import ClockFilter
from shared.errors import RoleTakenError
from shared.ledger import LatencyLedger, LedgerSnapshot, merge_snapshots
from shared.protocol import (
    DataMessage,
    Error,
    StreamPolicy,
    TactileCompact,
    carry_motion,
    is_latest_wins,
)
from shared.protocol.forward import WireMessage
from shared.protocol.peer_session import Outbox, Pending

__all__ = [
    "DIRECTION_OF",
    "STREAMS_OF",
    "DirectionStats",
    "Peer",
    "RemoteForwarder",
    "RouteResult",
    "Session",
]

log = logging.getLogger(__name__)

#: data streams each station role may send
STREAMS_OF = {"local": frozenset({"platform_state", "arm_command"}),
              "remote": frozenset({"arm_state", "tactile_frame", "tactile_compact"})}
#: sender role -> direction name
DIRECTION_OF = {"local": "local_to_remote", "remote": "remote_to_local"}
_OTHER = {"local": "remote", "remote": "local"}


class DirectionStats:
    """Latency books of one direction of one session.

    Ledgers (each bounded by ``window``):
        ``uplink[stream]``: station -> relay one-way delay, with seq loss and drop counts.
        ``relay``: relay residence (``relay_out - relay_in``), the latency the relay adds.
        ``end_to_end``: sender stamp -> estimated arrival at the receiving station
        (relay_out + the receiver's downlink estimate, half its min-delay round trip).
    """

    def __init__(self, name: str, window: int) -> None:
        self.name = name
        self.window = window
        self.uplink: dict[str, LatencyLedger] = {}
        self.relay = LatencyLedger(window)
        self.end_to_end = LatencyLedger(window)
        self.nats = LatencyLedger(window)  # NATS leg (nats_out -> nats_in) from other workers
        self.forwarded = 0
        self.unsynced = 0  # arrivals before the sender's clock offset was known
        #: per stream, the connection (peer_id) whose messages the ledger counts now
        self.senders: dict[str, int] = {}

    def stream(self, name: str) -> LatencyLedger:
        """The uplink ledger of one stream (created on first use)."""
        ledger = self.uplink.get(name)
        if ledger is None:
            ledger = self.uplink[name] = LatencyLedger(self.window)
        return ledger

    def uplink_snapshot(self) -> LedgerSnapshot:
        """All streams of this direction merged."""
        return merge_snapshots([lg.snapshot() for lg in self.uplink.values()])


@dataclass(eq=False)
class Peer:
    """One joined connection: its role, outbox, clock estimate and counters.

    ``outbox`` and ``clock`` belong to the connection's
    :class:`~shared.protocol.peer_session.PeerSession`; the ledgers are the relay's.
    """

    peer_id: int
    session_id: str
    role: str
    name: str
    transport: str
    outbox: Outbox
    window: int
    clock: ClockFilter = field(default_factory=ClockFilter)
    downlink: LatencyLedger = field(init=False)
    rtt: LatencyLedger = field(init=False)
    received: int = 0
    bad_messages: int = 0
    observer_drops: int = 0
    #: the per-connection secret given in ``welcome`` (a reconnect proves it to replace us)
    resume_secret: str = field(default="", repr=False)
    #: closes this peer's connection when a newer one of the same station replaces it
    evict: Callable[[], None] | None = field(default=None, repr=False)
    #: pushes ``stats`` to this peer at once (a station's clock offset changed)
    request_stats: Callable[[], None] | None = field(default=None, repr=False)
    reported: dict[str, Any] = field(default_factory=dict)
    #: per direction, the seq of the newest ``tactile_compact`` key frame queued to this
    #: peer (a delta needs its key frame: see :meth:`Session.deliver`)
    compact_key_seq: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.downlink = LatencyLedger(self.window)
        self.rtt = LatencyLedger(self.window)

    def record_clock_exchange(self, t0_us: int, t1_us: int, delay_us: float) -> None:
        """Book a completed clock exchange (already added to ``clock``): the relay ->
        station delay under the current best offset, and the round trip."""
        offset = self.clock.offset_us or 0.0
        self.downlink.record(None, t0_us, round(t1_us - offset))
        self.rtt.record(None, 0, round(delay_us))

    @property
    def downlink_estimate_us(self) -> float | None:
        """Estimated relay -> station one-way delay (half the best round trip)."""
        best = self.clock.best
        return None if best is None else best.delay_us / 2.0


class RemoteForwarder(Protocol):
    """How a session reaches peers held by other workers of a clustered relay."""

    def forward(self, session_id: str, sender_role: str, msg: DataMessage, t_in_us: int,
                sent_ref_us: int | None, need_station: bool) -> bool:
        """Send ``msg`` to the workers holding this session's observers and, with
        ``need_station``, its receiving station; True when another worker holds that
        station."""


@dataclass(frozen=True, slots=True)
class RouteResult:
    """What :meth:`Session.route` did with one message (for replies to the sender)."""

    error: Error | None = None


class Session:
    """One session: the two stations, observers, and the books of both directions."""

    def __init__(self, session_id: str, window: int) -> None:
        self.session_id = session_id
        self.window = window
        self.stations: dict[str, Peer] = {}
        self.observers: dict[int, Peer] = {}
        self.directions = {d: DirectionStats(d, window)
                           for d in ("local_to_remote", "remote_to_local")}
        #: a clustered relay's link to its other workers (None: this process is the relay)
        self.remote: RemoteForwarder | None = None
        #: per direction, the newest ``tactile_compact`` key frame that reached this relay
        #: process, with its arrival time and mid hops (for peers that joined after it)
        self._compact_keys: dict[str, tuple[TactileCompact, int,
                                            tuple[tuple[str, str, int], ...]]] = {}
        #: key frames queued again for a peer that had not received the one a delta needs
        self.compact_keys_resent = 0

    @property
    def empty(self) -> bool:
        """No peer left."""
        return not self.stations and not self.observers

    def join(self, peer: Peer, resume: str = "") -> Peer | None:
        """Add a peer.

        Args:
            peer: the new peer.
            resume: the ``resume`` secret of the hello; when it matches the secret of the
                connection holding the role, that connection is the same station's older one
                (dead or silent: the station would not reconnect otherwise) and is replaced.

        Returns:
            The replaced peer (already removed, its ``evict`` called), or None.

        Raises:
            RoleTakenError: ``local``/``remote`` already held in this session by another
                station (no or a wrong ``resume`` secret).
        """
        if peer.role == "observer":
            self.observers[peer.peer_id] = peer
            return None
        holder = self.stations.get(peer.role)
        if holder is not None:
            if not (resume and holder.resume_secret
                    and hmac.compare_digest(resume.encode(), holder.resume_secret.encode())):
                raise RoleTakenError(f"role {peer.role!r} is already taken in session "
                                     f"{self.session_id!r}")
            del self.stations[peer.role]
            if holder.evict is not None:
                holder.evict()
        self.stations[peer.role] = peer
        return holder

    def leave(self, peer: Peer) -> None:
        """Remove a peer (no-op if it is not here)."""
        if peer.role == "observer":
            self.observers.pop(peer.peer_id, None)
        elif self.stations.get(peer.role) is peer:
            del self.stations[peer.role]

    def _receiver(self, sender_role: str) -> Peer | None:
        """The station that receives ``sender_role``'s data, or None: none joined, or the
        relay already decided to close it (``silent``, a failed write: closed outbox) and
        it only waits for its socket's close to leave the session."""
        receiver = self.stations.get(_OTHER[sender_role])
        return None if receiver is None or receiver.outbox.closed else receiver

    def route(self, sender: Peer, msg: DataMessage, t_in_us: int,
              wire: WireMessage | None = None) -> Error | None:
        """Forward one data message from a station with the stream's policy.

        Args:
            sender: the station that sent it.
            msg: the validated message (without the relay_in hop yet).
            t_in_us: relay clock when its bytes arrived.
            wire: its bytes as received, forwarded as they are with the relay's hops
                spliced in (None: ``msg`` is encoded for each receiver).

        Returns:
            An ``error`` to send back to the sender (non-fatal), or None.
        """
        stream = msg.TYPE
        if stream not in STREAMS_OF.get(sender.role, ()):
            return Error(code="wrong_direction",
                         message=f"{sender.role} may not send {stream}", fatal=False)
        direction = self.directions[DIRECTION_OF[sender.role]]
        ledger = direction.stream(stream)
        # station -> relay: from the sender's last own stamp (its send time), else ts
        sent_station_us = msg.ts_us
        for hop in reversed(msg.hops):
            if hop.clock == sender.role:
                sent_station_us = hop.t_us
                break
        offset = sender.clock.offset_us
        sent_ref_us: int | None = None
        if offset is None:
            direction.unsynced += 1
        else:
            sent_ref_us = round(sent_station_us - offset)
            if direction.senders.get(stream) != sender.peer_id:  # a new connection sends it
                direction.senders[stream] = sender.peer_id
                ledger.sender_changed(msg.seq)
            ledger.record(msg.seq, sent_ref_us, t_in_us)
        fwd = msg  # relay_in/relay_out hops are added when it is encoded for each receiver
        receiver = self._receiver(sender.role)
        elsewhere = False  # the receiver is on another worker of a cluster
        if self.remote is not None:
            elsewhere = self.remote.forward(self.session_id, sender.role, fwd, t_in_us,
                                            sent_ref_us, receiver is None)
        if receiver is None and elsewhere:
            self._to_observers(direction, fwd, t_in_us, wire=wire)
            return None
        return self.deliver(sender.role, fwd, t_in_us, sent_ref_us, wire=wire)

    def deliver(self, sender_role: str, msg: DataMessage, t_in_us: int,
                sent_ref_us: int | None, mid_hops: tuple[tuple[str, str, int], ...] = (),
                to_station: bool = True, wire: WireMessage | None = None) -> Error | None:
        """Queue a station's message (already booked on its uplink) for this relay's peers:
        the observers and, with ``to_station``, the other station, with the stream's policy.

        Args:
            sender_role: ``local`` or ``remote``.
            msg: the message, without relay hops.
            t_in_us: when it reached the relay (its ``relay_in`` stamp).
            sent_ref_us: its send time on the relay clock, None when the sender's clock offset
                is not known yet.
            mid_hops: stamps between ``relay_in`` and ``relay_out`` (the NATS leg of a
                message from another worker).
            to_station: also to the receiving station (else observers only).
            wire: the message's bytes as received (forwarded as they are, with the hops
                spliced in), or None.

        Returns:
            An ``error`` for the sender (``no_peer``, ``queue_full``), or None.
        """
        stream = msg.TYPE
        direction = self.directions[DIRECTION_OF[sender_role]]
        ledger = direction.stream(stream)
        if isinstance(msg, TactileCompact) and msg.key:
            self._compact_keys[direction.name] = (msg, t_in_us, mid_hops)
        self._to_observers(direction, msg, t_in_us, mid_hops, wire)
        if not to_station:
            return None
        # a compact key frame is never superseded in a latest-wins slot by the deltas that
        # need it: it goes in the ordered queue
        latest = is_latest_wins(msg)
        receiver = self._receiver(sender_role)
        if receiver is None:
            ledger.record_drop("no_peer")
            if msg.POLICY is StreamPolicy.LATEST_WINS:
                return None
            return Error(code="no_peer", message=f"{stream} seq {msg.seq} not delivered: no "
                         f"{_OTHER[sender_role]} station in session {self.session_id!r}",
                         stream=stream, seq=msg.seq)

        def on_send(pending: Pending, t_out_us: int) -> None:
            direction.forwarded += 1
            direction.relay.record(None, t_in_us, t_out_us)
            down = receiver.downlink_estimate_us
            if sent_ref_us is not None and down is not None:
                direction.end_to_end.record(None, sent_ref_us, round(t_out_us + down))

        key = f"{direction.name}:{stream}"
        if latest:
            self._key_frame_first(direction.name, msg, receiver)
            # a platform_state or tactile frame that replaces one never sent starts where
            # that one started
            held = receiver.outbox.held(key)
            if held is not None:
                carried = carry_motion(held.message, msg)
                if carried is not msg:
                    msg, wire = carried, None  # encoded from the message, new stamps and all
            if receiver.outbox.put_latest(key, msg, t_in_us, on_send, mid_hops,
                                          wire) is not None:
                ledger.record_drop("latest_wins")
        elif not receiver.outbox.put_ordered(msg, on_send, forwarded=True, t_in_us=t_in_us,
                                             mid_hops=mid_hops, wire=wire):
            ledger.record_drop("queue_full")
            ledger.set_queue_depth(len(receiver.outbox))
            if msg.POLICY is StreamPolicy.LATEST_WINS:
                return None
            return Error(code="queue_full", message=f"{stream} seq {msg.seq} refused: the "
                         f"{receiver.role} station's queue is full", fatal=False,
                         stream=stream, seq=msg.seq)
        elif isinstance(msg, TactileCompact):
            receiver.compact_key_seq[direction.name] = msg.seq
        ledger.set_queue_depth(len(receiver.outbox))
        return None

    def _key_frame_first(self, direction: str, msg: DataMessage, peer: Peer) -> None:
        """Before a ``tactile_compact`` delta, queue its key frame to a peer that was not
        given it (it joined, or rejoined, after the key frame passed): otherwise the peer
        renders nothing until the sender's next key frame, up to ``key_every`` frames
        later. The key frame keeps its own stamps, so the receiver ages it as what it is."""
        if not isinstance(msg, TactileCompact) or msg.key \
                or peer.compact_key_seq.get(direction) == msg.key_seq:
            return
        cached = self._compact_keys.get(direction)
        if cached is None or cached[0].seq != msg.key_seq:
            return  # not seen by this relay process (restarted, or another worker's)
        key, t_in_us, mid_hops = cached
        if peer.outbox.put_ordered(key, forwarded=True, t_in_us=t_in_us, mid_hops=mid_hops):
            peer.compact_key_seq[direction] = key.seq
            self.compact_keys_resent += 1

    def _to_observers(self, direction: DirectionStats, msg: DataMessage, t_in_us: int,
                      mid_hops: tuple[tuple[str, str, int], ...] = (),
                      wire: WireMessage | None = None) -> None:
        if not self.observers:
            return
        key = f"{direction.name}:{msg.TYPE}"
        if is_latest_wins(msg):
            for obs in self.observers.values():
                self._key_frame_first(direction.name, msg, obs)
                if obs.outbox.put_latest(key, msg, t_in_us, None, mid_hops, wire) is not None:
                    obs.observer_drops += 1
        else:
            for obs in self.observers.values():
                if not obs.outbox.put_ordered(msg, forwarded=True, t_in_us=t_in_us,
                                              mid_hops=mid_hops, wire=wire):
                    obs.observer_drops += 1
                elif isinstance(msg, TactileCompact):
                    obs.compact_key_seq[direction.name] = msg.seq
