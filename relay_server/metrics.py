"""Figures of the relay as ``stats`` metrics, ``/status`` JSON and ``/metrics`` Prometheus text.

``stats`` metrics (scope ``relay``), pushed to every peer of a session each
``stats_interval_s``; all times are integer microseconds, ``null`` when not known yet::

    session                 session id
    role                    the receiving peer's role
    clock_offset_us         {local, remote}: station clock minus relay clock (the middle of
                              the clock filter's interval, see shared.clocksync); a station
                              on another worker of a cluster: its offset against that
                              worker moved onto this worker's clock (relay_server.cluster)
    clock_uncertainty_us    {local, remote}: bound on that offset's error when the stats
                              were built (half the interval plus drift since the last
                              exchange; across workers plus the bound on the workers'
                              offset and the drift since that worker's heartbeat); a
                              station adds its own drift allowance for the time since it
                              received them
    rtt_us                  {local, remote}: round trip of the chosen clock sample
    delay_us                {local_to_remote, remote_to_local}:
                              {station_to_relay, relay, relay_to_station, end_to_end}:
                                {p50, p99, max}
                            station_to_relay: sender's last own hop stamp (or ts) to relay_in,
                              corrected by the sender's offset; relay: relay_in -> relay_out
                              (what the relay adds); relay_to_station: receiver's clock
                              exchanges (t1 - offset - t0); end_to_end: sender stamp to
                              relay_out + half the receiver's best round trip (an estimate)
    jitter_us               {local_to_remote, remote_to_local}: RFC 3550 jitter of
                              station_to_relay (worst stream)
    rate_hz                 {local_to_remote, remote_to_local}: arrivals per second
    forwarded               {local_to_remote, remote_to_local}: messages written to the peer
    drops                   {local_to_remote, remote_to_local}:
                              {lost, latest_wins, queue_full, no_peer}
                            lost: sequence gaps (RFC 3550); latest_wins: state frames
                            replaced unsent; queue_full: ordered messages refused;
                            no_peer: sent while the other station was absent
    seq_resets              {local_to_remote, remote_to_local}: sequence jumps too large to
                              be loss (a sender restart): the gap count restarted there
    queue_depth             {local, remote}: messages waiting in the relay for that station
    observers               number of observers

``/status`` is the same per session plus per-stream details and peers; ``/metrics`` the
Prometheus text exposition (``teletouch_relay_*``).
"""

from __future__ import annotations

import math
from typing import Any

from relay_server.session import Peer, Session
from shared.ledger import LatencyLedger, LedgerSnapshot
from shared.timebase import now_us

__all__ = ["prometheus_text", "session_metrics", "session_status"]

_DIRECTIONS = ("local_to_remote", "remote_to_local")
_DROP_REASONS = ("latest_wins", "queue_full", "no_peer")


def _pcts(snap: LedgerSnapshot) -> dict[str, int | None]:
    def r(v: float | None) -> int | None:
        return None if v is None else round(v)
    return {"p50": r(snap.delay_p50_us), "p99": r(snap.delay_p99_us),
            "max": r(snap.delay_max_us)}


def _station(session: Session, role: str) -> Peer | None:
    return session.stations.get(role)


def _receiver_downlink(session: Session, direction: str) -> LatencyLedger | None:
    receiver = session.stations.get("remote" if direction == "local_to_remote" else "local")
    return None if receiver is None else receiver.downlink


def _held_elsewhere(session: Session, role: str) -> tuple[int | None, int | None]:
    """The clock offset and its bound of a station another worker of a cluster holds, on
    this worker's clock (:meth:`relay_server.cluster.ClusterLink.station_clock`), or
    (None, None)."""
    station_clock = getattr(session.remote, "station_clock", None)
    found = None if station_clock is None else station_clock(session.session_id, role)
    return (None, None) if found is None else found


