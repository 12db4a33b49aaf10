"""PoseHistory: the pad's position at a frame's capture time, interpolated (property tests
against the analytic position of a uniform motion)."""

from __future__ import annotations

import threading

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.agent.pose_history import PoseHistory


@given(v=st.tuples(*[st.floats(-500.0, 500.0)] * 3),
       p0=st.tuples(*[st.floats(-100.0, 100.0)] * 3),
       times=st.lists(st.integers(0, 10**6), min_size=2, max_size=64, unique=True),
       frac=st.floats(0.0, 1.0))
def test_uniform_motion_is_recovered_exactly_between_readings(
        v: tuple[float, float, float], p0: tuple[float, float, float], times: list[int],
        frac: float) -> None:
    """Readings of a pad moving at a constant velocity (mm/s), added in any order: the
    position at any moment between the first and the last reading is the motion's."""
    hist = PoseHistory(size=64)
    for t in times:  # unsorted: two threads add
        hist.add(t, tuple(p + vi * t / 1e6 for p, vi in zip(p0, v, strict=True)))
    lo, hi = min(times), max(times)
    t_q = round(lo + frac * (hi - lo))
    got = hist.at(t_q)
    assert got is not None
    want = tuple(p + vi * t_q / 1e6 for p, vi in zip(p0, v, strict=True))
    assert got == pytest.approx(want, abs=1e-6 + 1e-9 * max(abs(x) for x in want))


@given(times=st.lists(st.integers(0, 10**6), min_size=1, max_size=20, unique=True),
       after=st.integers(1, 200_000))
def test_outside_the_readings_it_holds_briefly_then_says_unknown(
        times: list[int], after: int) -> None:
    hist = PoseHistory(max_hold_us=50_000)
    for t in times:
        hist.add(t, (float(t), 0.0, 0.0))
    last = max(times)
    got = hist.at(last + after)
    assert got == ((float(last), 0.0, 0.0) if after <= 50_000 else None)
    assert hist.at(min(times) - 1) is None  # before the oldest: unknown, never guessed


def test_no_readings_or_bad_ones_give_nothing() -> None:
    hist = PoseHistory()
    assert hist.at(5) is None
    hist.add(1, (float("nan"), 0.0, 0.0))
    assert len(hist) == 0 and hist.at(1) is None


@settings(max_examples=20)
@given(n=st.integers(2, 200))
def test_only_the_newest_readings_are_kept(n: int) -> None:
    hist = PoseHistory(size=16)
    for t in range(n):
        hist.add(t * 1000, (float(t), 0.0, 0.0))
    assert len(hist) == min(n, 16)
    oldest = max(0, n - 16)
    assert hist.at(oldest * 1000) == (float(oldest), 0.0, 0.0)
    if oldest:
        assert hist.at(oldest * 1000 - 1) is None


def test_concurrent_adds_and_reads() -> None:
    hist = PoseHistory(size=64)
    stop = threading.Event()

    def writer(offset: int) -> None:
        t = offset
        while not stop.is_set():
            hist.add(t, (t / 1e3, 0.0, 0.0))
            t += 2

    threads = [threading.Thread(target=writer, args=(k,)) for k in (0, 1)]
    for th in threads:
        th.start()
    try:
        for _ in range(2000):
            got = hist.at(10**9)  # far after: None, or the newest when within the hold
            assert got is None or got[0] >= 0.0
    finally:
        stop.set()
        for th in threads:
            th.join()
