"""``teletouch bench relay-cpu``: the figures from made-up runs (CPU per 1,000 messages, the
paired ratio, stalled runs left out), and the load generator's stream selection."""

from __future__ import annotations

from array import array
from typing import Any

import pytest

from lab.bench.load_impl import STREAMS, LoadSettings, _summarise
from lab.bench.relay_cpu_impl import CURRENT, CpuSettings, cpu_ms_per_1k, markdown, summarise


def test_cpu_per_thousand_messages() -> None:
    # 0.2 cores for 4 s = 0.8 CPU s over 2,000 messages: 0.4 ms each, 400 ms per 1,000
    assert cpu_ms_per_1k(0.2, 2000, 4.0) == pytest.approx(400.0)
    assert cpu_ms_per_1k(0.2, 0, 4.0) is None


def _run(rnd: int, relay: str, ms: float, delivered: float = 1.0) -> dict[str, Any]:
    return {"round": rnd, "relay": relay, "mix": "all", "cpu_ms_per_1k": ms,
            "cores_per_session": ms / 1000, "forwarded_per_s": 1890.0, "relay_cpu_cores": 0.4,
            "added_p50_us": 500.0, "added_p99_us": 2000.0, "delivered_min": delivered,
            "lost_connections": 0, "drops": {}, "loadavg": 5.0, "gen_lag_p99_us": 100.0,
            "system_share": 0.1}


def test_the_ratio_pairs_rounds_and_leaves_stalled_runs_out() -> None:
    settings = CpuSettings(baseline_rev="old", mixes=("all",), rounds=3)
    runs = [_run(0, "old", 200.0), _run(0, CURRENT, 150.0),
            _run(1, "old", 100.0), _run(1, CURRENT, 90.0),
            _run(2, "old", 300.0), _run(2, CURRENT, 30.0, delivered=0.4)]  # stalled
    (row,) = summarise(runs, settings)
    assert row["ratio"]["rounds"] == 2
    assert row["ratio"]["median"] == pytest.approx((0.75 + 0.9) / 2)
    assert (row["ratio"]["min"], row["ratio"]["max"]) == pytest.approx((0.75, 0.9))
    assert row["old"]["cpu_ms_per_1k"] == pytest.approx(200.0)  # the median of all 3 valid
    assert row[CURRENT]["cpu_ms_per_1k"] == pytest.approx(120.0)  # the stalled one left out
    text = markdown({"settings": {**settings.__dict__}, "summary": [row], "runs": runs,
                     "machine": {"nproc": 2, "python": "3", "loadavg_start": (1.0,),
                                 "loadavg_end": (2.0,), "niceness": 0, "autogroup": ""},
                     "baseline_commit": "abc", "current": "def"}, "cmd")
    assert "| all | 200.000 |" in text and "| NO |" in text


def test_a_generator_sends_only_the_chosen_streams() -> None:
    raw = array("q", [100] * 10).tobytes()
    result = {"sent": {"platform_state": 10, "tactile_frame": 0, "arm_state": 0},
              "received": {"platform_state": 10, "tactile_frame": 0, "arm_state": 0},
              "added": dict.fromkeys(STREAMS, raw), "oneway": dict.fromkeys(STREAMS, raw),
              "recv_lag": raw, "send_lag": raw, "lost_connections": []}
    one = _summarise(1, 2, 1.0, [result], {}, LoadSettings(streams=("platform_state",)),
                     relay_cpu=0.1, gen_cpu=0.1, rss=(1, 1))
    assert one["held"] and one["delivered"] == {"platform_state": 1.0}
    # the same counts judged as the full mix: streams that sent nothing count as undelivered
    assert not _summarise(1, 2, 1.0, [result], {}, LoadSettings(), relay_cpu=0.1,
                          gen_cpu=0.1, rss=(1, 1))["held"]