def session_metrics(session: Session, role: str) -> dict[str, Any]:
    """The ``stats`` metrics of a session as seen by a peer of ``role`` (see module doc)."""
    offsets: dict[str, int | None] = {}
    uncertainty: dict[str, int | None] = {}
    rtts: dict[str, int | None] = {}
    depth: dict[str, int] = {}
    t_now = now_us()
    for r in ("local", "remote"):
        peer = _station(session, r)
        off: float | None = None
        unc: float | None = None
        if peer is not None:
            off, unc = peer.clock.offset_us, peer.clock.uncertainty_us(t_now)
        else:
            off, unc = _held_elsewhere(session, r)
        uncertainty[r] = None if unc is None else math.ceil(unc)
        rtt = None if peer is None else peer.clock.delay_us
        offsets[r] = None if off is None else round(off)
        rtts[r] = None if rtt is None else round(rtt)
        depth[r] = 0 if peer is None else len(peer.outbox)
    delay: dict[str, Any] = {}
    jitter: dict[str, float] = {}
    rate: dict[str, float] = {}
    drops: dict[str, Any] = {}
    forwarded: dict[str, int] = {}
    resets: dict[str, int] = {}
    for d in _DIRECTIONS:
        ds = session.directions[d]
        up = ds.uplink_snapshot()
        down = _receiver_downlink(session, d)
        delay[d] = {
            "station_to_relay": _pcts(up),
            "relay": _pcts(ds.relay.snapshot()),
            "relay_to_station": _pcts(down.snapshot()) if down is not None else
            {"p50": None, "p99": None, "max": None},
            "end_to_end": _pcts(ds.end_to_end.snapshot()),
        }
        jitter[d] = round(up.jitter_us, 1)
        rate[d] = round(up.rate_hz, 1)
        drops[d] = {"lost": up.lost, **{k: up.dropped.get(k, 0) for k in _DROP_REASONS}}
        forwarded[d] = ds.forwarded
        resets[d] = up.seq_resets
    return {"session": session.session_id, "role": role, "clock_offset_us": offsets,
            "clock_uncertainty_us": uncertainty, "rtt_us": rtts, "delay_us": delay,
            "jitter_us": jitter, "rate_hz": rate,
            "forwarded": forwarded, "drops": drops, "seq_resets": resets, "queue_depth": depth,
            "observers": len(session.observers)}


def _peer_status(peer: Peer) -> dict[str, Any]:
    return {"role": peer.role, "name": peer.name, "transport": peer.transport,
            "received": peer.received, "bad_messages": peer.bad_messages,
            "queue_depth": len(peer.outbox), "observer_drops": peer.observer_drops,
            "clock_samples": len(peer.clock), "reported": peer.reported}


def session_status(session: Session) -> dict[str, Any]:
    """Everything ``/status`` shows about one session (JSON-able)."""
    out = session_metrics(session, "observer")
    out.pop("role")
    streams: dict[str, Any] = {}
    for d in _DIRECTIONS:
        ds = session.directions[d]
        streams[d] = {name: lg.snapshot().as_dict() for name, lg in ds.uplink.items()}
        streams[d]["unsynced"] = ds.unsynced
    out["streams"] = streams
    out["compact_keys_resent"] = session.compact_keys_resent
    # the NATS leg of messages from other workers of a clustered relay (nats_out -> nats_in)
    out["nats_us"] = {d: _pcts(session.directions[d].nats.snapshot()) for d in _DIRECTIONS}
    out["peers"] = [_peer_status(p) for p in (*session.stations.values(),
                                              *session.observers.values())]
    return out


def _labels(**kw: str) -> str:
    inner = ",".join(f'{k}="{v}"' for k, v in kw.items())
    return "{" + inner + "}"


def prometheus_text(sessions: dict[str, Session], counters: dict[str, int]) -> str:
    """Prometheus text exposition of all sessions and relay-wide counters."""
    lines: list[str] = []

    def metric(name: str, kind: str, help_: str, samples: list[tuple[str, float]]) -> None:
        lines.append(f"# HELP teletouch_relay_{name} {help_}")
        lines.append(f"# TYPE teletouch_relay_{name} {kind}")
        lines.extend(f"teletouch_relay_{name}{lab} {val}" for lab, val in samples)

    metric("sessions", "gauge", "sessions with at least one peer", [("", len(sessions))])
    metric("events_total", "counter", "relay-wide events by kind",
           [(_labels(kind=k), v) for k, v in sorted(counters.items())])
    delay_s: list[tuple[str, float]] = []
    fwd_s: list[tuple[str, float]] = []
    drop_s: list[tuple[str, float]] = []
    jit_s: list[tuple[str, float]] = []
    off_s: list[tuple[str, float]] = []
    for sid, session in sorted(sessions.items()):
        m = session_metrics(session, "observer")
        for d in _DIRECTIONS:
            for leg, p in m["delay_us"][d].items():
                for q, key in (("0.5", "p50"), ("0.99", "p99"), ("1", "max")):
                    if p[key] is not None:
                        delay_s.append((_labels(session=sid, direction=d, leg=leg,
                                                quantile=q), p[key]))
            fwd_s.append((_labels(session=sid, direction=d), m["forwarded"][d]))
            jit_s.append((_labels(session=sid, direction=d), m["jitter_us"][d]))
            for reason, n in m["drops"][d].items():
                drop_s.append((_labels(session=sid, direction=d, reason=reason), n))
        for role, off in m["clock_offset_us"].items():
            if off is not None:
                off_s.append((_labels(session=sid, role=role), off))
    metric("delay_us", "gauge", "one-way delay percentiles over the recent window",
           delay_s)
    metric("forwarded_total", "counter", "messages forwarded", fwd_s)
    metric("drops_total", "counter", "messages lost or dropped by reason", drop_s)
    metric("jitter_us", "gauge", "RFC 3550 interarrival jitter", jit_s)
    metric("clock_offset_us", "gauge", "station clock minus relay clock", off_s)
    return "\n".join(lines) + "\n"
