"""What the display loop waits for in the demo: the CPU or the GIL (issue 12).

The loop's period jitter p99 is 0.07-0.3 ms with the local station alone and 0.8-2 ms in the
demo. Earlier rounds guessed the GIL (``docs/speed.md`` sections 12 and 18) without a way to
see it. This records the kernel's scheduler events while ``teletouch bench cpu`` runs the demo
and follows the display loop's thread through every tick:

* ``sched:sched_wakeup`` / ``sched:sched_switch`` for every task (who runs, who waits for a
  CPU), and ``clock_nanosleep`` / ``futex`` entries and exits of the loop's thread (its period
  sleep, and its waits for the GIL: CPython's GIL is a mutex and a condition variable, both
  futexes);
* per tick: the timer wake's run-queue delay (woken until on a CPU), the futex waits while
  the tick works, and for each wait longer than 0.2 ms the thread that ended it (the futex
  wake comes from the thread that released the GIL) and where that thread was during the
  wait: on a CPU, runnable but not running (preempted: the GIL held by a thread the scheduler
  does not run), or asleep.

Needs ``perf`` with the ``sched`` and ``syscalls`` tracepoints, tracefs mounted (here:
``mount -t tracefs nodev /sys/kernel/tracing``, once per boot) and the right to trace every
CPU (root here; elsewhere ``perf_event_paranoid`` <= -1 and tracefs access), and py-spy to
name the threads. A tick is one ``clock_nanosleep`` exit to the next entry (ticks that
overran and did not sleep are merged into one). In this Firecracker guest, events in an idle
CPU's context (a wake-up the kernel completes there, and the switch from idle to the woken
thread) are often missing from the record: such waits are counted but not attributed, and
a tick's wake-to-CPU delay is taken only where both of its events were recorded.

Run:   python benchmarks/trace_display_waits.py --label lan --link lan [--seconds 6]
Writes benchmarks/results/display_waits/<label>.md and .json (the demo's own
``bench cpu`` JSON beside them).
"""

from __future__ import annotations

import argparse
import bisect
import collections
import itertools
import json
import os
import platform as host_platform
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from lab.bench.cpu_impl import demo_processes, pyspy_path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "display_waits"
LONG_WAIT_S = 0.2e-3
MERGE_GAP_S = 30e-6
_EVENT = re.compile(r"^\s*(\S.*?)\s+(\d+)\s+\[(\d+)\]\s+([\d.]+):\s+(\S+):\s*(.*)$")
_SWITCH = re.compile(r"prev_pid=(\d+) .*prev_state=(\S+) ==> .*next_pid=(\d+) ")
_WAKE = re.compile(r" pid=(\d+) ")
_FUTEX_OP = re.compile(r"op: (0x[0-9a-f]+)")
#: futex commands that wait (WAIT, LOCK_PI, WAIT_BITSET, WAIT_REQUEUE_PI, LOCK_PI2); the
#: others (WAKE, REQUEUE, WAKE_OP, UNLOCK_PI, ...) return without sleeping
_FUTEX_WAITS = {0, 6, 9, 11, 13}


def _perf() -> str:
    path = shutil.which("perf")
    if path is None:
        raise SystemExit("perf is needed and was not found")
    return path


def _local_station(bench_pid: int, deadline_s: float) -> int:
    """The pid of the demo's local station (a child of the ``bench cpu`` process), once it
    runs."""
    while time.monotonic() < deadline_s:
        local = [pid for pid, cmd in demo_processes(bench_pid).items() if cmd == "local"]
        if local:
            return local[0]
        time.sleep(0.5)
    raise SystemExit("the demo's local station did not start")


def _threads(pid: int) -> tuple[dict[int, str], int]:
    """Thread names by tid (py-spy) and the tid running the display loop."""
    spy = pyspy_path()
    if spy is None:
        raise SystemExit("py-spy is needed (it names the threads) and was not found")
    dump = subprocess.run([spy, "dump", "--pid", str(pid)], capture_output=True, text=True,
                          timeout=60, check=False).stdout
    names: dict[int, str] = {}
    loop_tid = None
    current = None
    for line in dump.splitlines():
        m = re.match(r'Thread (\d+) \([^)]*\): "(.*)"', line)
        if m:
            current = int(m.group(1))
            names[current] = re.sub(r" socket://\S+| pty://\S+", "", m.group(2))
        elif current is not None and "DisplayLoop._run_in_thread" in line:
            loop_tid = current
    if loop_tid is None:
        raise SystemExit("no thread of the local station runs DisplayLoop._run_in_thread")
    names[loop_tid] = "display loop"
    return names, loop_tid


