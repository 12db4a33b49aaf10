"""Clock offset math and the minimum-delay filter, against synthetic clocks with known offset."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.clocksync import ClockFilter, sample_from_timestamps
from shared.errors import InputDataError


def exchange(offset_us: int, t0_us: int, up_us: int, hold_us: int, down_us: int
             ) -> tuple[int, int, int, int]:
    """One ping/pong with a station clock ``offset_us`` ahead: reference -> station -> back.

    ``up_us`` here is reference -> station, ``down_us`` station -> reference.
    """
    t1 = t0_us + up_us + offset_us
    t2 = t1 + hold_us
    t3 = t2 - offset_us + down_us
    return t0_us, t1, t2, t3


def test_symmetric_path_gives_exact_offset_and_delay() -> None:
    s = sample_from_timestamps(*exchange(12_345, 1_000_000, 700, 50, 700))
    assert s.offset_us == 12_345
    assert s.delay_us == 1400
    assert s.uplink_us == 700


@given(offset=st.integers(-10**12, 10**12), t0=st.integers(0, 10**15),
       up=st.integers(0, 10**7), down=st.integers(0, 10**7), hold=st.integers(0, 10**6))
def test_error_bounded_by_half_asymmetry(offset: int, t0: int, up: int, down: int,
                                          hold: int) -> None:
    s = sample_from_timestamps(*exchange(offset, t0, up, hold, down))
    assert abs(s.offset_us - offset) <= abs(up - down) / 2 + 1e-6
    assert s.delay_us == up + down
    # the error is exactly (up - down) / 2: the estimator is unbiased only for symmetric paths
    assert s.offset_us - offset == pytest.approx((up - down) / 2)


def test_inconsistent_timestamps_are_rejected() -> None:
    with pytest.raises(InputDataError):
        sample_from_timestamps(100, 0, 0, 50)  # t3 before t0
    with pytest.raises(InputDataError):
        sample_from_timestamps(0, 100, 50, 200)  # t2 before t1
    with pytest.raises(InputDataError):
        sample_from_timestamps(0, 0, 500, 100)  # hold longer than the round trip


@settings(max_examples=60)
@given(offset=st.integers(-10**9, 10**9), base=st.integers(50, 5000),
       spike=st.integers(20_000, 200_000), seed=st.integers(0, 2**32 - 1))
def test_min_delay_filter_beats_mean_under_spikes(offset: int, base: int, spike: int,
                                                  seed: int) -> None:
    rng = random.Random(seed)
    filt = ClockFilter(8)
    offsets = []
    t0 = 10**9
    # 8 exchanges: one clean (small symmetric jitter), the rest with a one-sided queueing
    # spike on a random direction, as a congested uplink or downlink would produce
    clean_at = rng.randrange(8)
    for i in range(8):
        up = base + rng.randint(0, 10)
        down = base + rng.randint(0, 10)
        if i != clean_at:
            if rng.random() < 0.5:
                up += rng.randint(spike // 2, spike)
            else:
                down += rng.randint(spike // 2, spike)
        s = filt.add_timestamps(*exchange(offset, t0, up, 30, down))
        offsets.append(s.offset_us)
        t0 += 1_000_000
    est = filt.offset_us
    assert est is not None
    mean_err = abs(sum(offsets) / len(offsets) - offset)
    filt_err = abs(est - offset)
    assert filt_err <= 5  # half of the clean sample's asymmetry (<= 10 us)
    assert filt_err < mean_err


def test_filter_keeps_only_last_n_samples() -> None:
    filt = ClockFilter(3)
    assert filt.offset_us is None and filt.to_reference_us(5) is None
    filt.add_timestamps(*exchange(100, 0, 10, 0, 10))  # best delay, will age out
    for k in range(3):
        filt.add_timestamps(*exchange(200, 1000 * (k + 1), 50, 0, 50))
    assert len(filt) == 3
    assert filt.offset_us == 200
    assert filt.to_reference_us(1200) == 1000


def test_filter_rejects_bad_size() -> None:
    with pytest.raises(ValueError):
        ClockFilter(0)


# --------------------------------------------------------------------------- bounds and steps

@settings(max_examples=200)
@given(offset=st.integers(-10**9, 10**9), seed=st.integers(0, 2**32 - 1),
       n=st.integers(1, 20), max_delay=st.integers(0, 300_000))
def test_true_offset_always_inside_the_reported_bound(offset: int, seed: int, n: int,
                                                      max_delay: int) -> None:
    """Whatever the (non-negative) path delays, |estimate - truth| <= uncertainty."""
    rng = random.Random(seed)
    filt = ClockFilter(8)
    t0 = 10**12
    for _ in range(n):
        up, down = rng.randint(0, max_delay), rng.randint(0, max_delay)
        stepped = filt.add(sample_from_timestamps(*exchange(offset, t0, up, rng.randint(0, 500),
                                                            down)))
        assert not stepped  # no step happened, none may be reported
        est, unc = filt.offset_us, filt.uncertainty_us(t0 + 2 * max_delay)
        assert est is not None and unc is not None
        assert abs(est - offset) <= unc + 1e-6
        best = filt.best  # never worse than the least-queued sample's own bound, aged
        assert best is not None
        latest = filt.latest
        assert latest is not None
        aged = max(t0 + 2 * max_delay, latest.t3_us) - best.t3_us
        assert unc <= best.delay_us / 2 + 500e-6 * aged + 1e-6
        t0 += rng.randint(1, 2_000_000)


@settings(max_examples=200)
@given(offset=st.integers(-10**9, 10**9), step=st.integers(-10**7, 10**7).filter(
    lambda s: abs(s) > 2_000), seed=st.integers(0, 2**32 - 1))
def test_a_clock_step_is_followed_at_the_next_exchange(offset: int, step: int,
                                                       seed: int) -> None:
    """8 samples before the step, then one after: the filter reports the step (when the
    step is larger than the intervals can hide) and the new estimate bounds the new truth."""
    rng = random.Random(seed)
    filt = ClockFilter(8)
    t0 = 10**12
    for _ in range(8):
        filt.add(sample_from_timestamps(*exchange(offset, t0, rng.randint(100, 400), 20,
                                                  rng.randint(100, 400))))
        t0 += 1_000_000
    stepped = filt.add(sample_from_timestamps(*exchange(offset + step, t0,
                                                        rng.randint(100, 400), 20,
                                                        rng.randint(100, 400))))
    assert stepped and filt.steps == 1 and len(filt) == 1
    est, unc = filt.offset_us, filt.uncertainty_us()
    assert est is not None and unc is not None
    assert abs(est - (offset + step)) <= unc + 1e-6
    assert unc <= 400  # one exchange of at most 800 us round trip


def test_drift_within_the_bound_is_not_a_step() -> None:
    """Clocks 400 ppm apart over 20 s, sampled each second on a 200 us path: no step."""
    filt = ClockFilter(8, drift_ppm=500.0)
    t0 = 10**12
    for i in range(20):
        off = 1000 + round(400e-6 * i * 1_000_000)
        assert not filt.add(sample_from_timestamps(*exchange(off, t0, 100, 10, 100)))
        t0 += 1_000_000
        assert abs((filt.offset_us or 0) - off) <= (filt.uncertainty_us() or 0) + 1e-6


def test_uncertainty_grows_with_time_since_the_last_exchange() -> None:
    filt = ClockFilter(8, drift_ppm=100.0)
    assert filt.uncertainty_us(0) is None and filt.interval() is None
    filt.add(sample_from_timestamps(*exchange(0, 10**9, 500, 0, 500)))
    assert filt.uncertainty_us() == pytest.approx(500)  # one exchange: half its round trip
    assert filt.uncertainty_us(10**9 + 1000 + 10_000_000) == pytest.approx(500 + 1000)
