"""Counter dataclasses summed field by field (the totals over reopened links and children)."""

from __future__ import annotations

import dataclasses

from hypothesis import given
from hypothesis import strategies as st

from local_site.display.base import DisplayStats
from local_site.platform.base import PlatformStats
from shared.counters import add_counters

_N = len(dataclasses.fields(PlatformStats))


@given(st.lists(st.integers(0, 2**40), min_size=_N, max_size=_N),
       st.lists(st.integers(0, 2**40), min_size=_N, max_size=_N))
def test_each_field_is_the_sum_and_the_type_is_kept(a: list[int], b: list[int]) -> None:
    x, y = PlatformStats(*a), PlatformStats(*b)
    total = add_counters(x, y)
    assert type(total) is PlatformStats
    assert dataclasses.astuple(total) == tuple(p + q for p, q in zip(a, b, strict=True))
    assert add_counters(total, PlatformStats()) == total  # zero counters change nothing


def test_another_counters_class() -> None:
    assert add_counters(DisplayStats(commands=2, resumes=1), DisplayStats(commands=3)) == \
        DisplayStats(commands=5, resumes=1)
