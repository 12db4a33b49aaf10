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
