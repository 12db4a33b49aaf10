"""The local station alone: CPU per thread and display-loop rate, two trees paired (issue 12).

``teletouch bench cpu`` measures the whole demo, where the local station's figures move with
the remote station, the relay and whatever else the machine runs. This benchmark runs only
``teletouch local --scene hemisphere:radius_mm=10 --platform sim --display sim`` (sim encoder
board on a pty, emulated ArrayTac on virtual CAN FD, display loop at 1 kHz, no relay) from two
source trees, alternating (before, after, before, after, ...), and reads over a window after a
warm-up:

- CPU seconds per wall second of the process and of each thread (``/proc/<pid>/task``: exact),
  threads named by a one-second py-spy look at the end of the window (when py-spy is there);
- the display loop's rate and period jitter from the station's summary;
- local CPU per loop iteration (holds better than CPU per second when the loop is starved).

Run:   git archive main | tar -x -C /tmp/teletouch-main
       python benchmarks/bench_local_station_cpu.py --before /tmp/teletouch-main --rounds 3
Writes benchmarks/results/local_station_cpu.md (``--out`` to change).
"""

from __future__ import annotations

import argparse
import json
import os
import platform as host_platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SCENE = "hemisphere:radius_mm=10"


def _task_cpu_s(pid: int) -> dict[int, float]:
    out: dict[int, float] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[int(tid)] = (int(fields[11]) + int(fields[12])) / tick
    return out


def _thread_names(pid: int, workdir: Path) -> dict[int, str]:
    spy = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    if not Path(spy).exists():
        return {}
    raw = workdir / "names.raw"
    subprocess.run([spy, "record", "--pid", str(pid), "--threads", "--idle", "--nonblocking",
                    "-r", "50", "-d", "1", "-f", "raw", "-o", str(raw)],
                   capture_output=True, timeout=30, check=False)
    names: dict[int, str] = {}
    if raw.exists():
        for line in raw.read_text().splitlines():
            m = re.match(r"thread \((\d+)\): ([^;]*)", line)
            if m:
                names[int(m.group(1))] = re.sub(
                    r" arraytac-sim-[0-9a-f]+| pty://sim| socket://[0-9.]+:\d+", "",
                    m.group(2))
    return names


