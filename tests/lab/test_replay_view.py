"""A replay as a live-view source: what it shows against the recording, pause and play."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from lab.replay import PlaybackClock, Replayer
from lab.replay_view import ReplayViewSource
from local_site.view.analysis import LiveAnalysisConfig
from shared.protocol import Hop, PlatformState, TactileFrame, Welcome
from shared.protocol.tactile_codec import TactileEncoder
from shared.recording import McapRecorder, read_mcap
from tests.lab.browser_support import interrupt
from tests.recordings import write_local_recording
from tests.support import REPO_ROOT, wait_until


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "local.mcap"
    write_local_recording(path, seconds=3.0)
    return path


def test_the_clock_stands_still_while_paused_and_never_passes_the_end() -> None:
    clock = PlaybackClock(1_000_000, 1_400_000, speed=2.0)
    assert clock.position_us() == 1_000_000  # not started: at the start
    t0 = time.perf_counter()
    clock.start()
    time.sleep(0.05)
    pos = clock.position_us()
    elapsed = time.perf_counter() - t0
    assert 1_000_000 + 0.05e6 * 2.0 <= pos <= 1_000_000 + elapsed * 1e6 * 2.0 + 1
    clock.pause()
    held = clock.position_us()
    time.sleep(0.05)
    assert clock.position_us() == held and clock.paused
    clock.play()
    stop = threading.Event()
    assert clock.wait_until(1_400_000, stop)
    time.sleep(0.01)
    assert clock.position_us() == 1_400_000  # clamped at the end
    clock.finish()
    assert clock.finished and clock.position_us() == 1_400_000
    paused = PlaybackClock(0, 10_000_000, 1.0, paused=True)
    paused.start()
    stop.set()
    assert not paused.wait_until(1, stop)  # a stop ends the wait of a paused clock


def test_after_the_replay_the_view_shows_the_recordings_last_state(recording: Path) -> None:
    rec = read_mcap(recording)
    replayer = Replayer(rec, speed=10.0, display="none")
    source = ReplayViewSource(replayer, LiveAnalysisConfig(interval_s=0.2, nice=0))
    try:
        replayer.run()
        live = source.live()
        end = replayer.clock.end_us
        frames = list(rec.on("/local/rx/tactile_frame"))
        pins = list(rec.on("/local/pins"))
        rp = live["replay"]
        assert rp["ended"] and not rp["paused"] and rp["position_us"] == end
        start = min(m.t_us for m in rec.messages)
        assert rp["duration_s"] == pytest.approx((end - start) / 1e6, abs=1e-3)
        assert rp["file"] == "local.mcap" and rp["station"] == "local" and rp["complete"]
        # the newest frame and pins, with their ages in recorded time at the end
        last = frames[-1].decode()
        assert isinstance(last, TactileFrame)
        assert live["patch"]["seq"] == last.seq
        assert live["patch"]["age_ms"] == pytest.approx((end - frames[-1].t_us) / 1e3, abs=0.1)
        assert live["pins"]["commanded_mm"] == pins[-1].json()["commanded_mm"]
        assert live["link"] == {"state": "replay"}
        # the probe's age on the replay's clock (none was sent before: never drawn stale)
        last_platform = max(m.t_us for m, _ in rec.wire_messages("tx", "platform_state"))
        assert live["probe"]["platform_age_ms"] == pytest.approx(
            (end - last_platform) / 1e3, abs=0.1)
        # the trajectory: recorded platform positions through the workspace, in order
        first, points = source.trail_since(0, 10_000)
        assert first == 0 and len(points) >= 10
        p0 = next(m for m, _ in rec.wire_messages("tx", "platform_state"))
        msg = p0.decode()
        assert isinstance(msg, PlatformState)
        ph = source.workspace.forward(np.asarray(msg.position_mm))
        assert points[0][:3] == pytest.approx([round(float(v), 2) for v in ph], abs=0.01)
        # every accepted frame went to the re-run analysis (frames and acceptances matched)
        assert source._analysis is not None
        assert source._analysis.frames_sent == sum(1 for _ in rec.on("/local/frame_accepted"))
    finally:
        source.close()


def test_pause_and_play_from_the_page_hold_and_resume_the_replay(recording: Path) -> None:
    rec = read_mcap(recording)
    replayer = Replayer(rec, speed=1.0, display="none", start_paused=True)
    source = ReplayViewSource(replayer, analysis=None)
    published: list[int] = []
    replayer.subscribe(lambda ev: published.append(ev.t_us))
    stop = threading.Event()
    thread = threading.Thread(target=replayer.run, args=(stop,), daemon=True)
    thread.start()
    try:
        wait_until(lambda: replayer.clock.started, 10, "the replay started")
        live = source.live()
        assert live["replay"]["paused"] and live["replay"]["position_s"] == 0
        assert live["patch"] is None  # nothing before play
        source.control({"type": "control", "action": "play"})
        wait_until(lambda: source.live()["patch"] is not None, 10, "a frame shown")
        source.control({"type": "control", "action": "pause"})
        held = source.live()
        count = len(published)
        time.sleep(0.2)
        again = source.live()
        assert len(published) == count
        assert again["replay"]["position_us"] == held["replay"]["position_us"]
        assert again["patch"]["age_ms"] == held["patch"]["age_ms"]  # ages stand still too
        with pytest.raises(ValueError, match="unknown replay control"):
            source.control({"type": "control", "action": "rewind"})
        source.control({"type": "control", "action": "play"})
        wait_until(lambda: len(published) > count, 10, "the replay going on")
    finally:
        stop.set()
        thread.join(10)
        source.close()


# started the way a background job of a shell without job control is: SIGINT ignored
_SIGINT_IGNORED = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
                   "os.execv(sys.executable, [sys.executable, '-m', 'lab.cli', *sys.argv[1:]])")


def _group(pgid: int) -> list[int]:
    """The live (not zombie) processes of a process group."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            found.append(int(entry))
    return found


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="lists a process group via /proc")
@pytest.mark.parametrize("whole_group", [False, True], ids=["sigint", "terminal_ctrl_c"])
def test_ctrl_c_ends_a_replay_view_promptly_and_cleanly_even_if_sigint_came_in_ignored(
        recording: Path, tmp_path: Path, whole_group: bool) -> None:
    # issue 9: started in the background by a shell without job control, the replay
    # inherited SIGINT ignored and never ended on Ctrl-C (killed after 90 s in the test)
    log_path = tmp_path / "replay.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-c", _SIGINT_IGNORED, "replay", str(recording), "--view",
             "127.0.0.1:0", "--speed", "4", "--display", "none"],
            cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=log, start_new_session=True)
        try:
            wait_until(lambda: "the view stays up" in log_path.read_text()
                       or proc.poll() is not None, 60, "the replay's end")
            assert proc.poll() is None, log_path.read_text()[-2000:]
            before = _group(proc.pid)
            assert len(before) >= 2, "the replay and its analysis process"
        finally:
            # whole_group: a terminal's Ctrl-C reaches every process of the group
            ended = interrupt(proc, timeout_s=30.0, group=whole_group)
    print(f"exit {ended.seconds:.2f} s after SIGINT; group before: {len(before)} processes")
    text = log_path.read_text()
    assert not ended.killed and proc.returncode == 0, text[-2000:]
    assert b"replayed " in ended.stdout
    assert "Traceback" not in text, text[-2000:]
    wait_until(lambda: not _group(proc.pid), 10, "every process of the replay gone")


