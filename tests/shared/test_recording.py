"""The MCAP recorder and reader: round trip, schemas, cut files, foreign files, back-pressure."""

from __future__ import annotations

import itertools
import json
import subprocess
import threading
import time
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.writer import Writer

from lab.cli import main
from shared.errors import ConfigError
from shared.protocol import (
    ArmState,
    Bye,
    Error,
    Hop,
    Message,
    PlatformState,
    Stats,
    TactileFrame,
)
from shared.protocol.codec import encode
from shared.recording import McapRecorder, RecordingFormatError, read_mcap
from shared.recording.schemas import DERIVED_SCHEMAS
from shared.recording.writer import hop_stages_ms
from tests.support import scaled, teletouch_cmd, wait_until


def _messages(n: int = 50) -> list[tuple[str, Message, int]]:
    rng = np.random.default_rng(1)
    out: list[tuple[str, Message, int]] = []
    t = 1_700_000_000_000_000
    out.append(("rx", Stats(metrics={"clock_offset_us": {"local": 0, "remote": 250}}), t))
    for i in range(n):
        t += 1000
        out.append(("tx", PlatformState(seq=i + 1, ts_us=t, hops=(Hop("local", "capture", t),),
                                        position_mm=(float(i), 2.0, 3.0)), t))
        height = rng.random((6, 5)).astype(np.float32)
        out.append(("rx", TactileFrame(
            seq=i + 1, ts_us=t - 500,
            hops=(Hop("remote", "capture", t - 700), Hop("relay", "relay_in", t - 400),
                  Hop("relay", "relay_out", t - 390), Hop("local", "station_rx", t - 100)),
            center_mm=(1.0, 2.0), pitch_mm=0.5, layers={"height_mm": height},
            contact=bool(i % 2), force_n=1.5, indentation_mm=0.2), t + 10))
        out.append(("rx", ArmState(seq=i + 1, ts_us=t, position_mm=(1.0, 2.0, 3.0),
                                   force_n=0.5), t + 20))
    out.append(("rx", Error(code="bad", message="m"), t + 30))
    out.append(("tx", Bye(reason="done"), t + 40))
    return out


def _write(path: Path, items: list[tuple[str, Message, int]], **kw: object) -> McapRecorder:
    rec = McapRecorder(path, "local", meta={"session": "s", "workspace": {"a": 1}}, **kw)  # type: ignore[arg-type]
    for direction, msg, t in items:
        assert rec.wire(direction, msg, t)
    return rec


def test_round_trip_message_by_message_with_schemas(tmp_path: Path) -> None:
    items = _messages()
    rec = _write(tmp_path / "r.mcap", items)
    rec.derived("pins", items[-1][2], lambda: {
        "commanded_mm": [0.5] * 16, "stiffness_k": [1.0] * 16, "friction": [0.0] * 16,
        "measured_mm": None, "safe_reason": "stale_scene"})
    counts = rec.close({"exit": "ok"})
    assert counts["dropped_queue_full"] == 0 and counts["write_errors"] == 0
    out = read_mcap(tmp_path / "r.mcap")
    assert out.complete and out.stop_reason is None and out.station == "local"
    assert out.meta == {"session": "s", "workspace": {"a": 1}}
    assert out.end["meta"] == {"exit": "ok"} and out.end["counts"]["messages_written"] == \
        len(out.messages)
    wire = list(out.wire_messages())
    assert len(wire) == len(items)
    for (m, msg), (direction, orig, t) in zip(wire, items, strict=True):
        assert m.topic == f"/local/{direction}/{orig.TYPE}" and m.t_us == t
        assert encode(msg, validate=False) == encode(orig, validate=False)
    # every derived message validates against the JSON Schema stored in the file
    derived = [m for m in out.messages if m.encoding == "json"]
    assert {m.topic for m in derived} == {"/local/trajectory", "/local/tactile",
                                          "/local/latency", "/local/pins"}
    by_title = {s["title"]: s for s in DERIVED_SCHEMAS.values()}
    assert set(out.schemas) == {"teletouch.Trajectory", "teletouch.Tactile", "teletouch.Latency",
                                "teletouch.Pins"} and set(out.schemas) <= set(by_title)
    for m in derived:
        schema = DERIVED_SCHEMAS[m.topic.split("/")[2]]
        assert out.schemas[schema["title"]] == schema
        jsonschema.validate(m.json(), schema)
    lat = next(out.on("/local/latency")).json()
    # remote clock 250 us ahead of the relay: capture at t-700 is t-950 on the relay clock
    assert lat["stages_ms"]["capture_to_relay_in"] == pytest.approx(0.55)
    assert lat["end_to_end_ms"] == pytest.approx(0.85)