def _policies(pid: int) -> dict[str, str]:
    out = {}
    for tid in sorted(os.listdir(f"/proc/{pid}/task")):
        policy = os.sched_getscheduler(int(tid))
        prio = os.sched_getparam(int(tid)).sched_priority
        out[tid] = {os.SCHED_FIFO: f"SCHED_FIFO {prio}", os.SCHED_RR: f"SCHED_RR {prio}"}.get(
            policy, "SCHED_OTHER")
    return out


def record(loop_tid: int, seconds: float, data: Path) -> list[tuple[float, int, str, str]]:
    """perf record system-wide, then the events as (time, common pid, event, fields)."""
    only = f"common_pid == {loop_tid}"
    cmd = [_perf(), "record", "-q", "-a", "-o", str(data),
           "-e", "sched:sched_switch", "-e", "sched:sched_wakeup"]
    for ev in ("sys_enter_futex", "sys_exit_futex", "sys_enter_clock_nanosleep",
               "sys_exit_clock_nanosleep"):
        cmd += ["-e", f"syscalls:{ev}", "--filter", only]
    subprocess.run([*cmd, "--", "sleep", str(seconds)], capture_output=True, check=True)
    text = subprocess.run([_perf(), "script", "-i", str(data)], capture_output=True,
                          text=True, check=True).stdout
    events = []
    for line in text.splitlines():
        m = _EVENT.match(line)
        if m:
            events.append((float(m.group(4)), int(m.group(2)), m.group(5), m.group(6) + " "))
    events.sort(key=lambda e: e[0])
    return events


def _intervals(events: list[tuple[float, int, str, str]]) \
        -> tuple[dict[int, list[tuple[float, float]]], dict[int, list[tuple[float, float]]]]:
    """Per task: on-CPU intervals, and runnable-but-not-running intervals."""
    on: dict[int, list[tuple[float, float]]] = collections.defaultdict(list)
    ready_iv: dict[int, list[tuple[float, float]]] = collections.defaultdict(list)
    running: dict[int, float] = {}
    ready: dict[int, float] = {}
    for t, _pid, name, rest in events:
        if name == "sched:sched_wakeup":
            w = _WAKE.search(rest)
            if w:
                ready.setdefault(int(w.group(1)), t)
        elif name == "sched:sched_switch":
            m = _SWITCH.search(rest)
            if not m:
                continue
            prev, state, nxt = int(m.group(1)), m.group(2), int(m.group(3))
            if prev in running:
                on[prev].append((running.pop(prev), t))
            if state.startswith("R"):
                ready[prev] = t
            running[nxt] = t
            if nxt in ready:
                ready_iv[nxt].append((ready.pop(nxt), t))
    return on, ready_iv


def _overlap(ivs: list[tuple[float, float]], a: float, b: float) -> float:
    return sum(max(0.0, min(e, b) - max(s, a)) for s, e in ivs if e > a and s < b)


def _episodes(waits: list[tuple[float, float, int]]) -> list[tuple[float, float, int]]:
    """Futex waits back to back (less than ``MERGE_GAP_S`` apart) as one wait, ended by the
    thread that ended the last: a GIL wait times out after the switch interval (0.2 ms in
    the local station), asks the holder to drop the GIL and waits again, until the holder
    does."""
    merged: list[tuple[float, float, int]] = []
    for a, b, who in waits:
        if merged and a - merged[-1][1] < MERGE_GAP_S:
            merged[-1] = (merged[-1][0], b, who)
        else:
            merged.append((a, b, who))
    return merged


