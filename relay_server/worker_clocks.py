"""The other relay workers' clocks against this worker's, measured by their heartbeats.

A worker's stamps (``relay_in``, ``nats_out``) are on its own clock; the worker that receives
the message stamps ``nats_in`` and ``relay_out`` on its own. Across hosts the two clocks
differ by whatever NTP left (or by anything, without NTP), and the NATS leg and the relay's
residence come out wrong by that much. So the sender puts its stamps on the receiver's clock
before it publishes them, with the receiver's offset measured as NTP's symmetric mode does
(RFC 5905), on the heartbeats the workers exchange anyway (every ``HEARTBEAT_S``):

* a heartbeat carries its send time ``t`` and, for each other worker, an **echo**: the send
  time of the last heartbeat heard from it (on its clock) and when it was heard (on this
  one's);
* a worker that hears a heartbeat echoing one of its own has the four times of an exchange
  (``t0``: its send, ``t1``: the other's receive, ``t2``: the other's send, ``t3``: its
  receive), the other's offset and the round trip without the other's hold time, as a
  station has them from a clock ping (:func:`shared.clocksync.sample_from_timestamps`);
* the other worker holds our heartbeat until its next one (up to ``HEARTBEAT_S``): the clocks
  may drift apart meanwhile, so each sample's interval is widened by 500 ppm of the whole
  exchange (RFC 5905's dispersion), and a round trip that this drift could make slightly
  negative counts as 0. An echo counts once (a later heartbeat may repeat it);
* the samples go through the stations' :class:`~shared.clocksync.ClockFilter`: the least
  queued sample's offset within the intersection of all of theirs (the last 8, about 4 s),
  each widened for the clocks' drift since, and a bound on its error; a clock step is
  followed at the next exchange.

Workers on one kernel (the same boot id; Linux) should read one monotonic clock, and their
stamps then differ by their wall anchors (:func:`shared.timebase.wall_anchor_ns`) exactly
(0 for the workers of one ``run_workers``, which take their supervisor's anchor). But a VM
cloned from a snapshot keeps its boot id and not its monotonic clock, and a time namespace
shifts the monotonic clock under one boot id; so such a peer is measured like any other,
and its anchors' figure is taken, as exact (uncertainty 0), once an exchange agrees with it:
within the measure's bound plus ``ANCHOR_SLACK_US``. Until then its offset is the measured
one (none before the first exchange: stamps go out uncorrected, which for the workers of one
supervisor is already exact). A process whose anchors a measure refutes is measured from
then on (a WARNING, once per observing worker and peer process); its ``same_kernel`` in
``/status`` is false. Where the boot id is unknown (not Linux) every offset is measured.
A worker restarted under the same id (a container keeps its host name and pid) is a new
process: another anchor or boot id in its heartbeat starts its figures again.

The ``now_us`` clock never steps (monotonic plus an anchor read when a process starts): a
relay started before its host's clock was set keeps that offset until it is restarted (the
whole service: ``run_workers`` hands its own anchor to the workers it starts again). An
offset beyond 5 ms is logged as a WARNING once per host of such workers (again after it
came back under 2.5 ms).
"""

from __future__ import annotations

import collections
import logging
from dataclasses import dataclass, field
from typing import Any, TypeGuard

from shared.clocksync import ClockFilter, sample_from_timestamps
from shared.errors import InputDataError

__all__ = ["ANCHOR_SLACK_US", "WARN_OFFSET_US", "WorkerClocks"]

log = logging.getLogger(__name__)

#: an offset beyond this is logged (again after it came back under half of it)
WARN_OFFSET_US = 5_000
#: figures beyond this are a peer's bug, not a clock: ignored (a century, in microseconds)
_SANE_US = 100 * 365 * 86_400 * 1_000_000
#: the clocks' largest relative drift (NTP's largest slew): the filter's and the dispersion's
_DRIFT_PPM = 500.0
#: own heartbeat send times an echo may name (a few heartbeat periods)
_SENT_KEPT = 8
#: how far beyond its bound the measure may lie from the anchors' figure of one kernel: a
#: margin (rounding needs a few microseconds) so that no real exchange refutes true anchors;
#: a clone's offset smaller than the bound plus this goes unnoticed, an error below 5 ms
ANCHOR_SLACK_US = 1_000


