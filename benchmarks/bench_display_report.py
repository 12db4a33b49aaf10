"""What the display process's reporter costs, and whether it disturbs the 1 kHz loop.

The display process (``local_site/agent/display_child.py``) runs the display loop on one
thread and, on another, sends the station a report every ``HEARTBEAT_S`` (20 ms): the new
loop periods, the counters, the pins' state, the board's feedback, the pins samples for the
recorder. Both threads share the process's GIL (switch interval 0.2 ms, as the child sets it).

Each run is a fresh process built as the child builds itself: the simulated board in-process
on the virtual CAN FD bus, the renderer, a local scene (``hemisphere``) under a platform that
moves on a circle and up and down, the pins sampled for a recorder at 50 Hz, the loop thread
at ``SCHED_FIFO`` 10 where allowed (the default), and the report's socket read by another
process, as the station reads it. Two modes, alternating each round:

- ``report``: the reporter thread as in the child (``_Reporter.run``);
- ``none``: no reporter (the loop's jitter without it).

Per run, over ``--seconds`` after a 1 s warm-up: the loop's rate and period jitter
(``|period - 1 ms|``: p50, p99, p99.9), the process's CPU, and (``report``) the thread CPU of
each report sent in the window as the child sends it, 20 ms after the previous one, its
thread asleep meanwhile. After the window, with the loop still running, 200 more reports
also go 20 ms apart (so each carries as much as before) but the thread spins meanwhile
instead of sleeping: its core stays on this thread's work, and the difference is roughly
what the sleep costs each report in caches and branch predictors. (The spinning thread takes
the GIL from the loop for up to a switch interval each tick; only the report's CPU is read
then.)

Limits: a local scene, so no tactile frames arrive and the reports carry no accepted frames
and no rendered frames' stamps, which the demo's do: its reports are somewhat larger.

Run: ``python benchmarks/bench_display_report.py --rounds 6 --out
benchmarks/results/display_report``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

MODES = ("report", "none")
SPUN_REPORTS = 200


def _measure(mode: str, seconds: float) -> dict[str, Any]:
    """One run in this process (see the module docstring)."""
    import numpy as np

    from local_site.agent.config import LocalAgentConfig
    from local_site.agent.display_child import _PinsTap, _Reporter, _TappedLedger
    from local_site.agent.display_loop import DisplayLoop
    from local_site.agent.display_process import HEARTBEAT_S
    from local_site.devices import open_display
    from local_site.platform.base import PlatformSample
    from local_site.render import Renderer, RendererConfig
    from local_site.scenes import open_scene
    from shared.gil import switch_interval
    from shared.timebase import now_us

    config = LocalAgentConfig()
    t0 = time.monotonic()

    def position() -> PlatformSample:
        t = time.monotonic() - t0
        return PlatformSample((30.0 + 10.0 * math.sin(t), 30.0 + 10.0 * math.cos(t),
                               2.0 + math.sin(3.0 * t)), (0.0, 0.0, 0.0), now_us(), 1, 1)

    display = open_display("sim", connect=False)
    ledger = _TappedLedger()
    pins = _PinsTap(config.record_pins_rate_hz)
    loop = DisplayLoop(display, Renderer(RendererConfig()),
                       open_scene("hemisphere", interpolation_order=1), positions=position,
                       platform_ok=lambda: True, ledger=ledger, recorder=pins)
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    reader = subprocess.Popen(
        [sys.executable, "-c", "import socket, sys\n"
         "s = socket.socket(fileno=int(sys.argv[1]))\nwhile s.recv(1 << 20): pass",
         str(theirs.fileno())], pass_fds=[theirs.fileno()])
    theirs.close()
    reporter = _Reporter(loop, ledger, ours, None, pins)
    stop = threading.Event()  # the loop's
    stop_reporting = threading.Event()  # the reporter thread's (the loop runs on after it)
    paced_ns: list[int] = []

    def report() -> None:  # _Reporter.run, timed
        while not stop_reporting.wait(HEARTBEAT_S):
            start = time.thread_time_ns()
            reporter.send()
            paced_ns.append(time.thread_time_ns() - start)

    spun_ns: list[int] = []
    with switch_interval(config.gil_switch_interval_s):
        thread = threading.Thread(target=loop.run_in_thread,
                                  args=(stop, 0, config.display_thread_realtime), daemon=True)
        thread.start()
        if mode == "report":
            threading.Thread(target=report, daemon=True).start()
        time.sleep(1.0)
        paced_ns.clear()  # the window's reports only
        recorded = loop.periods.recorded
        cpu0, wall0 = time.process_time(), time.monotonic()
        time.sleep(seconds)
        cpu1, wall1 = time.process_time(), time.monotonic()
        _, periods = loop.periods.since(recorded)
        reports = len(paced_ns)
        if mode == "report":
            stop_reporting.set()  # the reporter thread ends; the loop goes on for the spun
            time.sleep(2 * HEARTBEAT_S)
            due = time.perf_counter()
            for _ in range(SPUN_REPORTS):
                due += HEARTBEAT_S
                while time.perf_counter() < due:
                    pass
                start = time.thread_time_ns()
                reporter.send()
                spun_ns.append(time.thread_time_ns() - start)
            assert thread.is_alive(), "the loop stopped before the spun reports"
        stop.set()
        thread.join()
    ours.close()
    reader.wait()
    jitter_ms = np.abs(periods - loop.period_s) * 1e3
    out: dict[str, Any] = {
        "mode": mode, "periods": int(periods.size),
        "rate_hz": float(periods.size / periods.sum()),
        "jitter_p50_ms": float(np.percentile(jitter_ms, 50)),
        "jitter_p99_ms": float(np.percentile(jitter_ms, 99)),
        "jitter_p999_ms": float(np.percentile(jitter_ms, 99.9)),
        "cores": (cpu1 - cpu0) / (wall1 - wall0),
        "realtime": loop.realtime_applied, "reports": reports}
    if paced_ns:
        out.update(report_us_p50=float(np.percentile(paced_ns[:reports], 50)) / 1e3,
                   report_us_p90=float(np.percentile(paced_ns[:reports], 90)) / 1e3,
                   spun_report_us_p50=float(np.percentile(spun_ns, 50)) / 1e3)
    return out


def _child(mode: str, seconds: float) -> dict[str, Any]:
    done = subprocess.run([sys.executable, __file__, "--run", mode, "--seconds", str(seconds)],
                          capture_output=True, text=True, check=False, cwd=ROOT)
    if done.returncode != 0:
        raise SystemExit(f"a {mode} run failed:\n{done.stderr[-2000:]}")
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    result["load_1min"] = os.getloadavg()[0]
    return result


def _fmt(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _table(runs: list[dict[str, Any]]) -> str:
    head = ("| round | mode | load | loop Hz | jitter p50 ms | p99 ms | p99.9 ms | process cores "
            "| report CPU us p50 (p90), 20 ms apart, asleep between | spinning between, p50 |")
    lines = [head, "|" + "---|" * 10]
    for run in runs:
        paced = (f"{run['report_us_p50']:.0f} ({run['report_us_p90']:.0f})"
                 if "report_us_p50" in run else "-")
        lines.append(
            f"| {run['round']} | {run['mode']} | {run['load_1min']:.2f} | {run['rate_hz']:.1f} | "
            f"{run['jitter_p50_ms']:.3f} | {run['jitter_p99_ms']:.3f} | "
            f"{run['jitter_p999_ms']:.3f} | {run['cores']:.3f} | {paced} | "
            f"{_fmt(run.get('spun_report_us_p50'), 0)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from benchmarks.cli_args import count, positive

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", choices=MODES, help=argparse.SUPPRESS)
    parser.add_argument("--seconds", type=positive, default=8.0,
                        help="measured window per run (default 8)")
    parser.add_argument("--rounds", type=count, default=4,
                        help="rounds; each runs both modes, the order alternating (default 4)")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results"
                        / "display_report", help="directory for report.md and runs.json")
    args = parser.parse_args(argv)
    if args.run is not None:
        print(json.dumps(_measure(args.run, args.seconds)))
        return 0
    runs = []
    for r in range(1, args.rounds + 1):
        for mode in (MODES if r % 2 else MODES[::-1]):
            run = _child(mode, args.seconds)
            run["round"] = r
            runs.append(run)
            print(json.dumps(run), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "runs.json").write_text(json.dumps(runs, indent=1) + "\n")
    (args.out / "report.md").write_text(
        "# The display process's reporter: its CPU and the loop's jitter\n\n"
        f"`{' '.join(['python', 'benchmarks/bench_display_report.py', *sys.argv[1:]])}` "
        f"({args.rounds} rounds of {args.seconds:g} s per mode, order alternating; method in "
        "the benchmark's docstring)\n\n" + _table(runs) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
