"""The fault harness's own arithmetic and its probe's fake clock (no stations started)."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lab.faults import BoardLog, FaultRig, FaultSpec, ProbeLog, _latencies, scenarios
from tests.support import scaled


def test_probe_log_reads_complete_lines_only_and_incrementally(tmp_path: Path) -> None:
    path = tmp_path / "probe.txt"
    log = ProbeLog(path, "remote", 1)
    log.poll()  # no file yet: nothing, no error
    path.write_text("C 1.5 1000 1 12.5\nH 1.7 watchdog\nC 1.8 2000 0 1")
    log.poll()
    assert log.commands == [(1.5, 1000, True, 12.5)] and log.halts == [(1.7, "watchdog")]
    with open(path, "a") as f:
        f.write("50.000\nS 2.0 stale_scene\nA 2.1 7 3000\nR 2.2 7 3000\nU 2.3\nK 2.4 300000\n")
    log.poll()
    assert log.commands[-1] == (1.8, 2000, False, 150.0)
    assert log.safe == [(2.0, "stale_scene")] and log.accepted == [(2.1, 3000)]
    assert log.rendered == [(2.2, 3000)] and log.resumed == [2.3]
    assert log.steps == [(2.4, 300000)]
    with open(path, "a") as f:
        f.write("P 2.5 17 4000\nP 2.6 18 -1\nP 2.7 19\n")  # the last one is malformed
    log.poll()
    assert log.sent == [(2.5, 17, 4000), (2.6, 18, -1)]


def test_board_log_reads_the_board_events_and_knows_the_state_at_a_time(
        tmp_path: Path) -> None:
    path = tmp_path / "board.txt"
    log = BoardLog(path)
    log.poll()
    path.write_text("R 1.0 1\nR 1.02 2\nS 1.13 watchdog\nU 2.0\nR 2.0 1\nS 2.5 safe_state_frame\n"
                    "R 2.6")
    log.poll()
    assert log.applied == [(1.0, 1), (1.02, 2), (2.0, 1)]
    assert log.safe == [(1.13, "watchdog"), (2.5, "safe_state_frame")]
    assert log.resumed == [2.0]
    assert [log.safe_at(t) for t in (0.5, 1.1, 1.13, 1.5, 2.0, 2.2, 3.0)] == \
        [False, False, True, True, False, False, True]
    with open(path, "a") as f:
        f.write(" 3\n")
    log.poll()
    assert log.applied[-1] == (2.6, 3)


def _rig_with_board(tmp_path: Path, sent: list[tuple[float, int, int]],
                    applied: list[tuple[float, int]]) -> FaultRig:
    rig = FaultRig(tmp_path, board_process=True)
    rig.wall_minus_mono_us = 0.0  # wall clock == monotonic clock, in us
    probe = ProbeLog(tmp_path / "p.txt", "local", 1)
    probe.sent = sent
    rig.probes.append(probe)
    rig.board_log = BoardLog(tmp_path / "b.txt")
    rig.board_log.applied = applied
    return rig


def test_pin_ages_join_the_board_s_commands_to_the_latest_send_of_that_number(
        tmp_path: Path) -> None:
    # the display reconnected at t=5 and its sequence numbers restarted at 1
    sent = [(1.0, 1, 900_000), (1.01, 2, 950_000), (5.0, 1, 4_990_000), (5.02, 2, 4_000_000)]
    applied = [(1.002, 1), (1.3, 2), (5.001, 1), (5.021, 2), (6.0, 9)]
    rig = _rig_with_board(tmp_path, sent, applied)
    got = rig.pin_ages()
    assert [(m, s) for m, s, _ in got] == applied
    ages = [a for _, _, a in got]
    assert ages[:4] == [pytest.approx(102.0), pytest.approx(350.0), pytest.approx(11.0),
                        pytest.approx(1021.0)]
    assert ages[4] is None  # no send with that number: unmatched, not guessed
    assert [m for m, _, _ in rig.pin_ages(1.1, 5.01)] == [1.3, 5.001]


def test_commands_applied_after_the_newest_logged_send_wait_for_its_line(
        tmp_path: Path) -> None:
    # seq 3 was written and applied at 1.03, but the probe writes its line after the send
    # returns: at this moment its line is not there yet; seq 9 is a send truly missed
    sent = [(1.0, 1, 900_000), (1.01, 2, 950_000), (1.02, 4, 960_000)]
    applied = [(1.002, 1), (1.012, 2), (1.015, 9), (1.022, 4), (1.03, 3)]
    rig = _rig_with_board(tmp_path, sent, applied)
    assert rig.sends_logged_until() == 1.02
    got = rig.pin_ages(1.0, rig.sends_logged_until())
    assert [(m, s) for m, s, _ in got] == [(1.002, 1), (1.012, 2), (1.015, 9)]
    assert [a is None for _, _, a in got] == [False, False, True]
    assert FaultRig(tmp_path / "none").sends_logged_until() == -math.inf


@given(st.lists(st.tuples(st.floats(0, 10), st.integers(0, 3), st.integers(0, 10_000_000)),
                max_size=25),
       st.lists(st.tuples(st.floats(0, 10), st.integers(0, 3)), max_size=25))
def test_pin_ages_agree_with_a_brute_force_reference(
        tmp_path_factory: pytest.TempPathFactory, sent: list[tuple[float, int, int]],
        applied: list[tuple[float, int]]) -> None:
    rig = _rig_with_board(tmp_path_factory.mktemp("rig"), sent, applied)
    expected = []
    for mono, seq in applied:
        before = [(m, ts) for m, s, ts in sent if s == seq and m <= mono]
        ts = max(before)[1] if before else None
        expected.append((mono, seq, None if ts is None else (mono * 1e6 - ts) / 1e3))
    got = rig.pin_ages()
    assert [(m, s) for m, s, _ in got] == [(m, s) for m, s, _ in expected]
    for (_, _, a), (_, _, b) in zip(got, expected, strict=True):
        assert (a is None and b is None) or a == pytest.approx(b)


def test_latency_is_measured_from_the_last_input_before_each_event() -> None:
    inputs = [1.0, 1.01, 1.02, 5.0]
    events = [1.12, 1.5, 5.1, 0.5]  # 1.5 repeats 1.12's input; 0.5 has no input before it
    got = _latencies(sorted(events), inputs)
    assert got == [(1.12, pytest.approx(100.0)), (5.1, pytest.approx(100.0))]


@given(st.lists(st.floats(0, 100), min_size=1, max_size=30),
       st.lists(st.floats(0, 100), min_size=1, max_size=30))
def test_latencies_agree_with_a_brute_force_reference(inputs: list[float],
                                                      events: list[float]) -> None:
    inputs, events = sorted(inputs), sorted(events)
    expected = []
    used = set()
    for t in events:
        before = [i for i in inputs if i <= t]
        if before and before[-1] not in used:
            used.add(before[-1])
            expected.append((t, (t - before[-1]) * 1e3))
    assert _latencies(events, inputs) == expected


def test_true_age_removes_the_clock_step_the_harness_injected(tmp_path: Path) -> None:
    rig = FaultRig(tmp_path)
    rig.wall_minus_mono_us = 1_000_000_000.0
    rig.clock_steps["local"] = [(10.0, 300_000)]
    # sent at true wall 1_000_000_000 + 9.94e6 us, received 50 ms later, before the step
    assert rig.age_ms("local", 9.99, 1_000_000_000 + 9_940_000) == pytest.approx(50.0)
    # after the step the sender's stamps are 300 ms ahead; the true age is still 50 ms
    assert rig.age_ms("local", 20.0, 1_000_000_000 + 19_950_000 + 300_000) == \
        pytest.approx(50.0)
    assert rig.age_ms("remote", 20.0, 1_000_000_000 + 19_950_000) == pytest.approx(50.0)


def test_the_suite_covers_the_issue_s_faults() -> None:
    names = [s.name for s in scenarios()]
    kinds = {(s.fault.kind, s.fault.target, s.fault.duration_s) for s in scenarios()}
    for d in (0.5, 2.0, 10.0):
        assert ("relay_kill", "remote", d) in kinds
    for kind in ("blackhole", "reset"):
        for leg in ("local", "remote"):
            for d in (0.2, 2.0, 20.0, 60.0):
                assert (kind, leg, d) in kinds
    for role in ("local", "remote"):
        assert {("kill", role, 0.5), ("stop", role, 3.0), ("clock_step", role, 0.3)} <= kinds
    assert {("kill", "platform", 0.0), ("stop", "platform", 3.0)} <= kinds
    assert sum(s.cpu_burners == 2 for s in scenarios()) >= 3
    assert len(set(names)) == len(names)
    assert not any(s.fault.duration_s > 2.0 for s in scenarios(long=False)
                   if s.fault.kind in ("blackhole", "reset"))
    with pytest.raises(ValueError, match="unknown fault"):
        FaultSpec("meteor")
    with pytest.raises(ValueError, match="local, remote or platform"):
        FaultSpec("kill", "relay")
    with pytest.raises(ValueError, match="only be killed or stopped"):
        FaultSpec("clock_step", "platform", 0.3)


def test_probe_clock_steps_the_wall_clock_not_the_monotonic_one(tmp_path: Path) -> None:
    offset = tmp_path / "clock.txt"
    offset.write_text("0\n")
    code = (
        "import sys, time\n"
        "import lab.faults_probe as p\n"
        f"p._install_clock({str(offset)!r})\n"
        "print('ready', flush=True)\n"
        "sys.stdin.readline()\n"
        "w, m = time.time(), time.monotonic()\n"
        "print(w - m, time.time_ns() / 1e9 - time.monotonic(), flush=True)\n"
        "sys.stdin.readline()\n"
        "print(time.time() - time.monotonic(), flush=True)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdin is not None and proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        proc.stdin.write("\n")
        proc.stdin.flush()
        before = [float(v) for v in proc.stdout.readline().split()]
        offset.write_text("2.5\n")
        proc.send_signal(signal.SIGUSR2)
        proc.stdin.write("\n")
        proc.stdin.flush()
        after = float(proc.stdout.readline())
        proc.wait(scaled(10.0))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert abs(before[0] - before[1]) < 0.05
    assert after - before[0] == pytest.approx(2.5, abs=0.05)



def test_analysis_with_the_board_process_takes_the_safe_state_and_the_ages_from_the_board(
        tmp_path: Path) -> None:
    from lab.bench.faults import _verdict, report_markdown
    from lab.faults import analyse

    # a station renders fresh frames (10 ms old) until it is stopped at t=1.5; the board's
    # watchdog parks the pins 100 ms after the last command it applied; after SIGCONT at 4.5
    # the station renders again, and one command carries a frame 300 ms old to the pins
    frames = [1.0 + 0.02 * i for i in range(26)] + [4.6 + 0.02 * i for i in range(10)]
    sent = [(m, i + 1, round(m * 1e6) - 10_000) for i, m in enumerate(frames)]
    sent[-1] = (sent[-1][0], sent[-1][1], round(sent[-1][0] * 1e6) - 300_000)
    applied = [(m + 0.001, seq) for m, seq, _ in sent]
    rig = _rig_with_board(tmp_path, sent, applied)
    probe = rig.probe("local")
    probe.accepted = [(m, ts) for m, _, ts in sent[:-1]]
    probe.rendered = list(probe.accepted)
    assert rig.board_log is not None
    rig.board_log.safe = [(1.501 + 0.1, "watchdog")]
    rig.board_log.resumed = [4.601]
    rig.poll = lambda: None  # type: ignore[method-assign]  # the lists above are the files
    r = analyse(rig, [(1.5, 4.5)])
    assert r["safe_source"] == "board" and r["station_safe_ms"]["n"] == 0
    assert r["safe_ms"]["n"] == 1 and r["safe_ms"]["max"] == pytest.approx(101.0)
    assert r["board_safe_reasons"] == {"watchdog": 1}
    assert (r["pins_applied"], r["stale_at_pins"], r["pins_unmatched"]) == (36, 1, 0)
    assert r["stale_at_pins_max_age_ms"] == pytest.approx(301.0)
    fault = r["faults"][0]
    assert fault["board_safe_at_recovery"] is True
    assert fault["pins_after"]["stale_at_pins"] == 1 and fault["safe_ms"] == pytest.approx(101.0)
    r.update({"scenario": "local station SIGSTOP 3 s", "kind": "stop", "repeats": 1,
              "error": None, "board_process": True, "injected_unsteady": 0,
              "summaries": {"board": {"commands_applied": 36, "commands_rejected": 0,
                                      "watchdog_trips": 1, "niceness": -10,
                                      "link": {"connects": 1, "disconnects": 0,
                                               "feedback_dropped": 7}}}})
    assert "stale at the pins" in _verdict(r)
    md = report_markdown([r], command="x", machine="y", elapsed_s=1.0)
    assert "the drive board as its own process" in md
    assert "| local station SIGSTOP 3 s | watchdog 1 | -/-/- (0) | 36 / 0 | 1 (301) / 0 | 1 | " \
        "1 / 0 / 7 | yes | -10 |" in md


def test_a_partial_run_does_not_replace_the_committed_table_unless_told() -> None:
    from lab.bench.faults import results_dir

    assert results_dir(None, None) == "benchmarks/results"  # the whole suite
    assert results_dir(None, ["remote station SIGKILL"]) == ""  # --only: nowhere
    assert results_dir("my-results", ["relay"]) == "my-results"  # told where
    assert results_dir("", None) == ""


def test_major_page_faults_are_read_from_proc_and_agree_with_getrusage() -> None:
    import os
    import resource

    from lab.bench.faults import _major_faults as fmt
    from lab.faults import _major_faults

    before = _major_faults(os.getpid())
    after = resource.getrusage(resource.RUSAGE_SELF).ru_majflt  # independent: getrusage(2)
    assert before is not None and 0 <= after - before <= 5
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait(scaled(30.0))
    assert _major_faults(gone.pid) is None
    assert fmt(None) == "-" and fmt({"relay-1": 0}) == "0"
    assert fmt({"remote-1": 7, "relay-1": 0, "local-1": 2}) == "local-1 2, remote-1 7"


def test_major_faults_are_counted_from_the_steady_mark(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    # the start-up's faults (imports, before a station locks its memory) are not the
    # session's: a process running at the mark reports what came after it, one started
    # later (a restarted station) its whole life
    import lab.faults as faults

    counts = {"early-1": 10, "late-1": 4}
    monkeypatch.setattr(faults, "_major_faults", lambda pid: counts[names[pid]])
    rig = FaultRig(tmp_path)
    names: dict[int, str] = {}

    def start(name: str) -> None:
        proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"],
                                stdin=subprocess.PIPE)
        names[proc.pid] = name
        rig._all.append(faults._Proc(name, proc, tmp_path / f"{name}.log", 0.0))

    start("early-1")
    rig.mark_major_faults()
    start("late-1")
    counts["early-1"] += 7
    rig.stop()
    assert rig.major_faults == {"early-1": 7, "late-1": 4}


@pytest.mark.parametrize("lock", [True, False])
def test_the_rig_can_start_the_stations_without_their_memory_lock(tmp_path: Path,
                                                                   lock: bool) -> None:
    rig = FaultRig(tmp_path, lock_memory=lock)
    started: list[list[str]] = []
    rig._spawn = lambda name, args, **kw: started.append(args)  # type: ignore[assignment,method-assign]
    rig.leg_ports, rig.token = {"local": 1, "remote": 2}, "token"
    rig.start_station("local")
    rig.start_station("remote")
    assert [a[0] for a in started] == ["local", "remote"]
    assert all(("--no-lock-memory" in a) is not lock for a in started)


def test_only_selects_by_name_and_a_selection_of_nothing_is_an_error() -> None:
    from lab.bench.faults import select
    from shared.errors import ConfigError

    items = scenarios()
    assert select(items, None) == items
    chosen = select(items, ["PLATFORM process", "baseline"])
    assert [s.name for s in chosen] == ["baseline (no fault)", "platform process SIGKILL",
                                        "platform process SIGSTOP 3 s"]
    with pytest.raises(ConfigError, match=r"matches no scenario.*baseline"):
        select(items, ["no such scenario"])
