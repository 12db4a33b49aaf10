"""CPU of the demo's link emulator process(es), two checkouts alternately.

Runs ``teletouch demo --headless --json --no-view --link PROFILE`` from each checkout and
samples, every 0.5 s, the CPU time (utime + stime, /proc/PID/stat) of every process whose
command line is ``... lab.cli ... link ...``; the last sample of each such process is its CPU
over the session (the sampler misses at most the last 0.5 s). Prints, per run, the number of
emulator processes, their CPU seconds and the demo's wall time.

Run: ``python benchmarks/bench_link_cpu.py --before ../m2t-base --after . --rounds 2``
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

TICK = os.sysconf("SC_CLK_TCK")


def _link_cpu() -> dict[int, float]:
    out: dict[int, float] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
            if b"lab.cli" not in argv or b"link" not in argv:
                continue
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            out[int(entry)] = (int(fields[11]) + int(fields[12])) / TICK
        except (OSError, ValueError, IndexError):
            continue
    return out


def run(root: Path, profile: str) -> tuple[int, float, float, float]:
    cmd = [str(root / ".venv" / "bin" / "teletouch"), "--log-level", "WARNING", "demo",
           "--headless", "--json", "--no-view", "--link", profile]
    load = os.getloadavg()[0]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    seen: dict[int, float] = {}
    while proc.poll() is None:
        seen.update(_link_cpu())
        time.sleep(0.5)
    if proc.returncode != 0:
        raise SystemExit(f"demo in {root} failed with {proc.returncode}")
    return len(seen), sum(seen.values()), time.monotonic() - t0, load


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", type=Path, required=True)
    parser.add_argument("--after", type=Path, default=Path("."))
    parser.add_argument("--profile", default="city-1000km")
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    sides = {"before": args.before.resolve(), "after": args.after.resolve()}
    print(f"nproc {os.cpu_count()}, load average {os.getloadavg()[0]:.1f} at the start")
    print("| round | side | emulator processes | emulator CPU s | demo wall s | "
          "CPU / wall | load at start |")
    print("|---|---|---|---|---|---|---|")
    for i in range(args.rounds):
        for side in (("before", "after") if i % 2 == 0 else ("after", "before")):
            n, cpu, wall, load = run(sides[side], args.profile)
            print(f"| {i + 1} | {side} | {n} | {cpu:.2f} | {wall:.0f} | {cpu / wall:.3f} | "
                  f"{load:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
