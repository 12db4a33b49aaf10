"""shared.freshness: an error bound below zero (or not finite) is an unknown clock."""

from __future__ import annotations

import math

import pytest

from shared.freshness import clock_view_from_stats, judge_age

LIMITS = {"max_age_us": 100_000.0, "max_uncertainty_us": 30_000.0}


def test_a_fresh_stamp_with_a_known_clock_is_fresh() -> None:
    view = clock_view_from_stats({"clock_offset_us": {"local": 0, "remote": 0},
                                  "clock_uncertainty_us": {"local": 1000, "remote": 1000}}, 0)
    rel = view.relative("remote", "local", 0)
    assert rel == (0.0, 2000.0)
    assert judge_age(0, 50_000, rel, **LIMITS).verdict == "fresh"
    assert judge_age(0, 140_000, rel, **LIMITS).verdict == "stale"


@pytest.mark.parametrize("bounds", [(-50_000, 0), (-50_000, 60_000), (0, -1)])
def test_a_negative_bound_in_the_relays_stats_is_an_unknown_clock(
        bounds: tuple[int, int]) -> None:
    """A negative bound would widen the 100 ms window: a 140 ms old command looked fresh."""
    view = clock_view_from_stats({"clock_offset_us": {"local": 0, "remote": 0},
                                  "clock_uncertainty_us": {"local": bounds[0],
                                                           "remote": bounds[1]}}, 0)
    rel = view.relative("remote", "local", 0)
    assert rel is None
    assert judge_age(0, 140_000, rel, **LIMITS).verdict == "unknown_clock"


@pytest.mark.parametrize("unc", [-50_000.0, -1e-3, math.nan, math.inf, -math.inf])
def test_judge_age_refuses_a_negative_or_non_finite_bound(unc: float) -> None:
    verdict = judge_age(0, 140_000, (0.0, unc), **LIMITS)
    assert verdict.verdict == "unknown_clock" and not verdict.fresh
