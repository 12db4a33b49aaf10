"""The motion-to-touch floor of a group of ``bench cpu`` runs (``benchmarks/m2t_tail_table.py``,
through ``bench_motion_to_touch.floor_ms``): the link profile's nominal round trip plus the
medians of the working stages' and the design's waits' p50."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from benchmarks.bench_motion_to_touch import DESIGN_WAITS, SENSOR_STAGES, WORK_STAGES
from benchmarks.m2t_tail_table import floor_ms, table
from lab.linkemu import get_profile


def _run(link: str | None, p50: dict[str, float]) -> dict[str, Any]:
    return {"settings": {"link": link},
            "latency_ms": {stage: {"p50": v, "p99": 10 * v} for stage, v in p50.items()}}


def test_the_floor_adds_the_round_trip_and_the_medians_of_the_stages() -> None:
    stages = (*WORK_STAGES, *DESIGN_WAITS, *SENSOR_STAGES)
    # three runs: stage i's p50 is i+1, 2(i+1), 10(i+1) ms -> median 2(i+1)
    runs = [_run("city-1000km", {s: k * (i + 1) for i, s in enumerate(stages)})
            for k in (1.0, 2.0, 10.0)]
    runs[0]["latency_ms"]["arm_and_sensor"] = {"p50": 1000.0}  # a wait: not in the floor
    want = get_profile("city-1000km").round_trip_ms + sum(2.0 * (i + 1)
                                                          for i in range(len(stages)))
    assert floor_ms(runs) == pytest.approx(want)
    assert get_profile("city-1000km").round_trip_ms == pytest.approx(20.0)


def test_a_stage_counts_over_the_runs_that_report_it_and_none_without_it() -> None:
    stages = (*WORK_STAGES, *DESIGN_WAITS)
    assert floor_ms([_run(None, dict.fromkeys(stages, 1.0))]) is None  # no link emulator
    partial = dict.fromkeys(stages, 1.0)
    del partial["render"]
    full = dict.fromkeys(stages, 1.0) | {"render": 5.0}
    rtt = get_profile("lan").round_trip_ms
    # a run without the stage (an older format, a failed run) does not pull it to zero
    assert floor_ms([_run("lan", full), _run("lan", partial)]) == pytest.approx(
        rtt + len(stages) - 1 + 5.0)
    assert floor_ms([_run("lan", partial), _run("lan", partial)]) is None
    failed: dict[str, Any] = {"settings": {"link": "lan"}}  # no latency table at all
    assert floor_ms([_run("lan", full), failed]) == pytest.approx(rtt + len(stages) - 1 + 5.0)


def test_the_sensor_delivery_counts_where_reported_and_adds_nothing_in_older_ledgers() -> None:
    # before 2026-12-06 a camera's delivery was part of reconstruction_and_stiffness: a run
    # without the stage is not a run with a missing stage
    older = dict.fromkeys((*WORK_STAGES, *DESIGN_WAITS), 1.0)
    rtt = get_profile("lan").round_trip_ms
    base = rtt + len(older)
    assert floor_ms([_run("lan", older)]) == pytest.approx(base)
    newer = older | {"sensor_delivery": 30.0}
    assert SENSOR_STAGES == ("sensor_delivery",)
    assert floor_ms([_run("lan", newer)]) == pytest.approx(base + 30.0)
    assert floor_ms([_run("lan", newer), _run("lan", older)]) == pytest.approx(base + 30.0)


def test_the_tail_table_takes_a_group_mixing_older_and_newer_ledgers(tmp_path: Path) -> None:
    # one run from before sensor_delivery existed, one after: every stage is listed, each
    # over the runs that report it
    def run(n: int, stages: dict[str, float]) -> dict[str, Any]:
        tail = {"quantile": 0.95, "of": 100,
                "end_to_end": {"p50": 20.0, "tail_mean": 30.0},
                "stages": {s: {"p50": v, "tail_mean": v + 1.0, "excess": 1.0, "share": 0.1}
                           for s, v in stages.items()}}
        return {"label": f"cam-lan-{n}", "settings": {"link": "lan"}, "load_start": [0.5],
                "latency_ms": {"end_to_end": {"p50": 20.0, "p99": 40.0},
                               **{s: {"p50": v} for s, v in stages.items()}},
                "latency_tail_ms": tail}

    older = dict.fromkeys((*WORK_STAGES, *DESIGN_WAITS), 1.0)
    newer = older | {"sensor_delivery": 30.0}
    (tmp_path / "cpu-cam-lan-1.json").write_text(json.dumps(run(1, newer)))
    (tmp_path / "cpu-cam-lan-2.json").write_text(json.dumps(run(2, older)))
    text = table(tmp_path)
    assert "| sensor_delivery | 30.00 |" in text  # the one run that has it
    assert "| render | 1.00 (1.00-1.00) |" in text  # both runs
    assert "uplink_sampling, sensor_delivery); p99" in text  # counted in the floor
