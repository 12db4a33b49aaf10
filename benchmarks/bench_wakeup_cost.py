"""What a wake-up costs in CPU on this machine: sleeps and thread hand-overs (issue 12).

The demo's processes switch context some 14,500-15,800 times per second between them
(``teletouch bench cpu`` records it per process since this round). This measures what one
switch costs the thread that makes it, with nothing else to do:

1. ``time.sleep(period)`` in a loop, for periods from 0.2 to 10 ms (a loop at a fixed rate:
   the display loop's 1 ms, the uplink's 4 ms, ...);
2. the same wait in ``epoll`` (what an asyncio event loop does between events);
3. a hand-over between two threads of one interpreter: one sets a ``threading.Event`` every
   ``period``, the other waits for it (a reader thread waking a consumer, with the GIL
   passed between them); both threads' CPU counts, per hand-over.

CPU is the thread's own clock (``time.thread_time``: the kernel's run time of the thread,
which the per-thread ``schedstat`` run time confirms), divided by the iterations; pure work
per iteration is nil, so what is left is the cost of going to sleep and waking up, as this
kernel (a Firecracker guest without IRQ time accounting: interrupt and VM-exit time is
charged to the task that was running or woken) accounts it to the process.

Run:   python benchmarks/bench_wakeup_cost.py [--seconds 0.6] [--rounds 3]
Writes benchmarks/results/wakeup_cost.md.
"""

from __future__ import annotations

import argparse
import os
import platform as host_platform
import select
import statistics
import threading
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PERIODS_MS = (0.2, 0.5, 1.0, 2.0, 4.0, 10.0)


def _per_iteration_us(wait: Callable[[float], object], period_s: float, seconds: float
                      ) -> float:
    n = max(20, int(seconds / period_s))
    t0 = time.thread_time()
    for _ in range(n):
        wait(period_s)
    return (time.thread_time() - t0) / n * 1e6


def _handover_us(period_s: float, seconds: float, sleep_us: float) -> float:
    """CPU of both threads per hand-over: a setter every ``period_s``, a waiter; the
    setter's own sleep (``sleep_us`` per period, measured alone) taken off."""
    n = max(20, int(seconds / period_s))
    ready, stop = threading.Event(), threading.Event()
    cpu = {"waiter": 0.0}

    def waiter() -> None:
        t0 = time.thread_time()
        while not stop.is_set():
            if ready.wait(1.0):
                ready.clear()
        cpu["waiter"] = time.thread_time() - t0

    thread = threading.Thread(target=waiter)
    thread.start()
    t0 = time.thread_time()
    for _ in range(n):
        time.sleep(period_s)
        ready.set()
    setter = time.thread_time() - t0
    stop.set()
    ready.set()
    thread.join()
    return (setter + cpu["waiter"]) / n * 1e6 - sleep_us


def main(argv: list[str] | None = None) -> int:
    """Measure and write the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=0.6, help="per cell and round")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results"
                        / "wakeup_cost.md")
    args = parser.parse_args(argv)
    ep = select.epoll()
    rows = []
    for period_ms in PERIODS_MS:
        p = period_ms / 1e3
        cells: dict[str, list[float]] = {"sleep": [], "epoll": [], "handover": []}
        for _ in range(args.rounds):
            cells["sleep"].append(_per_iteration_us(time.sleep, p, args.seconds))
            cells["epoll"].append(_per_iteration_us(ep.poll, p, args.seconds))
            cells["handover"].append(_handover_us(p, args.seconds, cells["sleep"][-1]))
        med = {k: statistics.median(v) for k, v in cells.items()}
        rows.append((period_ms, med, {k: (min(v), max(v)) for k, v in cells.items()}))
        print(f"{period_ms:g} ms: " + ", ".join(f"{k} {v:.1f} us" for k, v in med.items()),
              flush=True)
    lines = ["# What a wake-up costs in CPU on this machine (issue 12)", "",
             f"Machine: {host_platform.machine()}, `nproc` {os.cpu_count()}, kernel "
             f"{host_platform.release()}; Python {host_platform.python_version()}; load "
             f"average {os.getloadavg()[0]:.2f} at the end. Command: `python benchmarks/"
             f"bench_wakeup_cost.py --seconds {args.seconds:g} --rounds {args.rounds}`. "
             "CPU per iteration in us (thread CPU clock), median of the rounds (range); the "
             "loops do no work, so this is the cost of sleeping and waking alone. "
             "`handover`: one thread sets an event every period, another waits for it: "
             "both threads' CPU per hand-over, the setter's own sleep taken off.", "",
             "| period ms | time.sleep | epoll | thread hand-over | at this rate: cores "
             "per sleeping loop |", "|---|---|---|---|---|"]
    for period_ms, med, rng in rows:
        lines.append(
            f"| {period_ms:g} | " + " | ".join(
                f"{med[k]:.1f} ({rng[k][0]:.1f}-{rng[k][1]:.1f})"
                for k in ("sleep", "epoll", "handover"))
            + f" | {med['sleep'] / (period_ms * 1e3):.3f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
