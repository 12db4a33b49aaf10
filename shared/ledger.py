"""Latency ledger of one stream: one-way delay, jitter, rate, drops, queue depth.

Sans-I/O and clock-agnostic: the caller gives each message's send time already converted
to a common reference clock (see :mod:`shared.clocksync`) and its receive time; the
ledger keeps

* delays ``received - sent`` (us) in a bounded ring buffer, for p50 / p99 / max;
* the RFC 3550 interarrival jitter ``J += (|D| - J) / 16`` with
  ``D = (R_j - S_j) - (R_i - S_i)`` over consecutive arrivals;
* sequence accounting: ``lost`` (RFC 3550: expected from the seq range minus received,
  so a late arrival fills its gap), ``out_of_order`` (seq not above the highest seen),
  ``dropped`` (discarded on purpose, e.g. relay latest-wins, by reason), and
  ``seq_resets``: a sequence jump of more than ``max_seq_jump`` forward (a hostile seq of
  2^63 - 1) or of more than ``max_misorder`` back (a sender restarted from 1) restarts the
  gap count from the new seq instead of adding the jump to ``lost`` or counting the new run
  ``out_of_order`` (RFC 3550 A.1 treats such jumps the same way);
* arrival rate over the window and the queue depth (current and peak);
* ``out_of_range``: arrivals whose delay is beyond :data:`MAX_DELAY_US` either way (a
  peer's figures that make no sense: a hostile ``ts``, a wild clock) are counted there and
  left out of the delays, jitter and rate (they count as received, their seq is accounted).

Memory is O(window) whatever the run length.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["MAX_DELAY_US", "LatencyLedger", "LedgerSnapshot", "merge_snapshots"]

#: a delay beyond this either way is a peer's bug, not a latency (a century, in microseconds;
#: far inside the int64 ring buffers)
MAX_DELAY_US = 100 * 365 * 86_400 * 1_000_000
_INT64_MIN, _INT64_MAX = -(1 << 63), (1 << 63) - 1


@dataclass(frozen=True, slots=True)
class LedgerSnapshot:
    """Figures of one ledger (or several merged) at one moment. Times in microseconds."""

    received: int
    lost: int
    out_of_order: int
    dropped: dict[str, int]
    delay_p50_us: float | None
    delay_p99_us: float | None
    delay_max_us: float | None
    delay_min_us: float | None
    delay_mean_us: float | None
    jitter_us: float
    rate_hz: float
    queue_depth: int
    queue_depth_max: int
    window: int = 0
    seq_resets: int = 0
    out_of_range: int = 0
    delays_us: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    recv_times_us: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)

    @property
    def dropped_total(self) -> int:
        """All deliberate drops, every reason."""
        return sum(self.dropped.values())

    def as_dict(self) -> dict[str, object]:
        """Plain JSON-able figures (no arrays)."""
        return {
            "received": self.received, "lost": self.lost, "out_of_order": self.out_of_order,
            "dropped": dict(self.dropped), "delay_p50_us": self.delay_p50_us,
            "delay_p99_us": self.delay_p99_us, "delay_max_us": self.delay_max_us,
            "delay_min_us": self.delay_min_us, "delay_mean_us": self.delay_mean_us,
            "jitter_us": self.jitter_us, "rate_hz": self.rate_hz,
            "queue_depth": self.queue_depth, "queue_depth_max": self.queue_depth_max,
            "window": self.window, "seq_resets": self.seq_resets,
            "out_of_range": self.out_of_range,
        }


def _rate_hz(recv_times_us: np.ndarray) -> float:
    if recv_times_us.size < 2:
        return 0.0
    span = float(recv_times_us.max() - recv_times_us.min())
    return (recv_times_us.size - 1) * 1e6 / span if span > 0 else 0.0


def percentiles(values: np.ndarray, qs: tuple[float, ...]) -> list[float]:
    """``np.percentile(values, qs)`` (linear interpolation), from one partial sort.

    The relay computes these for every stream of a session once a second while it forwards;
    one ``np.partition`` on the order statistics needed is about 3x cheaper than
    ``np.percentile`` on a full window, and gives the same numbers.

    Args:
        values: a non-empty 1-D array.
        qs: percentiles in [0, 100].
    """
    n = values.size
    pos = [q / 100.0 * (n - 1) for q in qs]
    ranks = sorted({int(np.floor(p)) for p in pos} | {int(np.ceil(p)) for p in pos})
    part = np.partition(values, ranks)
    out = []
    for p in pos:
        lo, hi = int(np.floor(p)), int(np.ceil(p))
        a, b = float(part[lo]), float(part[hi])
        out.append(a + (b - a) * (p - lo))
    return out


def _stats(delays: np.ndarray) -> tuple[float | None, ...]:
    if delays.size == 0:
        return (None, None, None, None, None)
    p50, p99 = percentiles(delays, (50.0, 99.0))
    return (p50, p99, float(delays.max()), float(delays.min()), float(delays.mean()))


#: default largest sequence jump still counted as loss (about 17 min of a 1 kHz stream)
DEFAULT_MAX_SEQ_JUMP = 1 << 20
#: a seq further back than this from the highest seen restarts the gap count (RFC 3550's
#: MAX_MISORDER): a restarted sender, not a late message
DEFAULT_MAX_MISORDER = 100


class LatencyLedger:
    """Per-stream latency statistics over a bounded window.

    Args:
        window: delays (and arrival times) kept for percentiles and rate.
        max_seq_jump: a seq further ahead than this of the highest seen restarts the gap
            accounting (counted in ``seq_resets``) instead of counting as loss.
        max_misorder: a seq further back than this from the highest seen restarts it too
            (found by review: a station restarted from seq 1 had its whole new run counted
            ``out_of_order`` and its losses hidden); closer back, it is a late message.
    """

    def __init__(self, window: int = 4096, max_seq_jump: int = DEFAULT_MAX_SEQ_JUMP,
                 max_misorder: int = DEFAULT_MAX_MISORDER) -> None:
        if window < 1:
            raise ValueError("window must be >= 1")
        if max_seq_jump < 1 or max_misorder < 1:
            raise ValueError("max_seq_jump and max_misorder must be >= 1")
        self.window = window
        self.max_seq_jump = max_seq_jump
        self.max_misorder = max_misorder
        self._delays = np.zeros(window, np.int64)
        self._recv = np.zeros(window, np.int64)
        self._n = 0  # delays booked; ring index = _n % window
        self._received = 0  # arrivals (also those out of range)
        self._jitter_us = 0.0
        self._last_transit: int | None = None
        self._first_seq: int | None = None
        self._highest_seq = 0
        self._seq_received = 0
        self._lost_before_reset = 0  # loss banked by earlier sequence runs
        self.seq_resets = 0
        self.out_of_range = 0  # arrivals with a delay beyond MAX_DELAY_US (not booked)
        self.out_of_order = 0
        self.dropped: dict[str, int] = {}
        self.queue_depth = 0
        self.queue_depth_max = 0

    @property
    def received(self) -> int:
        """Messages recorded so far (also those counted in ``out_of_range``)."""
        return self._received

    @property
    def jitter_us(self) -> float:
        """RFC 3550 interarrival jitter estimate (us)."""
        return self._jitter_us

    def record(self, seq: int | None, sent_us: int, received_us: int) -> int:
        """Account one arrival.

        Args:
            seq: the sender's sequence number for gap accounting, or None to skip it.
            sent_us: send (or capture) time, already in the reference clock.
            received_us: receive time, reference clock.

        Returns:
            The one-way delay ``received_us - sent_us`` (may be negative if the clock
            offset is off). One beyond :data:`MAX_DELAY_US` either way (or a receive time
            outside int64) is not booked, only counted in ``out_of_range``.
        """
        transit = int(received_us) - int(sent_us)
        self._received += 1
        if -MAX_DELAY_US <= transit <= MAX_DELAY_US and _INT64_MIN <= received_us <= _INT64_MAX:
            i = self._n % self.window
            self._delays[i] = transit
            self._recv[i] = received_us
            self._n += 1
            if self._last_transit is not None:
                d = transit - self._last_transit
                self._jitter_us += (abs(d) - self._jitter_us) / 16.0
            self._last_transit = transit
        else:
            self.out_of_range += 1
        if seq is not None:
            if self._first_seq is None:
                self._first_seq = self._highest_seq = seq
                self._seq_received = 1
            elif (seq - self._highest_seq > self.max_seq_jump
                  or self._highest_seq - seq > self.max_misorder):
                # the old run's loss, before this arrival counts in the new one (it was
                # counted in the old, one short)
                self._lost_before_reset += self._run_lost()
                self.seq_resets += 1
                self._first_seq = self._highest_seq = seq
                self._seq_received = 1
            else:
                self._seq_received += 1
                if seq > self._highest_seq:
                    self._highest_seq = seq
                else:
                    self.out_of_order += 1
        return transit

    def sender_changed(self, seq: int) -> None:
        """A new connection sends this stream from now on, ``seq`` its first: a seq not
        above the highest seen is a restarted sender (it numbers from 1 again), so the gap
        count restarts (``seq_resets``) however short the old run was (found by review:
        a run that had not passed ``max_misorder`` was still counted ``out_of_order``)."""
        if self._first_seq is not None and seq <= self._highest_seq:
            self._lost_before_reset += self._run_lost()
            self.seq_resets += 1
            self._first_seq = None
            self._highest_seq = 0
            self._seq_received = 0

    def _run_lost(self) -> int:
        if self._first_seq is None:
            return 0
        expected = self._highest_seq - self._first_seq + 1
        return max(0, expected - self._seq_received)

    @property
    def lost(self) -> int:
        """RFC 3550 cumulative loss: expected (highest - first + 1) minus received, >= 0,
        summed over the sequence runs separated by resets (so at most ``max_seq_jump`` per
        run beyond the messages actually missing)."""
        return self._lost_before_reset + self._run_lost()

    def record_drop(self, reason: str = "latest_wins", count: int = 1) -> None:
        """Count messages discarded on purpose (``latest_wins``, ``queue_full``, ...)."""
        if count < 0:
            raise ValueError("count must be >= 0")
        self.dropped[reason] = self.dropped.get(reason, 0) + count

    def set_queue_depth(self, depth: int) -> None:
        """Note the current queue depth (messages waiting); the peak is kept."""
        self.queue_depth = depth
        if depth > self.queue_depth_max:
            self.queue_depth_max = depth

    def delays_us(self) -> np.ndarray:
        """The delays in the window, oldest first (a copy)."""
        return self._window(self._delays)

    def _window(self, ring: np.ndarray) -> np.ndarray:
        if self._n <= self.window:
            return ring[: self._n].copy()
        i = self._n % self.window
        return np.concatenate((ring[i:], ring[:i]))

    def snapshot(self) -> LedgerSnapshot:
        """Figures now (percentiles over the window, counters since the start)."""
        delays = self.delays_us()
        recv = self._window(self._recv)
        p50, p99, mx, mn, mean = _stats(delays)
        return LedgerSnapshot(
            received=self._received, lost=self.lost, out_of_order=self.out_of_order,
            dropped=dict(self.dropped), delay_p50_us=p50, delay_p99_us=p99, delay_max_us=mx,
            delay_min_us=mn, delay_mean_us=mean, jitter_us=self._jitter_us,
            rate_hz=_rate_hz(recv), queue_depth=self.queue_depth,
            queue_depth_max=self.queue_depth_max, window=int(delays.size), delays_us=delays,
            recv_times_us=recv, seq_resets=self.seq_resets, out_of_range=self.out_of_range)


def merge_snapshots(snapshots: list[LedgerSnapshot]) -> LedgerSnapshot:
    """Combine the snapshots of several streams into one (percentiles over all windows).

    Counters and rates add, jitter is the worst stream's, queue depths add.
    """
    if not snapshots:
        return LatencyLedger(1).snapshot()
    delays = np.concatenate([s.delays_us for s in snapshots])
    dropped: dict[str, int] = {}
    for s in snapshots:
        for k, v in s.dropped.items():
            dropped[k] = dropped.get(k, 0) + v
    p50, p99, mx, mn, mean = _stats(delays)
    return LedgerSnapshot(
        received=sum(s.received for s in snapshots), lost=sum(s.lost for s in snapshots),
        out_of_order=sum(s.out_of_order for s in snapshots), dropped=dropped,
        delay_p50_us=p50, delay_p99_us=p99, delay_max_us=mx, delay_min_us=mn,
        delay_mean_us=mean, jitter_us=max(s.jitter_us for s in snapshots),
        rate_hz=sum(s.rate_hz for s in snapshots),
        queue_depth=sum(s.queue_depth for s in snapshots),
        queue_depth_max=sum(s.queue_depth_max for s in snapshots), window=int(delays.size),
        seq_resets=sum(s.seq_resets for s in snapshots),
        out_of_range=sum(s.out_of_range for s in snapshots), delays_us=delays,
        recv_times_us=np.concatenate([s.recv_times_us for s in snapshots]))
