"""Replay pacing and subscribers, and the summary's figures against numpy."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lab.replay import Replayer, ReplayEvent, format_summary, summarize
from shared.errors import ConfigError
from shared.protocol import ArmState, Hop, PlatformState
from shared.recording import McapRecorder, RecordedMessage, read_mcap

T0 = 1_700_000_000_000_000


def _recording(path: Path, n: int = 50, period_us: int = 20_000) -> list[int]:
    """Local tx platform states and rx arm states, one each per period; returns the delays."""
    rec = McapRecorder(path, "local")
    rng = np.random.default_rng(3)
    delays = [int(d) for d in rng.integers(100, 5000, n)]
    for i in range(n):
        t = T0 + i * period_us
        rec.wire("tx", PlatformState(seq=i + 1, ts_us=t, hops=(Hop("local", "capture", t),),
                                     position_mm=(float(i), 1.0, 2.0)), t)
        # two stamps on the remote clock delays[i] apart: a stage known without offsets
        rec.wire("rx", ArmState(seq=i + 1, ts_us=t, hops=(
            Hop("remote", "capture", t), Hop("remote", "sent", t + delays[i])),
            position_mm=(0.0, 0.0, 0.0)), t + delays[i])
    rec.close()
    return delays


def test_summary_rates_counts_and_latency_against_numpy(tmp_path: Path) -> None:
    delays = _recording(tmp_path / "r.mcap")
    s = summarize(read_mcap(tmp_path / "r.mcap"))
    assert s["complete"] and s["station"] == "local"
    assert s["streams"]["/local/tx/platform_state"]["count"] == 50
    assert s["streams"]["/local/tx/platform_state"]["rate_hz"] == pytest.approx(50.0)
    stage = s["latency_ms"]["/local/latency arm_state"]["capture_to_sent"]
    ms = np.asarray(delays) / 1e3
    assert stage["count"] == 50
    assert stage["p50"] == pytest.approx(float(np.percentile(ms, 50)))
    assert stage["p99"] == pytest.approx(float(np.percentile(ms, 99)))
    text = format_summary(s)
    assert "capture_to_sent" in text and "/local/trajectory" in text


def test_replay_paces_publishes_in_order_and_survives_a_bad_subscriber(tmp_path: Path) -> None:
    _recording(tmp_path / "r.mcap", n=50, period_us=20_000)  # ~1 s recorded
    rec = read_mcap(tmp_path / "r.mcap")
    events: list[ReplayEvent] = []

    def broken(ev: ReplayEvent) -> None:
        raise RuntimeError("subscriber bug")

    replayer = Replayer(rec, speed=5.0, display="none")
    replayer.subscribe(broken)
    replayer.subscribe(events.append)
    result = replayer.run()
    assert result.published == len(events) == len(rec.messages)
    assert result.subscriber_errors == len(rec.messages)
    assert [e.t_us for e in events] == sorted(m.t_us for m in rec.messages)
    # never faster than recorded / speed (a lower bound: a loaded machine may be slower)
    assert result.duration_s >= result.recorded_duration_s / 5.0 - 0.005
    assert isinstance(events[0].message, PlatformState) and events[0].data is None
    assert any(e.topic == "/local/trajectory" and e.data == {"seq": 1, "x_mm": 0.0,
                                                              "y_mm": 1.0, "z_mm": 2.0}
               for e in events)
    with pytest.raises(ConfigError, match="speed"):
        Replayer(rec, speed=0.0)


def test_a_payload_that_does_not_decode_is_skipped_and_counted(tmp_path: Path) -> None:
    """A wire message off the protocol and a derived message that is not a JSON object: the
    replay ended at the first (RecordingFormatError out of run) and the summary at the
    second; now both are skipped and counted, and everything else is replayed."""
    _recording(tmp_path / "r.mcap", n=20, period_us=5_000)
    rec = read_mcap(tmp_path / "r.mcap")
    good = len(rec.messages)
    rec.messages.insert(3, RecordedMessage("/local/rx/arm_state", T0 + 1, "msgpack", b"\xc1"))
    rec.messages.insert(7, RecordedMessage("/local/latency", T0 + 2, "json", b"[1, 2]"))
    deep = b"[" * 100_000 + b"]" * 100_000  # nested past the parser (found by review)
    rec.messages.insert(9, RecordedMessage("/local/latency", T0 + 3, "json", deep))
    events: list[ReplayEvent] = []
    replayer = Replayer(rec, speed=20.0, display="none")
    replayer.subscribe(events.append)
    result = replayer.run()
    assert result.undecodable == 3 and result.published == len(events) == good
    summary = summarize(rec)
    assert summary["latency_malformed_values"] == 2
    assert "or a message not a JSON object) left out" in format_summary(summary)