hops_strategy = st.lists(
    st.tuples(st.sampled_from(["local", "relay", "remote"]),
              st.sampled_from(["capture", "relay_in", "relay_out", "station_rx"]),
              st.integers(0, 10**12)), min_size=2, max_size=12)


@settings(max_examples=200, deadline=None)
@given(hops_strategy, st.integers(-10**6, 10**6), st.integers(-10**6, 10**6))
def test_hop_stages_telescope_to_end_to_end(raw: list[tuple[str, str, int]], off_local: int,
                                            off_remote: int) -> None:
    hops = [Hop(*h) for h in raw]
    offsets = {"local": off_local, "remote": off_remote, "relay": 0}
    stages, total = hop_stages_ms(hops, offsets)
    assert len(stages) == len(hops) - 1
    # independent reference: every stamp on the relay clock, first to last
    on_relay = [h.t_us - offsets[h.clock] for h in hops]
    assert total is not None
    assert total == pytest.approx((on_relay[-1] - on_relay[0]) / 1e3, abs=1e-6)
    assert sum(v for v in stages.values() if v is not None) == pytest.approx(total, abs=1e-6)
    # without the offsets, only same-clock stages are known
    unknown, _ = hop_stages_ms(hops, {})
    for (a, b), v in zip(itertools.pairwise(hops), unknown.values(), strict=True):
        assert (v is None) == (a.clock != b.clock)


@pytest.fixture(scope="module")
def full_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, list[bytes]]:
    path = tmp_path_factory.mktemp("cut") / "full.mcap"
    # many small chunks, so cuts fall between and inside chunks
    _write(path, _messages(200), chunk_bytes=4096).close()
    data = path.read_bytes()
    return data, [m.data for m in read_mcap(path).messages]


@settings(max_examples=60, deadline=None)
@given(st.floats(0.0, 1.0))
def test_a_cut_file_reads_a_prefix_or_fails_clearly(
        full_file: tuple[bytes, list[bytes]], tmp_path_factory: pytest.TempPathFactory,
        fraction: float) -> None:
    data, full = full_file
    cut = int(len(data) * fraction)
    path = tmp_path_factory.mktemp("c") / "cut.mcap"
    path.write_bytes(data[:cut])
    try:
        out = read_mcap(path)
    except RecordingFormatError as err:
        assert cut < 200, f"a cut at {cut} of {len(data)} bytes lost everything: {err}"
        assert "truncated" in str(err) or "not an MCAP file" in str(err) or "cut" in str(err)
        return
    got = [m.data for m in out.messages]
    assert got == full[:len(got)]  # what is read is exactly the start of the recording
    assert out.complete == (cut == len(data))
    if cut > len(data) * 0.6:
        assert len(got) > len(full) // 3  # chunks are small: most of it survives


