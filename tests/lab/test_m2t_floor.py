"""The motion-to-touch floor of a group of ``bench cpu`` runs (``benchmarks/m2t_tail_table.py``):
the link profile's nominal round trip plus the medians of the working stages' and the
design's waits' p50."""

from __future__ import annotations

from typing import Any

import pytest

from benchmarks.bench_motion_to_touch import DESIGN_WAITS, WORK_STAGES
from benchmarks.m2t_tail_table import floor_ms
from lab.linkemu import get_profile


def _run(link: str | None, p50: dict[str, float]) -> dict[str, Any]:
    return {"settings": {"link": link},
            "latency_ms": {stage: {"p50": v, "p99": 10 * v} for stage, v in p50.items()}}


def test_the_floor_adds_the_round_trip_and_the_medians_of_the_stages() -> None:
    stages = (*WORK_STAGES, *DESIGN_WAITS)
    # three runs: stage i's p50 is i+1, 2(i+1), 10(i+1) ms -> median 2(i+1)
    runs = [_run("city-1000km", {s: k * (i + 1) for i, s in enumerate(stages)})
            for k in (1.0, 2.0, 10.0)]
    runs[0]["latency_ms"]["arm_and_sensor"] = {"p50": 1000.0}  # a wait: not in the floor
    want = get_profile("city-1000km").round_trip_ms + sum(2.0 * (i + 1)
                                                          for i in range(len(stages)))
    assert floor_ms(runs) == pytest.approx(want)
    assert get_profile("city-1000km").round_trip_ms == pytest.approx(20.0)


def test_no_floor_without_a_link_or_with_a_stage_missing() -> None:
    stages = (*WORK_STAGES, *DESIGN_WAITS)
    assert floor_ms([_run(None, dict.fromkeys(stages, 1.0))]) is None
    partial = dict.fromkeys(stages, 1.0)
    del partial["render"]
    assert floor_ms([_run("lan", dict.fromkeys(stages, 1.0)), _run("lan", partial)]) is None
