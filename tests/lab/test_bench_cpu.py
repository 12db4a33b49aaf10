"""The CPU benchmark's stage attribution: simulated hardware apart, innermost product stage,
waits recognised by their line, py-spy raw lines parsed per thread."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest

from lab.bench.cpu_impl import classify_stack, parse_raw_profile, thread_roots, window_drops
from lab.bench.cpu_report import product_and_sim


def test_sim_frames_win_anywhere_on_the_stack() -> None:
    stack = [("run", "/x/local_site/display/emulator.py", 10),
             ("send", "/venv/site-packages/can/interfaces/virtual.py", 5)]
    assert classify_stack(stack) == "sim: ArrayTac plant + firmware"


def test_the_innermost_product_stage_wins() -> None:
    stack = [("tick", "/x/local_site/agent/display_loop.py", 1),
             ("render", "/x/local_site/render/renderer.py", 2),
             ("clip", "/venv/site-packages/numpy/core/fromnumeric.py", 3)]
    assert classify_stack(stack) == "render"
    assert classify_stack([("f", "/usr/lib/python3.11/json/decoder.py", 1)]) == \
        "other (interpreter, libraries)"


def test_raw_profile_lines_by_thread_with_waits_apart(tmp_path: Path) -> None:
    src = tmp_path / "mod.py"
    src.write_text("import time\ntime.sleep(1)\nx = sum(range(10))\n")
    render = tmp_path / "local_site" / "render" / "renderer.py"
    render.parent.mkdir(parents=True)
    render.write_text("def render():\n    return 1 + 1\n")
    text = "\n".join([
        f"thread (101): MainThread;<module> ({src}:2) 7",
        f"thread (101): MainThread;<module> ({src}:3);render ({render}:2) 5",
        f"thread (0x1f): Thread-1;<module> ({src}:3) 2",
        "garbage line",
    ])
    out = parse_raw_profile(text)
    assert out[101]["idle"] == 7 and out[101]["render"] == 5
    assert out[0x1F]["other (interpreter, libraries)"] == 2
    roots = thread_roots(text)
    assert roots == {101: "MainThread: <module> (mod.py)", 0x1F: "Thread-1: <module> (mod.py)"}


def test_product_and_sim_totals() -> None:
    run = {"stages": {"local": {"render": 0.1, "sim: ArrayTac plant + firmware": 0.3},
                      "relay": {"relay forwarding": 0.05}}}
    product, sim = product_and_sim(run)
    assert abs(product - 0.15) < 1e-12 and abs(sim - 0.3) < 1e-12


def test_the_demos_processes_and_the_local_stations_board_process_are_found(
        monkeypatch: pytest.MonkeyPatch) -> None:
    from lab.bench import cpu_impl

    py = "/venv/bin/python3"
    table = [  # (pid, parent, argv): the bench is pid 10
        (11, 10, [py, "-P", "-m", "lab.cli", "--log-level", "INFO", "relay", "--port", "1"]),
        (12, 10, [py, "-P", "-m", "lab.cli", "link", "--profile", "lan"]),
        (13, 10, [py, "-P", "-m", "lab.cli", "remote", "--relay", "ws://x"]),
        (14, 10, [py, "-P", "-m", "lab.cli", "local", "--platform", "sim-process"]),
        (15, 14, [py, "-m", "local_site.platform.sim_process", "{}"]),  # the local's board
        (16, 13, [py, "-m", "local_site.platform.sim_process", "{}"]),  # not the local's
        (17, 99, [py, "-P", "-m", "lab.cli", "local"]),  # another demo's station
        (18, 10, ["py-spy", "record", "--pid", "14"]),
        # --display board-process: the emulated drive board (simulated hardware as a whole)
        (19, 10, [py, "-P", "-m", "lab.cli", "--log-level", "INFO", "board", "--listen",
                  "127.0.0.1:7"]),
    ]
    monkeypatch.setattr(cpu_impl, "_processes", lambda: iter(table))
    assert cpu_impl.demo_processes(10) == {11: "relay", 12: "link", 13: "remote", 14: "local",
                                      15: "sim-board", 19: "board"}
    assert set(cpu_impl._SIM_PROCESSES) == {"sim-board", "board"}


def test_the_local_stations_platform_process_and_a_board_below_it_are_found(
        monkeypatch: pytest.MonkeyPatch) -> None:
    from lab.bench import cpu_impl

    py = "/venv/bin/python3"
    table = [  # --platform-process, with and without --platform sim-process
        (14, 10, [py, "-P", "-m", "lab.cli", "local", "--platform", "sim-process",
                  "--platform-process"]),
        (20, 14, [py, "-P", "-m", "local_site.agent.platform_child", "{}"]),
        (21, 20, [py, "-P", "-m", "local_site.platform.sim_process", "{}"]),
        (22, 13, [py, "-P", "-m", "local_site.agent.platform_child", "{}"]),  # not ours
    ]
    monkeypatch.setattr(cpu_impl, "_processes", lambda: iter(table))
    assert cpu_impl.demo_processes(10) == {14: "local", 20: "platform", 21: "sim-board"}


def test_a_snapshot_counts_each_threads_context_switches() -> None:
    import threading
    import time

    from lab.bench.cpu_impl import snapshot

    done, may_end = threading.Event(), threading.Event()

    def sleeper() -> None:  # 20 sleeps: at least 20 voluntary switches of this thread
        for _ in range(20):
            time.sleep(0.001)
        done.set()
        may_end.wait(10.0)  # alive while the second snapshot reads it

    pid = os.getpid()
    thread = threading.Thread(target=sleeper)
    before = snapshot([pid])
    thread.start()
    assert done.wait(10.0)
    tid = thread.native_id
    after = snapshot([pid])
    may_end.set()
    thread.join()
    assert tid is not None and tid in after.switches[pid]
    assert after.switches[pid][tid] - before.switches[pid].get(tid, 0) >= 20
    assert after.switches[pid][tid] >= 20 and after.threads[pid][tid] >= 0.0


def test_the_relays_drops_are_counted_over_the_window_only() -> None:
    start = {"local_to_remote": {"lost": 1, "latest_wins": 5, "queue_full": 0, "no_peer": 7}}
    end = {"local_to_remote": {"lost": 1, "latest_wins": 9, "queue_full": 0, "no_peer": 7},
           "remote_to_local": {"lost": 0, "latest_wins": 2, "queue_full": 0, "no_peer": 0}}
    assert window_drops([start, end]) == {
        "local_to_remote": {"lost": 0, "latest_wins": 4, "queue_full": 0, "no_peer": 0},
        "remote_to_local": {"lost": 0, "latest_wins": 2, "queue_full": 0, "no_peer": 0}}
    assert window_drops([start]) is None  # the window never ended
    assert window_drops([{}, end]) is None  # a reading without the session is no reading
    assert window_drops([start, {}]) is None


def test_the_cpu_the_host_stole_is_read_from_proc_stat(tmp_path: Path) -> None:
    from lab.bench.cpu_impl import steal_s

    tck = os.sysconf("SC_CLK_TCK")
    stat = tmp_path / "stat"
    # user nice system idle iowait irq softirq steal guest guest_nice
    stat.write_text("cpu  100 3 50 1000 7 2 10 20 0 0\ncpu0 50 1 25 500 3 1 5 10 0 0\n")
    assert steal_s(str(stat)) == 20 / tck
    stat.write_text("cpu  100 3 50\n")  # a kernel too old for steal: nothing made up
    assert steal_s(str(stat)) is None
    assert steal_s(str(tmp_path / "absent")) is None
    real = steal_s()
    if real is None:
        pytest.skip("no /proc/stat here")
    assert real >= 0


def test_the_cpu_the_host_stole_over_a_window_is_in_cores() -> None:
    from lab.bench.cpu_impl import CpuSnapshot, stolen_cores

    start = CpuSnapshot(100.0, steal_s=3.0)
    assert stolen_cores(start, CpuSnapshot(104.0, steal_s=3.5)) == pytest.approx(0.125)
    assert stolen_cores(start, CpuSnapshot(104.0, steal_s=3.0)) == 0.0
    # a snapshot that could not read /proc/stat, or no time between them: no figure
    assert stolen_cores(start, CpuSnapshot(104.0)) is None
    assert stolen_cores(CpuSnapshot(100.0), CpuSnapshot(104.0, steal_s=3.5)) is None
    assert stolen_cores(start, CpuSnapshot(100.0, steal_s=3.5)) is None


def test_the_reference_workloads_time_this_thread() -> None:
    from lab.bench.cpu_impl import reference_speed

    ref = reference_speed(rounds=3)
    assert set(ref) == {"python_us", "memory_gb_s"}
    assert all(math.isfinite(v) and v > 0 for v in ref.values())
    with pytest.raises(ValueError):
        reference_speed(rounds=0)


def test_the_reference_figures_reach_the_tables() -> None:
    from benchmarks.bench_cpu_paired import _reference
    from lab.bench.cpu_report import _pair

    run = {"reference": {"before": {"python_us": 1000.0, "memory_gb_s": 20.0},
                         "after": {"python_us": 1500.0}}}
    assert _pair(run, "python_us", 0) == "1000 / 1500"
    assert _pair(run, "memory_gb_s", 1) == "20.0 / -"
    assert _pair({}, "python_us", 0) == "-"  # runs before the probe existed
    assert _reference(run, "python_us") == 1250.0
    assert _reference(run, "memory_gb_s") == 20.0
    assert _reference({"reference": None}, "python_us") is None


def test_a_window_counts_each_threads_time_on_a_run_queue(tmp_path: Path) -> None:
    """Three CPU-bound processes pinned to one CPU for 0.4 s: each runs about a third of the
    time and waits on the run queue about two thirds (a busy loop never sleeps, so its time
    on the CPU and its wait add up to the window, whatever else the machine runs). The
    window's figures give each process' threads' waits over the window per second."""
    import subprocess
    import sys
    import time

    from lab.bench.cpu_impl import CpuBenchSettings, _figures, _Window, snapshot

    cpu = min(os.sched_getaffinity(0))
    code = f"import os; os.sched_setaffinity(0, {{{cpu}}})\nwhile True: pass"
    busy = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(3)]
    try:
        pids = [p.pid for p in busy]
        time.sleep(0.2)  # pinned and running
        start = snapshot(pids)
        time.sleep(0.4)
        end = snapshot(pids)
    finally:
        for p in busy:
            p.kill()
            p.wait()
    if not any(end.waits.get(pid) for pid in pids):
        pytest.skip("this kernel keeps no run-queue waits (schedstat)")
    wall = end.wall_s - start.wall_s
    for pid in pids:
        waited = sum(end.waits[pid].values()) - sum(start.waits[pid].values())
        ran = sum(end.threads[pid].values()) - sum(start.threads[pid].values())
        # ran is counted in 10 ms ticks; the two snapshots read each process a little apart
        assert waited + ran == pytest.approx(wall, abs=0.1 * wall + 0.03)
        assert waited >= 0.4 * wall  # two others share its CPU: about 2/3
    names = {pid: f"relay{i}" for i, pid in enumerate(pids)}
    win = _Window(CpuBenchSettings(), tmp_path, None, start=start, end=end, names=names)
    procs = _figures(win, {}, (0.0, 0.0, 0.0), None)["processes"]
    for pid, name in names.items():
        waited = sum(end.waits[pid].values()) - sum(start.waits[pid].values())
        assert procs[name]["waiting_threads"] == pytest.approx(waited / wall)


