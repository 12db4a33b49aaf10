"""``teletouch bench load``: the step judgement on made-up measurements, and one real tiny
run (a relay process, a generator process, one session) whose JSON carries the figures."""

from __future__ import annotations

import json
import subprocess
from array import array
from typing import Any

import pytest

from lab.bench.load_impl import STREAMS, LoadSettings, _summarise
from shared.protocol import encode
from tests.support import scaled, teletouch_cmd


def _result(added_us: list[int], sent: int = 100, received: int = 100,
            lost: list[str] | None = None) -> dict[str, Any]:
    raw = array("q", added_us).tobytes()
    return {"sent": dict.fromkeys(STREAMS, sent), "received": dict.fromkeys(STREAMS, received),
            "added": dict.fromkeys(STREAMS, raw), "oneway": dict.fromkeys(STREAMS, raw),
            "recv_lag": array("q", [10]).tobytes(), "send_lag": array("q", [5]).tobytes(),
            "lost_connections": lost or []}


def _judge(results: list[dict[str, Any]], connected: int = 2) -> dict[str, Any]:
    return _summarise(1, connected, 1.0, results, {"sessions": {}, "counters": {}},
                      LoadSettings(limit_p99_us=5000.0), relay_cpu=0.5, gen_cpu=0.1,
                      rss=(1, 1))


def test_a_step_is_held_only_with_a_low_p99_full_delivery_and_every_station() -> None:
    fast = [500] * 99 + [4000]
    assert _judge([_result(fast)])["held"]
    slow_tail = [500] * 90 + [9000] * 10
    step = _judge([_result(slow_tail)])
    assert not step["held"] and step["sustained"]  # p50 fine, p99 over the limit
    assert not _judge([_result(fast, received=90)])["sustained"]  # 90 % delivered
    assert not _judge([_result(fast, lost=["local@s: closed"])])["sustained"]
    assert not _judge([_result(fast)], connected=1)["sustained"]  # a station never joined
    assert not _judge([_result([9000] * 100)])["sustained"]
    merged = _judge([_result([100] * 50), _result([300] * 50)])  # generators pooled
    assert merged["added_latency_us"]["p50"] == pytest.approx(200.0)


def test_the_tactile_frame_is_about_19_kb() -> None:
    from lab.bench.load_impl import tactile_frame

    assert 18_500 <= len(encode(tactile_frame())) <= 20_000  # validated: a real frame


def test_the_compact_stream_is_the_remote_codec_key_frames_then_small_deltas() -> None:
    from lab.bench.load_impl import _TactileStream
    from shared.protocol import TactileCompact, decode
    from shared.protocol.tactile_codec import TactileDecoder

    stream, decoder = _TactileStream("compact"), TactileDecoder()
    decoded = [decode(stream.message(seq)) for seq in range(1, 62)]  # validated on decode
    messages = [m for m in decoded if isinstance(m, TactileCompact)]
    assert len(messages) == 61
    keys = [m for m in messages if m.key]
    assert [m.seq for m in keys] == [1, 31, 61]  # a key frame every 30 (key_every)
    sizes = [len(stream.message(seq)) for seq in range(62, 122)]
    assert max(sizes) < 8_000 and sum(sizes) / len(sizes) < 4_000  # far below 19 kB raw
    frames = [decoder.decode(m) for m in messages]
    assert all(f is not None for f in frames)  # every delta refers to a key frame it has
    with pytest.raises(ValueError, match="tactile must be one of"):
        LoadSettings(tactile="jpeg")


@pytest.mark.slow
@pytest.mark.parametrize("tactile", ["raw", "compact"])
def test_a_tiny_real_run_reports_json(tactile: str) -> None:
    out = subprocess.run([*teletouch_cmd(), "--log-level", "WARNING", "bench", "load",
                          "--steps", "1", "--step-s", "1", "--generators", "1", "--json",
                          "--tactile", tactile],
                         capture_output=True, text=True, timeout=scaled(120.0), check=True)
    doc = json.loads(out.stdout)
    assert {"sessions_held", "sessions_sustained", "added_latency_us",
            "relay_cpu_cores"} <= set(doc)
    step = doc["steps"][0]
    assert step["stations_connected"] == 2
    assert all(step["sent"][s] > 0 for s in STREAMS)
    assert step["received"]["platform_state"] > 0 and step["received"]["tactile_frame"] > 0
    assert step["added_latency_us"]["p50"] > 0
    assert doc["relay_cpu_cores"] > 0
    frame_bytes = doc["tactile_frame_bytes"]
    assert (frame_bytes > 18_500) if tactile == "raw" else (200 < frame_bytes < 4_000)
