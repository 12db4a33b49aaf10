"""Paired before/after run: relay latency and throughput, demo motion-to-touch, two checkouts.

A change that must not make the system slower is judged on a *paired* run: the two checkouts
(each with its own ``.venv``, e.g. a ``git worktree`` of the base commit beside this one)
run the same jobs alternately on the same machine in the same minutes, so machine load
affects both sides alike. The order within a pair alternates (ABBA...) to cancel drift.

Per pair and side:

* ``teletouch bench relay --json --sessions 1 5`` (short phases): added p50/p99 over a
  direct WebSocket path, relay residence p99, forwarded messages per second;
* ``teletouch demo --headless --json --link city-1000km``: motion-to-touch end-to-end
  p50/p99 as the local station measured it.

The report gives each side's median over the pairs and the after/before ratio of the medians.

Run: ``python benchmarks/bench_paired.py --before ../base --after . --pairs 3``
(writes ``benchmarks/results/paired.md`` unless ``--no-write``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"

#: metric name -> (job, path into the job's JSON)
METRICS: dict[str, tuple[str, tuple[str, ...]]] = {
    "relay added p50, 1 session (us)": ("relay", ("added_latency_us_by_sessions", "1", "p50")),
    "relay added p99, 1 session (us)": ("relay", ("added_latency_us_by_sessions", "1", "p99")),
    "relay added p99, 5 sessions (us)": ("relay", ("added_latency_us_by_sessions", "5", "p99")),
    "relay residence p99, 5 sessions (us)": ("relay",
                                             ("relay_residence_us_by_sessions", "5", "p99")),
    "relay forwarded msgs/s": ("relay", ("throughput_msgs_per_s",)),
    "demo motion-to-touch p50 (ms)": ("demo", ("latency_ms", "end_to_end", "p50")),
    "demo motion-to-touch p99 (ms)": ("demo", ("latency_ms", "end_to_end", "p99")),
}


def _job(root: Path, job: str, demo_duration_s: float) -> dict[str, Any]:
    exe = root / ".venv" / "bin" / "teletouch"
    if job == "relay":
        cmd = [str(exe), "--log-level", "WARNING", "bench", "relay", "--json",
               "--sessions", "1", "5", "--duration-s", "3"]
    else:
        cmd = [str(exe), "--log-level", "WARNING", "demo", "--headless", "--json",
               "--link", "city-1000km", "--duration", f"{demo_duration_s:g}"]
    proc = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=900,
                          check=False)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} (in {root}) failed with {proc.returncode}:\n"
                         f"{proc.stderr[-2000:]}")
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]))


def _get(data: dict[str, Any], path: tuple[str, ...]) -> float | None:
    value: Any = data
    for key in path:
        if not isinstance(value, dict) or key not in value:
            return None
        value = value[key]
    return None if value is None else float(value)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", type=Path, required=True, help="checkout before the change")
    parser.add_argument("--after", type=Path, required=True, help="checkout after the change")
    parser.add_argument("--pairs", type=int, default=3, help="before/after pairs (default 3)")
    parser.add_argument("--demo-duration-s", type=float, default=40.0)
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args()
    sides = {"before": args.before.resolve(), "after": args.after.resolve()}
    values: dict[str, dict[str, list[float]]] = {s: {m: [] for m in METRICS} for s in sides}
    for i in range(args.pairs):
        order = ["before", "after"] if i % 2 == 0 else ["after", "before"]
        for side in order:
            for job in ("relay", "demo"):
                data = _job(sides[side], job, args.demo_duration_s)
                for name, (metric_job, path) in METRICS.items():
                    v = _get(data, path) if metric_job == job else None
                    if v is not None:
                        values[side][name].append(v)
            print(f"pair {i + 1}/{args.pairs} {side} done", file=sys.stderr)
    lines = [
        "# Paired before/after run",
        "",
        f"Command: `python benchmarks/bench_paired.py --before {os.path.relpath(sides['before'])}"
        f" --after {os.path.relpath(sides['after'])} --pairs {args.pairs}`",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores shared with other jobs, "
        f"Python {platform.python_version()}; load average {os.getloadavg()[0]:.1f} at the end. "
        f"{args.pairs} pairs, order alternating; each figure is the median over the pairs.",
        "",
        "| metric | before | after | after / before |",
        "|---|---|---|---|",
    ]
    for name in METRICS:
        b, a = values["before"][name], values["after"][name]
        if not b or not a:
            lines.append(f"| {name} | - | - | - |")
            continue
        mb, ma = statistics.median(b), statistics.median(a)
        ratio = f"{ma / mb:.2f}" if mb else "-"
        lines.append(f"| {name} | {mb:.1f} | {ma:.1f} | {ratio} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.no_write:
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / "paired.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