def test_schedstat_is_read_as_the_run_queue_wait(tmp_path: Path) -> None:
    from lab.bench.cpu_impl import _run_queue_wait_s

    task = tmp_path / "task"
    task.mkdir()
    (task / "schedstat").write_text("5000000000 1500000000 42\n")  # ran 5 s, waited 1.5 s
    assert _run_queue_wait_s(f"{task}/") == 1.5
    (task / "schedstat").write_text("0 0 0\n")  # a kernel keeping no such figures
    assert _run_queue_wait_s(f"{task}/") is None
    (task / "schedstat").write_text("garbage\n")
    assert _run_queue_wait_s(f"{task}/") is None
    assert _run_queue_wait_s(f"{tmp_path}/none/") is None


def test_the_waiting_figures_reach_the_tables(tmp_path: Path) -> None:
    import json

    from benchmarks.bench_cpu_paired import figures
    from lab.bench.cpu_report import waiting_threads, write_report

    procs = {"relay": {"cores": 0.1, "switches_per_s": 10.0, "waiting_threads": 0.02},
             "remote": {"cores": 0.4, "switches_per_s": 20.0, "waiting_threads": 0.05}}
    assert waiting_threads({"processes": procs}) == pytest.approx(0.07)
    path = tmp_path / "cpu-x.json"
    path.write_text(json.dumps({"load_start": [1.0, 1.0, 1.0], "processes": procs}))
    assert figures(path)["wait"] == pytest.approx(0.07)
    run = {"label": "x", "load_start": [1.0, 1.0, 1.0], "wall_s": 12.0, "stages": {},
           "processes": procs}
    write_report([run], tmp_path)
    text = (tmp_path / "cpu.md").read_text()
    assert "threads waiting to run (mean)" in text and "| remote | 0.050 |" in text
    # a process without the figure (a run from before it was recorded): no total
    del procs["relay"]["waiting_threads"]
    assert waiting_threads({"processes": procs}) is None
    path.write_text(json.dumps({"load_start": [1.0, 1.0, 1.0], "processes": procs}))
    assert figures(path)["wait"] is None


def test_runs_beside_burners_are_labelled_by_their_count_and_nice() -> None:
    from benchmarks.bench_cpu_paired import run_prefix

    assert run_prefix(0) == "" and run_prefix(0, 10) == ""
    assert run_prefix(2) == "b2-"  # the labels of the runs before --burner-nice
    assert run_prefix(2, 10) == "b2n10-"
    # each in a CPU group of its own (--cgroups): apart from the runs without
    assert run_prefix(2, 0, cgroups=True) == "b2cg-" and run_prefix(2, 10, True) == "b2n10cg-"
    assert run_prefix(0, 0, cgroups=True) == "cg-"


def test_a_sides_cpu_weight_is_its_cgroup_flag() -> None:
    from benchmarks.bench_cpu_paired import side_weight

    assert side_weight([]) == 100  # systemd's default CPUWeight=
    assert side_weight(["--sensor-fps::80", "cgroup:1000", "bench:--display=sim"]) == 1000