def _is_int(value: object) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool)


@dataclass
class _Peer:
    """What this worker knows of another worker's clock."""

    filter: ClockFilter = field(default_factory=lambda: ClockFilter(drift_ppm=_DRIFT_PPM))
    #: the process heard: its (boot id, anchor) as its heartbeats give them
    process: tuple[object, object] | None = None
    #: its clock minus ours by the wall anchors, when it gives our boot id (else None)
    anchors_say_us: int | None = None
    #: an exchange agreed with ``anchors_say_us``: one monotonic clock, taken as exact
    anchored: bool = False
    #: an exchange refuted ``anchors_say_us``: not one clock, measured from then on
    refuted: bool = False
    #: the last heartbeat heard from it: (its send time, our receive time)
    heard: tuple[int, int] | None = None
    #: the send time of ours its last counted echo named (an echo counts once)
    echoed_t0: int | None = None
    host: str = "?"
    warned: bool = False


class WorkerClocks:
    """The other workers' clock offsets (see the module docstring).

    Args:
        me: this worker's id (what the others' echoes name it).
        boot_id: this kernel's boot id (None: unknown, every offset is measured).
        anchor_ns: this worker's wall clock minus the monotonic clock (ns).
    """

    def __init__(self, me: str, boot_id: str | None, anchor_ns: int) -> None:
        self.me = me
        self.boot_id = boot_id
        self.anchor_ns = anchor_ns
        self._peers: dict[str, _Peer] = {}
        self._sent: collections.deque[int] = collections.deque(maxlen=_SENT_KEPT)
        self._warned_hosts: set[str] = set()

    def stamp(self, hb: dict[str, Any], t_us: int) -> None:
        """Add this worker's clock fields to heartbeat ``hb``, sent at ``t_us``."""
        self._sent.append(t_us)
        hb["t"] = t_us
        hb["boot"] = self.boot_id
        hb["anchor"] = self.anchor_ns
        hb["echo"] = {w: list(p.heard) for w, p in self._peers.items() if p.heard is not None}

    def heard(self, worker: str, hb: dict[str, Any], received_us: int) -> None:
        """``worker``'s heartbeat ``hb`` arrived at ``received_us``; a figure that makes no
        sense (a peer's bug) is ignored."""
        boot, anchor = hb.get("boot"), hb.get("anchor")
        process = (boot if isinstance(boot, str) else None, anchor if _is_int(anchor) else None)
        peer = self._peers.get(worker)
        if peer is None or peer.process != process:  # new, or restarted under its id
            peer = self._peers[worker] = _Peer(process=process)
        host = hb.get("host")
        peer.host = host if isinstance(host, str) else "?"
        if self.boot_id is not None and boot == self.boot_id and _is_int(anchor) \
                and abs(anchor - self.anchor_ns) < _SANE_US * 1000:
            peer.anchors_say_us = round((anchor - self.anchor_ns) / 1000)
        if self._measure(peer, hb, received_us) and peer.anchors_say_us is not None \
                and not peer.refuted:
            self._test_anchors(worker, peer, received_us)
        self._check(worker, peer)

    def _measure(self, peer: _Peer, hb: dict[str, Any], received_us: int) -> bool:
        """Count the exchange ``hb`` completes, if any: True when it gave a sample."""
        sent = hb.get("t")
        if not _is_int(sent) or abs(sent - received_us) > _SANE_US:
            return False
        peer.heard = (sent, received_us)
        echo = hb.get("echo")
        mine = echo.get(self.me) if isinstance(echo, dict) else None
        if not (isinstance(mine, list) and len(mine) == 2 and all(map(_is_int, mine))):
            return False
        t0, t1 = mine
        if t0 not in self._sent or (peer.echoed_t0 is not None and t0 <= peer.echoed_t0):
            return False  # not a heartbeat of ours (or long ago), or counted already
        try:  # held up to a heartbeat: the clocks' drift meanwhile is counted
            sample = sample_from_timestamps(t0, t1, sent, received_us, drift_ppm=_DRIFT_PPM)
        except InputDataError:  # out of order, or a round trip below what drift explains
            return False
        peer.echoed_t0 = t0
        peer.filter.add(sample)
        return True

    def _test_anchors(self, worker: str, peer: _Peer, now_us: int) -> None:
        """Take the anchors' figure of a peer of this kernel while the measure holds it."""
        measured, bound = peer.filter.offset_us, peer.filter.uncertainty_us(now_us)
        said = peer.anchors_say_us
        if measured is None or bound is None or said is None:
            return
        if abs(said - measured) <= bound + ANCHOR_SLACK_US:
            peer.anchored = True
            return
        log.warning("relay worker %s (host %s) runs on this worker's kernel (boot id) but its "
                    "clock is %+.1f ms from this one's, not %+.1f ms as the wall anchors say "
                    "(within %.1f ms): not one monotonic clock (a VM cloned from a snapshot, "
                    "or a time namespace?); its offset is measured from now on", worker,
                    peer.host, measured / 1e3, said / 1e3, bound / 1e3)
        peer.refuted = True
        peer.anchored = False

    def _check(self, worker: str, peer: _Peer) -> None:
        offset = self.offset_us(worker)
        if offset is None:
            return
        if abs(offset) > WARN_OFFSET_US and not peer.warned:
            peer.warned = True
            first = peer.host not in self._warned_hosts  # once per host, not per worker
            self._warned_hosts.add(peer.host)
            log.log(logging.WARNING if first else logging.DEBUG,
                    "relay worker %s's clock (host %s) is %+.1f ms from this worker's: "
                    "stamps crossing between them are put on the receiver's clock, but check "
                    "the hosts' NTP (a relay started before its host's clock was set keeps "
                    "that offset until it is restarted)", worker, peer.host, offset / 1e3)
        elif abs(offset) <= WARN_OFFSET_US // 2 and peer.warned:
            peer.warned = False
            if not any(p.warned for p in self._peers.values() if p.host == peer.host):
                self._warned_hosts.discard(peer.host)

    def offset_us(self, worker: str) -> int | None:
        """``worker``'s clock minus this worker's (us); None while not known."""
        peer = self._peers.get(worker)
        if peer is None:
            return None
        if peer.anchored and peer.anchors_say_us is not None:
            return peer.anchors_say_us
        offset = peer.filter.offset_us
        return None if offset is None else round(offset)

    def estimate(self, worker: str, now_us: int) -> tuple[int, float] | None:
        """``worker``'s clock minus this worker's (us) and a bound on its error at ``now_us``
        (0 for a peer of this kernel whose anchors an exchange agreed with); None while not
        known."""
        peer = self._peers.get(worker)
        offset = self.offset_us(worker)
        if peer is None or offset is None:
            return None
        if peer.anchored:
            return offset, 0.0
        bound = peer.filter.uncertainty_us(now_us)
        return None if bound is None else (offset, bound + 0.5)  # + the offset's rounding

    def to_theirs(self, worker: str, t_us: int) -> int:
        """A time on this worker's clock on ``worker``'s (unchanged while not known)."""
        offset = self.offset_us(worker)
        return t_us if offset is None else t_us + offset

    def forget(self, worker: str) -> None:
        """``worker`` is gone."""
        self._peers.pop(worker, None)

    def known(self) -> set[str]:
        """The workers this worker keeps figures of."""
        return set(self._peers)

    def status(self, worker: str, now_us: int) -> dict[str, Any]:
        """What ``/status`` shows of ``worker``'s clock at ``now_us`` (this worker's clock):
        its offset (its clock minus this one's), a bound on the offset's error by then, the
        least round trip of the exchanges, and whether it reads the same monotonic clock (an
        exchange agreed with the wall anchors: the offset is theirs, exact)."""
        peer = self._peers.get(worker)
        same = peer is not None and peer.anchored
        bound = None if peer is None or same else peer.filter.uncertainty_us(now_us)
        rtt = None if peer is None else peer.filter.delay_us
        return {"clock_offset_us": self.offset_us(worker),
                "clock_uncertainty_us": 0 if same else
                None if bound is None else round(bound),
                "nats_rtt_min_us": None if rtt is None else round(rtt),
                "same_kernel": same}
