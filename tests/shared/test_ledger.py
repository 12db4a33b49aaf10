"""Latency ledger against numpy references: percentiles, RFC 3550 jitter, loss, bounds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from shared.ledger import MAX_DELAY_US, LatencyLedger, merge_snapshots, percentiles


def reference_jitter(transits: np.ndarray) -> float:
    j = 0.0
    for d in np.diff(transits):
        j += (abs(float(d)) - j) / 16.0
    return j


@settings(max_examples=80, deadline=None)
@given(delays=st.lists(st.integers(-10**6, 10**7), min_size=1, max_size=300),
       window=st.integers(1, 128))
def test_percentiles_and_jitter_match_numpy(delays: list[int], window: int) -> None:
    ledger = LatencyLedger(window)
    sent = np.arange(len(delays), dtype=np.int64) * 1000 + 10**12
    recv = sent + np.asarray(delays, np.int64)
    for i, (s, r) in enumerate(zip(sent, recv, strict=True)):
        assert ledger.record(i, int(s), int(r)) == delays[i]
    snap = ledger.snapshot()
    ref = np.asarray(delays[-window:], dtype=np.int64)
    np.testing.assert_array_equal(snap.delays_us, ref)
    assert snap.delay_p50_us == pytest.approx(float(np.percentile(ref, 50)))
    assert snap.delay_p99_us == pytest.approx(float(np.percentile(ref, 99)))
    assert snap.delay_max_us == float(ref.max())
    assert snap.delay_mean_us == pytest.approx(float(ref.mean()))
    assert snap.jitter_us == pytest.approx(reference_jitter(np.asarray(delays)), rel=1e-9,
                                           abs=1e-9)
    assert snap.received == len(delays)
    assert snap.window == min(window, len(delays))


def test_empty_ledger_has_no_percentiles() -> None:
    snap = LatencyLedger(8).snapshot()
    assert snap.delay_p50_us is None and snap.rate_hz == 0.0 and snap.lost == 0


def test_loss_reorder_and_drops() -> None:
    ledger = LatencyLedger(64)
    for seq in (0, 1, 2, 5, 6, 4, 9):  # 3, 7, 8 missing; 4 arrives late
        ledger.record(seq, seq * 1000, seq * 1000 + 100)
    assert ledger.lost == 3
    assert ledger.out_of_order == 1
    ledger.record_drop("latest_wins", 4)
    ledger.record_drop("latest_wins")
    ledger.record_drop("queue_full")
    snap = ledger.snapshot()
    assert snap.dropped == {"latest_wins": 5, "queue_full": 1}
    assert snap.dropped_total == 6
    with pytest.raises(ValueError):
        ledger.record_drop("x", -1)


def test_rate_and_queue_depth() -> None:
    ledger = LatencyLedger(1000)
    for i in range(501):  # 500 intervals of 2 ms -> 500 Hz
        ledger.record(i, i * 2000, i * 2000 + 300)
    assert ledger.snapshot().rate_hz == pytest.approx(500.0)
    ledger.set_queue_depth(7)
    ledger.set_queue_depth(2)
    snap = ledger.snapshot()
    assert (snap.queue_depth, snap.queue_depth_max) == (2, 7)


def test_memory_is_bounded() -> None:
    ledger = LatencyLedger(16)
    for i in range(10_000):
        ledger.record(i, i, i + (i % 7))
    snap = ledger.snapshot()
    assert snap.delays_us.size == 16
    assert snap.received == 10_000
    assert ledger._delays.size == 16


def test_merge_matches_pooled_reference() -> None:
    rng = np.random.default_rng(3)
    a, b = LatencyLedger(100), LatencyLedger(100)
    da, db = rng.integers(0, 5000, 80), rng.integers(1000, 9000, 50)
    for i, d in enumerate(da):
        a.record(i, i * 1000, i * 1000 + int(d))
    for i, d in enumerate(db):
        b.record(i * 2, i * 1000, i * 1000 + int(d))  # every other seq missing
    b.record_drop("latest_wins", 3)
    merged = merge_snapshots([a.snapshot(), b.snapshot()])
    pooled = np.concatenate([da, db])
    assert merged.delay_p99_us == pytest.approx(float(np.percentile(pooled, 99)))
    assert merged.received == 130
    assert merged.lost == 49
    assert merged.dropped == {"latest_wins": 3}
    assert merged.jitter_us == max(a.jitter_us, b.jitter_us)
    assert merge_snapshots([]).received == 0


def test_a_huge_sequence_jump_is_a_reset_not_loss() -> None:
    """Issue 11: one seq of 2^63 - 1 made ``lost`` 9.2e18 for the rest of the connection."""
    ledger = LatencyLedger(64, max_seq_jump=1000)
    for seq in range(10):
        ledger.record(seq, 0, 10)
    ledger.record(2**63 - 1, 0, 10)
    assert ledger.lost == 0 and ledger.seq_resets == 1
    ledger.record(0, 0, 10)  # the sender restarts from 0: another reset, still no loss
    ledger.record(2, 0, 10)  # then a real gap of one
    assert (ledger.lost, ledger.seq_resets) == (1, 2)
    snap = ledger.snapshot()
    assert (snap.lost, snap.seq_resets) == (1, 2)
    assert snap.as_dict()["seq_resets"] == 2
    assert merge_snapshots([snap, snap]).seq_resets == 4


def test_a_sender_restarted_from_seq_1_is_a_reset_and_its_losses_count() -> None:
    """Found by review: a station restarted from seq 1 (a backward jump under 2^20) had its
    whole new run counted out_of_order, and the losses of both runs vanished from lost."""
    ledger = LatencyLedger(64)
    for seq in (s for s in range(1, 5001) if not 2000 < s <= 2500):  # 500 lost
        ledger.record(seq, 0, 10)
    assert (ledger.lost, ledger.seq_resets) == (500, 0)
    for seq in (s for s in range(1, 3001) if not 1000 < s <= 1300):  # restarted; 300 lost
        ledger.record(seq, 0, 10)
    assert (ledger.lost, ledger.out_of_order, ledger.seq_resets) == (800, 0, 1)
    # a message a little late is still a late message, not a restart
    ledger.record(2990, 0, 10)
    assert (ledger.out_of_order, ledger.seq_resets) == (1, 1)


def test_a_new_sender_numbering_from_1_again_restarts_the_count_however_short_its_run() -> None:
    """Found by review: a run that had not passed max_misorder (a station restarting every
    couple of seconds) was still counted out_of_order; the relay tells the ledger when a new
    connection sends the stream."""
    ledger = LatencyLedger(64)
    for seq in (s for s in range(1, 61) if s not in range(20, 30)):  # 10 lost
        ledger.record(seq, 0, 10)
    ledger.sender_changed(1)  # a restarted station: from 1 again
    for seq in (s for s in range(1, 61) if s not in range(40, 45)):  # 5 lost
        ledger.record(seq, 0, 10)
    assert (ledger.lost, ledger.out_of_order, ledger.seq_resets) == (15, 0, 1)
    ledger.sender_changed(61)  # the same station reconnected (resume): its seqs go on
    ledger.record(61, 0, 10)
    assert (ledger.lost, ledger.seq_resets) == (15, 1)


def test_a_delay_out_of_range_is_counted_not_booked() -> None:
    """A station clock offset of ~9e18 us made a delay overflow the int64 ring: OverflowError
    out of the relay's routing. Such a delay is counted in ``out_of_range`` and left out of
    the figures; the message still counts as received and its seq is accounted."""
    ledger = LatencyLedger(8)
    ledger.record(1, 0, 1_000)
    ledger.record(2, -(2**62), 2**62)  # a delay of 2**63: beyond int64
    ledger.record(3, 0, MAX_DELAY_US + 1)  # fits int64, but no latency is a century
    ledger.record(4, 2**64, 2**64 + 5)  # a sane delay at a receive time beyond int64
    ledger.record(5, 0, 2_000)
    snap = ledger.snapshot()
    assert (snap.received, snap.out_of_range, snap.lost, snap.window) == (5, 3, 0, 2)
    assert snap.delays_us.tolist() == [1_000, 2_000] and snap.delay_max_us == 2_000
    assert snap.jitter_us == 1_000 / 16.0
    assert snap.as_dict()["out_of_range"] == 3
    assert merge_snapshots([snap, snap]).out_of_range == 6


@settings(max_examples=80, deadline=None)
@given(seqs=st.lists(st.integers(0, 2**63 - 1), min_size=1, max_size=200),
       max_jump=st.integers(1, 10_000))
def test_lost_is_bounded_by_the_jump_limit(seqs: list[int], max_jump: int) -> None:
    """Whatever the seqs, each run adds at most max_jump per arrival to ``lost``."""
    ledger = LatencyLedger(16, max_seq_jump=max_jump)
    for seq in seqs:
        ledger.record(seq, 0, 1)
    assert 0 <= ledger.lost <= len(seqs) * max_jump
    assert ledger.seq_resets <= len(seqs) - 1


@settings(max_examples=200, deadline=None)
@given(hnp.arrays(np.int64, st.integers(1, 300), elements=st.integers(-10**12, 10**12)),
       st.lists(st.floats(0.0, 100.0), min_size=1, max_size=4))
def test_percentiles_match_numpy(values: np.ndarray, qs: list[float]) -> None:
    """The partial-sort percentiles are numpy's linear-interpolation percentiles."""
    ours = percentiles(values, tuple(qs))
    ref = np.percentile(values, qs)
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-3)