def test_foreign_and_non_mcap_files_get_clear_errors(tmp_path: Path) -> None:
    foreign = tmp_path / "ros.mcap"
    with open(foreign, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="someone else")
        cid = w.register_channel("/chatter", "json", 0)
        w.add_message(cid, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    with pytest.raises(RecordingFormatError, match=r"not a Tele-Touch recording.*'ros2'"):
        read_mcap(foreign)
    bare = tmp_path / "bare.mcap"
    with open(bare, "wb") as fh:
        w = Writer(fh)
        w.start(profile="teletouch", library="imitation")
        w.finish()
    with pytest.raises(RecordingFormatError, match="without the Tele-Touch start metadata"):
        read_mcap(bare)
    for name, content in (("text.mcap", b"hello, this is not MCAP\n" * 10),
                          ("empty.mcap", b""), ("npz.mcap", b"PK\x03\x04" + bytes(100))):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(RecordingFormatError, match="not an MCAP file"):
            read_mcap(tmp_path / name)
    with pytest.raises(RecordingFormatError, match="cannot open"):
        read_mcap(tmp_path / "missing.mcap")


def test_the_cli_names_the_problem_without_a_traceback(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
        ) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap")
    good = tmp_path / "good.mcap"
    _write(good, _messages(3)).close()
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(good.read_bytes()[:20])
    # as a user runs it: a real process
    done = subprocess.run([*teletouch_cmd(), "replay", "--summary", str(junk)],
                          capture_output=True, text=True, timeout=scaled(60.0), check=False)
    assert done.returncode == 1
    assert "RecordingFormatError" in done.stderr and "not an MCAP file" in done.stderr
    assert "Traceback" not in done.stderr
    # every command that reads a recording, in-process (the same entry point)
    for path, what in ((junk, "not an MCAP file"), (truncated, "truncated")):
        for sub in (["replay", "--summary"], ["replay", "--display", "none"], ["report"]):
            caplog.clear()
            assert main([*sub, str(path)]) == 1
            assert what in caplog.text and "Traceback" not in caplog.text
    assert main(["replay", "--summary", str(good)]) == 0
    out = capsys.readouterr().out
    assert "local station, 21 messages" in out and "complete" in out
    assert "/local/rx/tactile_frame" in out and "capture_to_relay_in" in out


def test_a_full_queue_drops_and_counts_without_blocking(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path / "q.mcap", "local", queue_size=4)
    gate = threading.Event()
    # hold the writer thread inside a derived payload so the queue fills up
    rec.derived("frame_accepted", 1, lambda: (gate.wait(scaled(10.0)), {"seq": 0, "rx_us": 1})[1])
    items = _messages(100)
    t0 = time.perf_counter()
    accepted = sum(rec.wire(d, m, t) for d, m, t in items)
    elapsed = time.perf_counter() - t0
    gate.set()
    counts = rec.close()
    assert accepted <= 5 and rec.dropped == len(items) - accepted > 0
    assert elapsed < scaled(1.0)  # 300 puts against a stalled writer did not wait for it
    out = read_mcap(tmp_path / "q.mcap")
    assert out.complete and out.end["counts"]["dropped_queue_full"] == counts[
        "dropped_queue_full"]
    assert len(list(out.wire_messages())) == accepted


def test_a_steady_stream_does_not_hold_off_the_periodic_flush(tmp_path: Path) -> None:
    """Producers that never let the queue run empty (a thread appending as fast as it can,
    faster than the writer encodes) must not starve the periodic flush: a station killed
    mid-session keeps what was recorded up to the last flush."""
    path = tmp_path / "s.mcap"
    # chunks far larger than the test writes: only the periodic flush puts one in the file
    rec = McapRecorder(path, "local", flush_interval_s=0.05, chunk_bytes=1 << 30)
    size_at_start = path.stat().st_size
    stop = threading.Event()
    items = _messages(50)

    def produce() -> None:
        while not stop.is_set():
            for direction, msg, t_us in items:
                rec.wire(direction, msg, t_us)

    producer = threading.Thread(target=produce)
    producer.start()
    try:
        wait_until(lambda: path.stat().st_size > size_at_start, 10.0,
                   "a chunk in the file while producers keep the writer busy")
        assert rec.sync(scaled(10.0))  # and a sync gets through the stream
    finally:
        stop.set()
        producer.join()
    counts = rec.close()
    out = read_mcap(path)
    assert out.complete and counts["messages_written"] == len(out.messages) > 0
    assert counts["dropped_queue_full"] == rec.dropped  # the overflow, counted


def test_bad_settings_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"name it \*\.mcap"):
        McapRecorder(tmp_path / "old.npz", "local")
    with pytest.raises(ConfigError, match="cannot write"):
        McapRecorder(tmp_path / "missing-dir" / "r.mcap", "local")
    with pytest.raises(ConfigError, match="must be > 0"):
        McapRecorder(tmp_path / "r.mcap", "local", queue_size=0)
    for bad in (0.0, -5.0, float("nan"), 5000.0):
        with pytest.raises(ConfigError, match="image_rate_hz"):
            McapRecorder(tmp_path / "r.mcap", "local", image_rate_hz=bad)
    rec = McapRecorder(tmp_path / "r.mcap", "local")
    with pytest.raises(KeyError, match="unknown derived channel"):
        rec.derived("nope", 1, {})
    rec.close()
    assert rec.close() == rec.counts()  # idempotent
    assert not rec.wire("tx", Bye(reason="late"), 1)  # after close: refused, not queued


def test_a_payload_that_fails_is_counted_and_the_recording_goes_on(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path / "e.mcap", "local")

    def bad() -> dict[str, object]:
        raise ValueError("broken payload")

    rec.derived("pins", 1, bad)
    rec.wire("tx", Bye(reason="x"), 2)
    counts = rec.close()
    assert counts["write_errors"] == 1
    out = read_mcap(tmp_path / "e.mcap")
    assert [m.topic for m in out.messages] == ["/local/tx/bye"]
    assert json.loads(json.dumps(out.end))["counts"]["write_errors"] == 1