def analyse(events: list[tuple[float, int, str, str]], loop_tid: int,
            names: dict[int, str]) -> dict[str, Any]:
    """The loop's ticks from the events (see the module docstring)."""
    wakes: list[float] = []
    wakers: list[int] = []
    switch_in: list[float] = []
    ticks: list[dict[str, Any]] = []
    futex_enter: float | None = None
    for t, pid, name, rest in events:
        if name == "sched:sched_wakeup":
            w = _WAKE.search(rest)
            if w and int(w.group(1)) == loop_tid:
                wakes.append(t)
                wakers.append(pid)
        elif name == "sched:sched_switch":
            m = _SWITCH.search(rest)
            if m and int(m.group(3)) == loop_tid:
                switch_in.append(t)
        elif pid != loop_tid:
            continue
        elif name == "syscalls:sys_exit_clock_nanosleep":
            ticks.append({"exit": t, "futex": []})
        elif name == "syscalls:sys_enter_futex":
            op = _FUTEX_OP.search(rest)
            # only the calls that may sleep: the thread's own wakes of others go by
            futex_enter = t if op and int(op.group(1), 16) & 0x7F in _FUTEX_WAITS else None
        elif name == "syscalls:sys_exit_futex":
            if futex_enter is not None and ticks:
                # the wake-up that ended the wait falls inside it (none: it returned at once,
                # the futex's value had changed already)
                i = bisect.bisect_right(wakes, t) - 1
                waker = wakers[i] if i >= 0 and wakes[i] >= futex_enter else -1
                ticks[-1]["futex"].append((futex_enter, t, waker))
            futex_enter = None
        elif name == "syscalls:sys_enter_clock_nanosleep" and ticks:
            ticks[-1]["sleep"] = t
    on, ready_iv = _intervals(events)
    rows = []
    for prev, tk in itertools.pairwise(ticks):
        if "sleep" not in tk or "sleep" not in prev:
            continue
        # the wake-up and switch-in that ended the period sleep, when both were recorded
        # (wake-ups done in an idle CPU's context are missing from this guest's traces)
        i = bisect.bisect_right(wakes, tk["exit"]) - 1
        j = bisect.bisect_right(switch_in, tk["exit"]) - 1
        seen = i >= 0 and j >= 0 and prev["sleep"] <= wakes[i] <= switch_in[j]
        first = [f for f in tk["futex"] if f[0] - tk["exit"] < 50e-6]
        start = first[0][1] if first else tk["exit"]
        rows.append({"start": start,
                     "runq_ms": (switch_in[j] - wakes[i]) * 1e3 if seen else None,
                     "gil_at_start_ms": (first[0][1] - first[0][0]) * 1e3 if first else 0.0,
                     "work_ms": (tk["sleep"] - start) * 1e3,
                     "futex_ms": sum(b - a for a, b, _ in tk["futex"]) * 1e3,
                     "futex_n": len(tk["futex"]), "futex": tk["futex"]})
    starts = np.array([r["start"] for r in rows])
    jitter = np.abs(np.diff(starts) * 1e3 - 1.0)
    work = np.array([r["work_ms"] for r in rows])
    futex = np.array([r["futex_ms"] for r in rows])
    runq = np.array([r["runq_ms"] for r in rows if r["runq_ms"] is not None])
    long_ticks = work > 1.0
    by: dict[str, dict[str, list[float]]] = collections.defaultdict(
        lambda: {"wait_ms": [], "on_cpu": [], "runnable": []})
    for r in rows:
        for a, b, who in _episodes(r["futex"]):
            if b - a < LONG_WAIT_S:
                continue
            d = by["not recorded (woken from an idle CPU)" if who == -1 else
                   names.get(who, "an interrupt (timer or wake-up IPI) in another task")]
            d["wait_ms"].append((b - a) * 1e3)
            d["on_cpu"].append(_overlap(on.get(who, []), a, b) / (b - a))
            d["runnable"].append(_overlap(ready_iv.get(who, []), a, b) / (b - a))

    def pct(a: np.ndarray, q: float) -> float:
        return float(np.percentile(a, q)) if a.size else float("nan")

    return {
        "ticks": len(rows),
        "jitter_p50_ms": pct(jitter, 50), "jitter_p99_ms": pct(jitter, 99),
        "runq_p50_ms": pct(runq, 50), "runq_p99_ms": pct(runq, 99),
        "runq_ticks": int(runq.size),
        "gil_wait_at_start_share": float(np.mean([r["gil_at_start_ms"] > 0 for r in rows])),
        "futex_waits_per_tick": float(np.mean([r["futex_n"] for r in rows])),
        "work_p50_ms": pct(work, 50), "work_p99_ms": pct(work, 99),
        "ticks_over_1ms": int(long_ticks.sum()),
        "futex_share_of_ticks_over_1ms": float(futex[long_ticks].sum() / work[long_ticks].sum())
        if long_ticks.any() else float("nan"),
        "long_waits": {k: {"n": len(v["wait_ms"]), "total_ms": float(np.sum(v["wait_ms"])),
                           "wait_p50_ms": float(np.median(v["wait_ms"])),
                           "wait_max_ms": float(np.max(v["wait_ms"])),
                           "on_cpu_median": float(np.median(v["on_cpu"])),
                           "runnable_median": float(np.median(v["runnable"]))}
                       for k, v in sorted(by.items(), key=lambda kv: -sum(kv[1]["wait_ms"]))},
    }


