"""Fixes of the recording / replay audit: each test fails without its fix.

* the pins' safe state is recorded (``/local/pins`` with null commanded values), and the
  replay view shows it as such; a pins sample older than 2.5 periods is shown as unknown
  (old recordings have no sample while safe); the report draws no line across such a gap;
* a pins sample records the measured positions as unknown (null) when the board's latest
  feedback is stale (a silent board's last positions were recorded as current);
* a recording's latency stage names and values are checked before the replay view passes
  them on (no markup, no string values that stop every snapshot);
* a moment of full disk: messages count as written only once flushed, the others as lost;
  a torn write is cut back off; ``sync`` answers at once; ``--summary`` prints it all;
* ``/local/findings`` is stamped on the session's clock;
* the remote station writes its summary when its recording cannot be finished;
* a corrupt chunk is skipped, the chunks after it read; a malformed ``--truth`` is refused.
"""

from __future__ import annotations

import asyncio
import errno
import json
import threading
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import jsonschema
import numpy as np
import pytest

import shared.recording.writer as writer_module
from lab.replay import Replayer, format_summary, summarize
from lab.replay_view import ReplayViewSource
from local_site.recording import PinsSampler, SessionRecorder
from local_site.render import PinCommand
from shared.errors import ConfigError, InputDataError
from shared.protocol import Bye, Hop, PlatformState
from shared.recording import McapRecorder, read_mcap
from shared.recording.schemas import DERIVED_SCHEMAS
from shared.timebase import now_us
from tests.recordings import write_local_recording

T0 = 1_790_000_000_000_000
PERIOD_US = 20_000  # 50 Hz pins


def _command(h: float = 1.0) -> PinCommand:
    return PinCommand(np.full((4, 4), h), np.full((4, 4), 0.8), np.zeros((4, 4)))


def _platform(rec: McapRecorder | SessionRecorder, seq: int, t: int) -> None:
    msg = PlatformState(seq=seq, ts_us=t, hops=(Hop("local", "capture", t),),
                        position_mm=(30.0, 30.0, 39.0))
    if isinstance(rec, SessionRecorder):
        rec.tap("tx", msg, t)
    else:
        rec.wire("tx", msg, t)


def _seq(msg: Any) -> int:
    assert isinstance(msg, PlatformState)
    return msg.seq


def _view_at(path: Path, position_us: int) -> dict[str, Any]:
    """The replay view's snapshot with the replay stopped at ``position_us``."""
    replayer = Replayer(read_mcap(path), display="none")
    source = ReplayViewSource(replayer, None)
    for m in replayer._messages:
        if m.t_us > position_us:
            break
        source.on_event(replayer.event(m))
    replayer.clock._anchor_us = float(position_us)  # a paused clock standing there
    replayer.clock._paused = True
    return source.live()


# ---------------------------------------------------------------- 1: the pins' safe state


def test_the_sampler_records_the_safe_state_at_once_and_at_its_rate() -> None:
    class Board:
        is_connected = False

    sampler = PinsSampler(1e-3)  # one sample per 1,000 s unless the state changes
    assert sampler.offer(None, Board(), None) is None  # nothing on the pins, not safe
    first = sampler.offer("command", Board(), None)
    assert first is not None and first[1:] == ("command", None, None)
    assert sampler.offer("command 2", Board(), None) is None  # a new command: no change
    safe = sampler.offer(None, Board(), "no_frames")  # the safe state: recorded at once
    assert safe is not None and safe[1:] == (None, None, "no_frames")
    assert sampler.offer(None, Board(), "no_frames") is None
    other = sampler.offer(None, Board(), "display_lost")  # another reason is a change too
    assert other is not None and other[3] == "display_lost"
    back = sampler.offer("command", Board(), None)
    assert back is not None and back[1] == "command"
    steady = PinsSampler(1e6)  # due at every offer: the safe state keeps being sampled
    assert steady.offer(None, Board(), "stale_scene") is not None
    assert steady.offer(None, Board(), "stale_scene") is not None