def _frame(seq: int, height_mm: float, t_us: int, peak_mm: float | None = None
           ) -> TactileFrame:
    height = np.full((8, 8), height_mm, np.float32)
    if peak_mm is not None:
        height[3, 3] = peak_mm  # one sample changed: the encoder sends a delta
    return TactileFrame(seq=seq, ts_us=t_us, center_mm=(30.0, 30.0), pitch_mm=0.5,
                        hops=(Hop("local", "station_rx", t_us),), layers={"height_mm": height})


def _two_sessions(path: Path) -> None:
    """A recording of two link sessions: the old sender's key frame (2 mm) and a delta (a
    3 mm peak), then a restarted sender's delta on its key seq 1, whose key frame was lost."""
    rec = McapRecorder(path, "local", meta={"session": "s"})
    t = 1_700_000_000_000_000
    old, new = TactileEncoder(), TactileEncoder()
    rec.tap("rx", Welcome(session="s", role="local"), t)  # as the link taps it
    rec.tap("rx", old.encode(_frame(1, 2.0, t + 1000)), t + 1000)
    delta = old.encode(_frame(2, 2.0, t + 2000, peak_mm=3.0))
    assert not delta.key and delta.key_seq == 1
    rec.tap("rx", delta, t + 2000)
    rec.tap("rx", Welcome(session="s", role="local"), t + 3000)  # the sender restarted
    new.encode(_frame(1, 0.5, t + 4000))  # its key frame lost on the way
    stray = new.encode(_frame(2, 0.5, t + 5000))  # a delta on key seq 1, 0 mm of change
    assert not stray.key and stray.key_seq == 1
    rec.tap("rx", stray, t + 5000)
    rec.close()


def test_a_replay_forgets_the_key_frame_at_a_new_link_session(tmp_path: Path) -> None:
    """The station forgets its key frame at each new link session (a restarted sender
    numbers its frames from 1 again); the replay kept one decoder for the whole recording and
    applied the new sender's delta to the old sender's key frame of the same seq, showing
    2 mm where the station rendered nothing (found by audit). The link's welcome is recorded
    now (its resume secret blanked), and the replay starts anew there."""
    path = tmp_path / "local.mcap"
    _two_sessions(path)
    recording = read_mcap(path)
    replayer = Replayer(recording, speed=100.0, display="none")
    source = ReplayViewSource(replayer, None)
    try:
        replayer.run()
        patch = source.live()["patch"]
        # the last frame decoded is the old session's seq 2 (its 3 mm peak), not the new
        # sender's delta applied to the old key frame (2 mm flat)
        assert patch["seq"] == 2 and patch["hi_mm"] == pytest.approx(3.0, abs=0.01)
    finally:
        source.close()


def test_a_replay_on_a_display_hands_it_only_what_the_station_decoded(tmp_path: Path) -> None:
    """The same for the replay that drives a display: the stray delta never reaches it."""
    path = tmp_path / "local.mcap"
    _two_sessions(path)
    result = Replayer(read_mcap(path), speed=100.0, display="sim").run()
    assert result.frames_to_display == 2