def report(label: str, result: dict[str, Any], bench: dict[str, Any], args: argparse.Namespace,
           policies: dict[str, str], names: dict[int, str]) -> str:
    loop = bench.get("display_loop", {})
    lines = [f"# What the display loop waits for: run `{label}`", "",
             f"Machine: {host_platform.machine()}, `nproc` {os.cpu_count()}, load average "
             f"{bench.get('load_start', [float('nan')])[0]:.2f} at the start. Command: `python "
             f"benchmarks/trace_display_waits.py --label {label}"
             + (f" --link {args.link}" if args.link else "") + f" --seconds {args.seconds:g}`"
             f" (`teletouch bench cpu --no-profile`, {args.seconds:g} s of scheduler events "
             "from its window; method in the script's docstring).", "",
             f"The demo's own figures over its window: display loop "
             f"{loop.get('rate_hz', float('nan')):.0f} Hz, period jitter p99 "
             f"{loop.get('jitter_p99_ms', float('nan')):.2f} ms; all processes "
             f"{sum(p['cores'] for p in bench.get('processes', {}).values()):.2f} cores.", "",
             "| ticks traced | jitter p50 / p99 ms | timer wake to CPU p50 / p99 ms (ticks "
             "with both events) | ticks "
             "starting with a GIL wait | futex waits per tick | tick work p50 / p99 ms | "
             "ticks working > 1 ms | share of their time in futex waits |",
             "|---|---|---|---|---|---|---|---|",
             f"| {result['ticks']} | {result['jitter_p50_ms']:.3f} / "
             f"{result['jitter_p99_ms']:.3f} | {result['runq_p50_ms']:.3f} / "
             f"{result['runq_p99_ms']:.3f} ({result['runq_ticks']}) | "
             f"{result['gil_wait_at_start_share']:.0%} | "
             f"{result['futex_waits_per_tick']:.2f} | {result['work_p50_ms']:.3f} / "
             f"{result['work_p99_ms']:.3f} | {result['ticks_over_1ms']} | "
             f"{result['futex_share_of_ticks_over_1ms']:.0%} |", "",
             "Waits longer than 0.2 ms (back-to-back futex waits merged: a GIL wait times out "
             "after the switch interval and waits again), by the thread whose release ended "
             "them, and where that thread was during the wait (medians over the waits):", "",
             "| ended by | waits | total ms | wait p50 / max ms | on a CPU | runnable, not "
             "running |",
             "|---|---|---|---|---|---|"]
    for who, d in result["long_waits"].items():
        lines.append(f"| {who} | {d['n']} | {d['total_ms']:.1f} | {d['wait_p50_ms']:.2f} / "
                     f"{d['wait_max_ms']:.2f} | {d['on_cpu_median']:.0%} | "
                     f"{d['runnable_median']:.0%} |")
    lines += ["", "Scheduling policy of the local station's threads during the run: "
              + ", ".join(f"{names.get(int(t), t)} {p}" for t, p in policies.items()) + ".", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the demo under `bench cpu`, trace the display loop, write the results."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--label", required=True)
    parser.add_argument("--link", default=None, help="link-emulator profile (default: none)")
    parser.add_argument("--seconds", type=float, default=6.0, help="traced seconds")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "lab.cli", "bench", "cpu", "--no-profile", "--label",
           args.label, "--out-dir", str(args.out)]
    if args.link:
        cmd += ["--link", args.link]
    bench = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        pid = _local_station(bench.pid, time.monotonic() + 120.0)
        time.sleep(5.0)  # into the demo's measured window (its warm-up is 3 s)
        names, loop_tid = _threads(pid)
        policies = _policies(pid)
        events = record(loop_tid, args.seconds, args.out / f"{args.label}.perf.data")
        bench.wait(timeout=600)
    finally:
        if bench.poll() is None:
            bench.kill()
            bench.wait()
    (args.out / f"{args.label}.perf.data").unlink(missing_ok=True)
    result = analyse(events, loop_tid, names)
    summary = json.loads((args.out / f"cpu-{args.label}.json").read_text())
    (args.out / f"{args.label}.json").write_text(json.dumps(result, indent=1))
    text = report(args.label, result, summary, args, policies, names)
    (args.out / f"{args.label}.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