def run_once(tree: Path, label: str, warmup_s: float, window_s: float,
             board_process: bool = False) -> dict[str, Any]:
    """One station from ``tree``: CPU per thread over the window, the loop's summary.

    With ``board_process`` the emulated ArrayTac board runs as ``teletouch board`` (its own
    process, from the same tree, not counted) and the station reaches it over ``socket://``.
    """
    workdir = Path(tempfile.mkdtemp(prefix=f"local-cpu-{label}-"))
    env = {**os.environ, "PYTHONPATH": str(tree)}
    board = None
    display = "sim"
    if board_process:
        board = subprocess.Popen([sys.executable, "-m", "lab.cli", "board", "--listen",
                                  "127.0.0.1:0"], cwd=workdir, env=env, stdout=subprocess.PIPE,
                                 stderr=subprocess.DEVNULL, text=True)
        assert board.stdout is not None
        first = board.stdout.readline()
        if not first.startswith("board listening on socket://"):
            board.kill()
            raise SystemExit(f"the board process did not start: {first!r}")
        display = first.split()[-1]
    cmd = [sys.executable, "-m", "lab.cli", "local", "--scene", SCENE, "--platform", "sim",
           "--display", display, "--duration", str(warmup_s + window_s + 2.0), "--no-status",
           "--summary-json", "summary.json"]
    with open(workdir / "local.log", "wb") as log:
        proc = subprocess.Popen(cmd, cwd=workdir, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        time.sleep(warmup_s)
        load = os.getloadavg()[0]
        t0, start = time.monotonic(), _task_cpu_s(proc.pid)
        time.sleep(window_s)
        t1, end = time.monotonic(), _task_cpu_s(proc.pid)
        names = _thread_names(proc.pid, workdir)
        proc.wait(timeout=60)
    finally:
        for p in (proc, board):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
    summary = json.loads((workdir / "summary.json").read_text())
    wall = t1 - t0
    threads: dict[str, float] = {}
    for tid, cpu in end.items():
        name = names.get(tid, "other")
        threads[name] = threads.get(name, 0.0) + (cpu - start.get(tid, 0.0)) / wall
    loop = summary["display_loop"]
    cores = sum(threads.values())
    shutil.rmtree(workdir, ignore_errors=True)
    return {"label": label, "load": load, "cores": cores, "threads": threads,
            "rate_hz": loop["rate_hz"], "jitter_p99_ms": loop["jitter_p99_ms"],
            "overruns": loop["overruns"], "us_per_iteration": cores / loop["rate_hz"] * 1e6}


def _median(values: list[float]) -> float:
    s = sorted(values)
    mid = len(s) // 2
    return s[mid] if len(s) % 2 else (s[mid - 1] + s[mid]) / 2


def report(runs: list[dict[str, Any]], args: argparse.Namespace) -> str:
    """The results as Markdown."""
    names = sorted({n for r in runs for n in r["threads"]},
                   key=lambda n: -max(r["threads"].get(n, 0.0) for r in runs))
    lines = ["# The local station alone: CPU per thread and display-loop rate (issue 12)", "",
             f"Machine: {host_platform.machine()}, `nproc` {os.cpu_count()}, shared with other "
             "agents' jobs (load average per run below); Python "
             f"{host_platform.python_version()}. Command: `python "
             f"benchmarks/bench_local_station_cpu.py --before {args.before} --rounds "
             f"{args.rounds}{' --board-process' if args.board_process else ''}` (after = "
             "this tree), runs alternating before/after; each run: "
             f"`teletouch local --scene {SCENE} --platform sim --display "
             f"{'socket://...' if args.board_process else 'sim'}` (sim encoder board on a "
             "pty, "
             + ("the emulated ArrayTac as `teletouch board`, a process of its own reached "
                "over `socket://` and not counted, " if args.board_process else
                "emulated ArrayTac on virtual CAN FD, ")
             + f"1 kHz display loop, no relay), {args.warmup:g} s warm-up, {args.window:g} s "
             "window. Cores = CPU s per wall s (`/proc/<pid>/task`), threads named by "
             "py-spy.", "",
             "| run | load avg | cores | display loop Hz | jitter p99 ms | overruns | "
             "us CPU per iteration | " + " | ".join(names) + " |",
             "|---|---|---|---|---|---|---|" + "---|" * len(names)]
    for r in runs:
        lines.append(f"| {r['label']} | {r['load']:.2f} | {r['cores']:.3f} | "
                     f"{r['rate_hz']:.0f} | {r['jitter_p99_ms']:.2f} | {r['overruns']} | "
                     f"{r['us_per_iteration']:.0f} | "
                     + " | ".join(f"{r['threads'].get(n, 0.0):.3f}" for n in names) + " |")
    pairs = [(b, a) for b, a in zip(runs[::2], runs[1::2], strict=False)]
    ratios = [a["cores"] / b["cores"] for b, a in pairs]
    per_iter = [a["us_per_iteration"] / b["us_per_iteration"] for b, a in pairs]
    lines += ["", f"after/before, paired runs: cores median {_median(ratios):.2f} "
              f"(range {min(ratios):.2f}-{max(ratios):.2f}), CPU per loop iteration median "
              f"{_median(per_iter):.2f} (range {min(per_iter):.2f}-{max(per_iter):.2f}), "
              f"{len(pairs)} pairs.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the paired benchmark and write the results."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="the tree to compare with")
    parser.add_argument("--after", type=Path, default=ROOT, help="default: this tree")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--warmup", type=float, default=6.0)
    parser.add_argument("--window", type=float, default=8.0)
    parser.add_argument("--board-process", action="store_true",
                        help="the emulated ArrayTac board as a process of its own, reached "
                             "over socket:// (not counted)")
    parser.add_argument("--out", type=Path, default=RESULTS / "local_station_cpu.md")
    args = parser.parse_args(argv)
    runs = []
    for i in range(1, args.rounds + 1):
        for tag, tree in (("before", args.before), ("after", args.after)):
            r = run_once(tree.resolve(), f"{tag}-{i}", args.warmup, args.window,
                         args.board_process)
            print(f"{r['label']}: load {r['load']:.2f}, {r['cores']:.3f} cores, loop "
                  f"{r['rate_hz']:.0f} Hz, jitter p99 {r['jitter_p99_ms']:.2f} ms", flush=True)
            runs.append(r)
    text = report(runs, args)
    args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