def test_the_sampler_records_stale_feedback_as_unknown_positions(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The board's last feedback was recorded as the pins' positions however old it was (a
    silent board: its positions of a second ago recorded as now)."""
    monkeypatch.setattr("local_site.recording.now_us", lambda: T0)  # a clock standing still

    class Board:
        is_connected = True

        def __init__(self, age_us: int) -> None:
            self.feedback = SimpleNamespace(t_us=T0 - age_us, position_mm=np.full(16, 3.0))

        def latest_feedback(self) -> SimpleNamespace:
            return self.feedback

    def measured(sampler: PinsSampler, age_us: int) -> Any:
        sample = sampler.offer("command", Board(age_us), None)
        assert sample is not None and sample[:2] == (T0, "command")
        return sample[2]

    sampler = PinsSampler(1e6)  # due at every offer
    np.testing.assert_array_equal(measured(sampler, 0), 3.0)
    assert measured(sampler, 1_000_000) is None  # silent for 1 s: unknown, not 3 mm
    # the limit is the sampler's: 20 ms by default (ten periods of the board's 500 Hz)
    assert measured(sampler, 20_000) is not None
    assert measured(sampler, 20_001) is None
    assert measured(PinsSampler(1e6, measured_max_age_s=0.001), 5_000) is None
    with pytest.raises(ConfigError, match="measured_max_age_s"):
        PinsSampler(50.0, measured_max_age_s=0.0)


def test_a_safe_period_is_recorded_and_replayed_as_the_safe_state(tmp_path: Path) -> None:
    path = tmp_path / "safe.mcap"
    rec = SessionRecorder(path, {"session": "safe"})
    for i in range(150):  # 1 s rendering, 1 s safe, 1 s rendering, pins at 50 Hz
        t = T0 + i * PERIOD_US
        _platform(rec, i + 1, t)
        if 50 <= i < 100:
            rec.record_pins(t, None, np.full(16, 0.1), "stale_scene")
        else:
            rec.record_pins(t, _command(1.0 + i / 100), np.full(16, 0.9), None)
    counts = rec.mcap.close()
    assert counts["write_errors"] == 0  # the null command was written, not refused
    pins = [m.json() for m in read_mcap(path).on("/local/pins")]
    assert len(pins) == 150
    for doc in pins:  # every sample, the safe ones too, fits the stored schema
        jsonschema.validate(doc, DERIVED_SCHEMAS["pins"])
    assert pins[60]["commanded_mm"] is None and pins[60]["safe_reason"] == "stale_scene"
    assert read_mcap(path).meta["pins_rate_hz"] == 50.0
    # the replay, in the middle of the safe period: the safe state, no command
    live = _view_at(path, T0 + 70 * PERIOD_US + 5_000)
    assert live["safe"] == {"reason": "stale_scene", "known": True}
    assert live["pins"]["commanded_mm"] is None
    assert live["pins"]["measured_mm"] == [0.1] * 16


def test_pins_older_than_two_and_a_half_periods_are_unknown_not_rendering(
        tmp_path: Path) -> None:
    # a recording made before the fix: no pins sample while the pins were safe
    path = tmp_path / "old.mcap"
    rec = McapRecorder(path, "local", meta={"session": "old"})
    for i in range(150):
        t = T0 + i * PERIOD_US
        _platform(rec, i + 1, t)
        if i < 50 or i >= 125:  # 1.5 s without a sample
            rec.derived("pins", t, {"commanded_mm": [1.5] * 16, "stiffness_k": [0.8] * 16,
                                    "friction": [0.0] * 16, "measured_mm": [1.4] * 16,
                                    "safe_reason": None})
    rec.close()
    last = T0 + 49 * PERIOD_US
    fresh = _view_at(path, last + 40_000)  # 2 periods: still the last sample
    assert fresh["pins"]["commanded_mm"] == [1.5] * 16
    assert fresh["safe"] == {"reason": None, "known": True}
    gap = _view_at(path, last + 1_000_000)  # 1 s into the gap: nothing is known
    assert gap["pins"] is None
    assert gap["safe"] == {"reason": None, "known": False}


def test_the_reports_pins_figure_draws_the_safe_state_and_no_line_across_gaps(
        tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from lab.html_report import _pins_figure

    path = tmp_path / "r.mcap"
    rec = SessionRecorder(path, {"session": "r"})
    for i in range(60):
        t = T0 + i * PERIOD_US + (2_000_000 if i >= 40 else 0)  # a 2 s gap before #40
        rec.record_pins(t, None if 20 <= i < 30 else _command(), None,
                        "stale_frame" if 20 <= i < 30 else None)
    rec.close()
    html_text = _pins_figure(read_mcap(path))
    assert "<img" in html_text and "1 gaps with no pin sample" in html_text


def test_the_display_loop_records_its_safe_state(tmp_path: Path) -> None:
    # the station's own loop: frames, none for 0.8 s (it goes to its safe state), frames
    from local_site.agent.display_loop import DisplayLoop, FrameSlot, SameClockLink
    from local_site.devices import open_display
    from local_site.platform.base import PlatformSample
    from local_site.render import Renderer
    from local_site.scenes import TactileFrameScene
    from shared.protocol import TactileFrame

    path = tmp_path / "loop.mcap"
    rec = SessionRecorder(path, {"session": "loop"})
    scene = TactileFrameScene()
    slot = FrameSlot(prepare=scene.prepare)
    display = open_display("sim", connect=False)
    pos = [PlatformSample(position_mm=(30.0, 30.0, 39.0), velocity_mm_s=(0.0, 0.0, 0.0),
                          t_us=now_us(), seq=1, board_t_us=0)]
    loop = DisplayLoop(display, Renderer(), scene, positions=lambda: pos[0],
                       platform_ok=lambda: True, frames=slot, link=SameClockLink(),
                       recorder=rec, stale_timeout_s=0.1)
    display.connect()
    stop = threading.Event()
    thread = threading.Thread(target=loop.run_in_thread, args=(stop,), daemon=True)
    thread.start()
    seq = 0

    def feed(seconds: float) -> None:
        nonlocal seq
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            seq += 1
            t = now_us()
            pos[0] = PlatformSample(position_mm=(30.0, 30.0, 39.0),
                                    velocity_mm_s=(0.0, 0.0, 0.0), t_us=t, seq=seq,
                                    board_t_us=0)
            slot.put(TactileFrame(seq=seq, ts_us=t, hops=(Hop("local", "capture", t),),
                                  center_mm=(30.0, 30.0), pitch_mm=0.5,
                                  layers={"height_mm": np.full((16, 16), 0.6, np.float32)},
                                  contact=True, force_n=1.0, indentation_mm=0.5), t)
            time.sleep(1 / 30)

    try:
        feed(0.6)
        gap_start = now_us()
        time.sleep(0.8)
        gap_end = now_us()
        feed(0.4)
    finally:
        stop.set()
        thread.join(10)
        display.disconnect()
    rec.close()
    assert sum(loop.counters.safe_entries.values()) >= 1
    pins = [(m.t_us, m.json()) for m in read_mcap(path).on("/local/pins")]
    in_gap = [doc for t, doc in pins if gap_start + 300_000 < t < gap_end]
    assert in_gap, "no pins sample while the loop was in its safe state"
    assert all(d["safe_reason"] is not None and d["commanded_mm"] is None for d in in_gap)
    assert any(d["safe_reason"] is None and d["commanded_mm"] is not None for _, d in pins)


# ---------------------------------------------------------------- 2: untrusted latency


def test_the_replay_view_drops_bad_stage_names_and_values(tmp_path: Path) -> None:
    path = tmp_path / "lat.mcap"
    rec = McapRecorder(path, "local", meta={"session": "bad"})
    for i in range(20):
        _platform(rec, i + 1, T0 + i * 1000)
    rec.derived("latency", T0 + 5000, {"type": "tactile_frame", "seq": 1,
                                       "end_to_end_ms": "5",
                                       "stages_ms": {
                                           '<img src=x onerror="alert(1)">': 1.0,
                                           "relay_in_to_relay_out": "1.0",
                                           "station_rx_to_render": True,
                                           "relay_out_to_station_rx": None,
                                           "capture_to_relay_in": 2.5,
                                           "capture_to_relay_in_2": 0.5}})
    rec.close()
    live = _view_at(path, T0 + 19_000)  # raised TypeError before
    assert live["latency"]["stages_ms"] == {"capture_to_relay_in": 2.5,
                                            "capture_to_relay_in_2": 0.5}
    assert live["latency"]["end_to_end_ms"] is None


# ---------------------------------------------------------------- 3, 5: a full disk


class _FailingFile:
    """The recorder's file, failing its writes when told: ``enospc`` raises at once,
    ``torn`` writes half (as a write to an almost full disk does) and then raises."""

    def __init__(self, real: Any) -> None:
        self._real = real
        self.mode: str | None = None  # None: works
        self.failures = 0

    def write(self, data: Any) -> Any:
        if self.mode is None:
            return self._real.write(data)
        self.failures += 1
        if self.mode == "torn" and self.failures == 1 and len(data) > 1:
            return self._real.write(bytes(data)[:len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    def __getattr__(self, name: str) -> Any:
        return getattr(self._real, name)


@pytest.fixture
def failing_files(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[_FailingFile]]:
    made: list[_FailingFile] = []

    def fake_open(*args: Any, **kw: Any) -> _FailingFile:
        f = _FailingFile(open(*args, **kw))  # noqa: SIM115 - the recorder closes it
        made.append(f)
        return f

    monkeypatch.setattr(writer_module, "open", fake_open, raising=False)
    yield made


@pytest.mark.parametrize("mode", ["enospc", "torn"])
def test_a_moment_of_full_disk_counts_the_lost_messages_and_the_rest_reads(
        tmp_path: Path, failing_files: list[_FailingFile], mode: str) -> None:
    path = tmp_path / "full.mcap"
    rec = McapRecorder(path, "local", meta={"session": "full"}, flush_interval_s=60.0)
    seq = 0

    def batch(n: int) -> None:
        nonlocal seq
        for _ in range(n):
            seq += 1
            _platform(rec, seq, T0 + seq * 1000)  # platform_state + trajectory: 2 messages

    batch(30)
    assert rec.sync()
    (fh,) = failing_files
    fh.mode = mode  # the disk is full
    batch(20)
    t = time.monotonic()
    assert not rec.sync()  # the flush failed: said at once, not after 10 s
    assert time.monotonic() - t < 5.0
    fh.mode = None  # space again
    batch(10)
    assert rec.sync()
    rec.wire("tx", Bye(reason="done"), T0 + 10**6)
    counts = rec.close()
    out = read_mcap(path)
    seqs = [_seq(m.decode()) for m in out.on("/local/tx/platform_state")]
    assert seqs == list(range(1, 31)) + list(range(51, 61))  # the rest reads, in order
    assert out.complete
    assert counts["messages_written"] == len(out.messages) == 81
    assert counts["messages_lost"] == 40 and counts["write_errors"] == 1
    assert counts["per_topic"]["/local/tx/platform_state"] == 40
    assert out.end["counts"]["messages_lost"] == 40  # in the file's end metadata too
    text = format_summary(summarize(out))
    assert "1 write errors, 40 lost" in text and "messages are missing" in text


def test_a_disk_full_from_the_start_is_a_clear_config_error(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    class Full:
        def __init__(self, *args: Any, **kw: Any) -> None:
            pass

        def write(self, data: Any) -> int:
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name: str) -> Any:
            return lambda *a, **k: 0

    monkeypatch.setattr(writer_module, "open", Full, raising=False)
    with pytest.raises(ConfigError, match="cannot write the recording"):
        McapRecorder(tmp_path / "x.mcap", "local")


# ---------------------------------------------------------------- 4: the findings' clock


def test_the_findings_are_stamped_on_the_sessions_clock(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import local_site.palpation as palpation

    finding = SimpleNamespace(center_mm=(30.0, 30.0), kind="benign", equivalent_radius_mm=3.0,
                              confidence=0.9, severity_rank=1)
    monkeypatch.setattr(palpation, "analyse_recording", lambda rec, ws: [finding])
    path = tmp_path / "f.mcap"
    rec = SessionRecorder(path, {"session": "f"})
    start = now_us()
    _platform(rec, 1, start)
    real_ns = time.time_ns
    monkeypatch.setattr(time, "time_ns", lambda: real_ns() + 3600 * 10**9)  # a clock step
    assert rec.add_findings() == 1
    monkeypatch.setattr(time, "time_ns", real_ns)
    rec.close()
    (m,) = read_mcap(path).on("/local/findings")
    assert 0 <= m.t_us - start < 60e6  # not an hour later


# ---------------------------------------------------------------- 5: the remote's summary


@pytest.fixture
async def relay() -> AsyncIterator[Any]:
    from relay_server.config import RelayConfig
    from relay_server.server import RelayServer
    from tests.support import free_tcp_port

    server = RelayServer(RelayConfig(host="127.0.0.1", port=free_tcp_port(),
                                     tcp_port=free_tcp_port(), tokens={"rec": "tok"}))
    await server.start()
    try:
        yield server
    finally:
        await server.close()


async def test_the_remote_writes_its_summary_when_its_recording_cannot_be_finished(
        relay: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from remote_site.agent.app import AgentOptions, run_agent
    from tests.support import scaled

    real_close = McapRecorder.close

    def failing_close(self: McapRecorder, end_meta: Any = None) -> dict[str, Any]:
        real_close(self, end_meta)  # its thread ends; then the footer "fails"
        raise ConfigError(f"cannot finish the recording {self.path}: [Errno 28] disk full")

    monkeypatch.setattr(McapRecorder, "close", failing_close)
    options = AgentOptions(relay=f"tcp://127.0.0.1:{relay.tcp_port}", session="rec",
                           token="tok", duration_s=0.5, record=tmp_path / "remote.mcap")
    summaries: list[dict[str, Any]] = []
    with pytest.raises(ConfigError, match="disk full"):  # exits 1 through the CLI
        await asyncio.wait_for(run_agent(options, asyncio.Event(),
                                         on_summary=summaries.append), scaled(60.0))
    assert len(summaries) == 1
    assert "disk full" in summaries[0]["recording_error"]
    assert summaries[0]["recording"]["path"] == str(tmp_path / "remote.mcap")


def _losing_close(monkeypatch: pytest.MonkeyPatch) -> None:
    """McapRecorder.close as after a brief full disk: the file finished, 3 messages lost."""
    real_close = McapRecorder.close

    def losing_close(self: McapRecorder, end_meta: Any = None) -> dict[str, Any]:
        counts = real_close(self, end_meta)
        self.lost, self.write_errors = 3, 1
        return {**counts, "messages_lost": 3, "write_errors": 1}

    monkeypatch.setattr(McapRecorder, "close", losing_close)


async def test_the_remote_exits_1_when_its_recording_lost_messages(
        relay: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Before, a recording that lost messages to a full disk ended the session as a success
    (exit 0) with only messages_lost saying so."""
    from remote_site.agent.app import AgentOptions, run_agent
    from tests.support import scaled

    _losing_close(monkeypatch)
    options = AgentOptions(relay=f"tcp://127.0.0.1:{relay.tcp_port}", session="rec",
                           token="tok", duration_s=0.5, record=tmp_path / "remote.mcap")
    summaries: list[dict[str, Any]] = []
    with pytest.raises(ConfigError, match="lost 3 messages"):  # exits 1 through the CLI
        await asyncio.wait_for(run_agent(options, asyncio.Event(),
                                         on_summary=summaries.append), scaled(60.0))
    assert "lost 3 messages" in summaries[0]["recording_error"]
    assert summaries[0]["recording"]["messages_lost"] == 3


async def test_the_local_station_exits_1_when_its_recording_lost_messages(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.local_site.agent_support import relay_agent
    from tests.relay_server.relay_clients import running_relay
    from tests.support import scaled

    _losing_close(monkeypatch)
    async with running_relay() as relay_server:
        agent = relay_agent(f"ws://127.0.0.1:{relay_server.ws_port}/", tmp_path,
                            render_loop="thread")
        agent.duration_s = 0.5
        code = await asyncio.wait_for(agent.run(), scaled(60.0))
    assert code == 1
    assert agent.summary is not None and "lost 3 messages" in agent.summary["recording_error"]
    assert agent.summary["recording"]["messages_lost"] == 3


# ---------------------------------------------------------------- a corrupt chunk, --truth


def _chunk_offsets(data: bytes) -> list[tuple[int, int]]:
    """(offset, length) of every chunk record (opcode 0x06) of an MCAP file."""
    import struct

    pos, out = 8, []
    while pos + 9 <= len(data):
        op, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        if op == 0x06:
            out.append((pos, length))
        if op == 0x02:  # footer
            break
        pos += 9 + length
    return out


@pytest.mark.parametrize("which", [0, 1])
def test_a_corrupt_chunk_is_skipped_and_the_chunks_after_it_read(
        tmp_path: Path, which: int) -> None:
    path = tmp_path / "c.mcap"
    rec = McapRecorder(path, "local", meta={"session": "c"})
    for batch in range(3):  # three chunks of 20 platform states
        for i in range(20):
            seq = batch * 20 + i + 1
            _platform(rec, seq, T0 + seq * 1000)
        assert rec.sync()
    rec.close()
    data = bytearray(path.read_bytes())
    chunks = _chunk_offsets(bytes(data))
    assert len(chunks) == 3
    pos, length = chunks[which]  # chunk 0 also holds the channels' only data-section records
    data[pos + 9 + length - 20] ^= 0x55  # a byte of its compressed records
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    out = read_mcap(bad)
    got = [_seq(m.decode()) for m in out.on("/local/tx/platform_state")]
    kept = [s for s in range(1, 61) if not which * 20 < s <= which * 20 + 20]
    assert got == kept  # everything but the corrupt chunk's 20
    assert out.skipped_chunks == 1 and out.skipped_reason and out.unreadable_messages == 0
    assert "CORRUPT: 1 chunks skipped" in format_summary(summarize(out))


def test_a_malformed_ground_truth_is_refused_with_a_clear_error(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from lab.html_report import write_report

    path = tmp_path / "local.mcap"
    write_local_recording(path, seconds=1.0)
    for truth in ({"tumors": 5}, [1, 2], {"tumors": [{"id": "a", "center_mm": ["x", 1]}]}):
        t = tmp_path / "truth.json"
        t.write_text(json.dumps(truth))
        with pytest.raises(InputDataError, match=r"ground truth .* is malformed"):
            write_report(path, tmp_path / "r.html", truth_path=t)


def test_payloads_off_their_schema_are_left_out_counted_or_refused_clearly(
        tmp_path: Path) -> None:
    from local_site.recording import load_recording
    from shared.recording import RecordingFormatError

    path = tmp_path / "ws.mcap"
    rec = McapRecorder(path, "local", meta={"session": "ws"})
    for i in range(10):
        _platform(rec, i + 1, T0 + i * 1000)
    rec.derived("latency", T0 + 5000, {"type": "tactile_frame", "seq": 1, "end_to_end_ms": 4.0,
                                       "stages_ms": {"capture_to_relay_in": "abc",
                                                     "relay_in_to_relay_out": 1.0}})
    rec.derived("latency", T0 + 6000, {"type": "tactile_frame", "seq": 2, "end_to_end_ms": 5.0,
                                       "stages_ms": [["capture_to_relay_in", 1.0]]})
    rec.derived("frame_accepted", T0 + 7000, {"seq": "x", "rx_us": 1})
    rec.close()
    out = read_mcap(path)
    s = summarize(out)  # raised ValueError / TypeError before
    assert s["latency_malformed_values"] == 2
    lat = s["latency_ms"]["/local/latency tactile_frame"]
    assert lat["relay_in_to_relay_out"]["count"] == 1 and lat["end_to_end"]["count"] == 2
    assert "2 malformed values (not a number, or a message not a JSON object) left out" \
        in format_summary(s)
    with pytest.raises(RecordingFormatError, match="frame_accepted message without integer"):
        load_recording(path)  # raised ValueError before
    pytest.importorskip("matplotlib")
    from lab.html_report import _latency_figure

    _, rows = _latency_figure(out)  # raised on the string and the list before
    assert {r["stage"] for r in rows} == {"relay_in_to_relay_out", "end_to_end"}


def test_the_reports_figures_leave_out_messages_that_are_no_json_object(tmp_path: Path) -> None:
    """A pins or latency message that is not a JSON object (or nested past the parser)
    stopped the report (found by review)."""
    pytest.importorskip("matplotlib")
    from lab.html_report import _latency_figure, _pins_figure
    from shared.recording.reader import RecordedMessage

    path = tmp_path / "r.mcap"
    rec = McapRecorder(path, "local", meta={"session": "bad"})
    _platform(rec, 1, T0)
    rec.close()
    out = read_mcap(path)
    for topic, t in (("/local/pins", T0 + 1), ("/local/latency", T0 + 2)):
        out.messages.append(RecordedMessage(topic, t, "json", b"[1, 2]"))
        out.messages.append(RecordedMessage(topic, t + 1, "json", b"[" * 100_000))
    assert "No pin channel" in _pins_figure(out)
    _, rows = _latency_figure(out)
    assert rows == []
