"""Fuzz the decoder, the session cores and the relay; write benchmarks/results/fuzz.md.

Targets (``lab.fuzz``): ``decoder``, ``framing``, ``station``, ``peer``, ``relay``. Engines:

* ``atheris``: coverage-guided (libFuzzer), one subprocess per target
  (``python -m lab.fuzz.atheris_main``), seeded with real encoded messages of every type;
  reports libFuzzer's coverage (``cov``: edges, ``ft``: features) and stops at the first crash;
* ``builtin``: the coverage-less mutation engine of ``lab.fuzz.engine`` (in this process),
  which goes on after a crash and counts crash buckets.

Then (unless ``--no-smoke``) fuzzed frames over real TCP and WebSocket sockets to a relay
subprocess, which must still serve a good session afterwards.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lab.child import module_argv

__all__ = ["AtherisResult", "configure_parser", "run", "run_atheris"]

_TARGETS = ("decoder", "framing", "station", "peer", "relay")
_MAX_LEN = {"decoder": 9000, "framing": 4096}  # session scripts: 4096 (the seeds: < 2.8 KB)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Flags of ``teletouch bench fuzz``."""
    parser.add_argument("--inputs", type=int, default=100_000,
                        help="inputs per target and engine (default 100000)")
    parser.add_argument("--targets", nargs="+", choices=_TARGETS, default=list(_TARGETS),
                        help="targets, run in this order (default: all)")
    parser.add_argument("--engine", choices=("atheris", "builtin", "both"), default="atheris",
                        help="atheris (coverage-guided, default), builtin (coverage-less) "
                             "or both")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--max-seconds", type=int, default=None,
                        help="stop each atheris target after this long (libFuzzer "
                             "-max_total_time); the table shows the inputs actually run")
    parser.add_argument("--jobs", type=int, default=1,
                        help="atheris processes at once (default 1)")
    parser.add_argument("--smoke-connections", type=int, default=300,
                        help="fuzz connections to the real relay process (default 300)")
    parser.add_argument("--no-smoke", action="store_true", help="skip the real-socket run")
    parser.add_argument("--write-results", metavar="DIR", default=None,
                        help="write fuzz.md to DIR")


@dataclass
class AtherisResult:
    """One atheris process: libFuzzer's final statistics, or its crash report."""

    target: str
    inputs: int = 0
    cov: int | None = None
    ft: int | None = None
    corpus: int | None = None
    seconds: float = 0.0
    peak_rss_mb: int | None = None
    crash: str | None = None  # the tail of the report (traceback) when it stopped on one
    returncode: int = 0
    extra: dict[str, Any] = field(default_factory=dict)


def _start_atheris(target: str, inputs: int, seed: int, workdir: Path,
                   max_seconds: int | None = None) -> tuple[subprocess.Popen[str], float]:
    from lab.fuzz.engine import seeds_for

    corpus = workdir / target
    corpus.mkdir(parents=True)
    for i, data in enumerate(seeds_for(target)):
        (corpus / f"seed{i:03d}").write_bytes(data)
    cmd = [*module_argv("lab.fuzz.atheris_main"), target, f"-runs={inputs}",
           f"-seed={seed}", "-timeout=20", "-rss_limit_mb=2048",
           f"-max_len={_MAX_LEN.get(target, 4096)}", "-print_final_stats=1",
           f"-artifact_prefix={workdir}/{target}-", str(corpus)]
    if max_seconds:
        cmd.insert(-1, f"-max_total_time={max_seconds}")
    # libFuzzer's log goes to a file: a pipe that nobody reads while another target is
    # awaited fills up and stalls the process
    with open(workdir / f"{target}.log", "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, text=True,
                                cwd=Path(__file__).resolve().parents[2])
    return proc, time.perf_counter()


def _parse_atheris(target: str, output: str, returncode: int, seconds: float
                   ) -> AtherisResult:
    res = AtherisResult(target, seconds=seconds, returncode=returncode)
    stats = dict(re.findall(r"^stat::(\w+):\s+(\d+)", output, re.M))
    res.inputs = int(stats.get("number_of_executed_units", 0))
    if "peak_rss_mb" in stats:
        res.peak_rss_mb = int(stats["peak_rss_mb"])
    lines = re.findall(r"^#(\d+)\s+\w+\s+cov: (\d+) ft: (\d+) corp: (\d+)", output, re.M)
    if lines:
        last = lines[-1]
        res.cov, res.ft, res.corpus = int(last[1]), int(last[2]), int(last[3])
        res.inputs = res.inputs or int(last[0])
    if returncode != 0 or "ERROR: libFuzzer" in output or "Uncaught Python exception" in output:
        start = output.find("=== Uncaught Python exception")
        res.crash = output[start if start >= 0 else -3000:][:3000]
    return res


def run_atheris(targets: list[str], inputs: int, seed: int, jobs: int = 1,
                max_seconds: int | None = None) -> list[AtherisResult]:
    """Run atheris over each target (``jobs`` processes at once)."""
    results: dict[str, AtherisResult] = {}
    with tempfile.TemporaryDirectory(prefix="teletouch-fuzz-") as tmp:
        waiting = list(targets)
        running: list[tuple[str, subprocess.Popen[str], float]] = []
        while waiting or running:
            while waiting and len(running) < max(1, jobs):
                t = waiting.pop(0)
                running.append((t, *_start_atheris(t, inputs, seed, Path(tmp), max_seconds)))
            done = [r for r in running if r[1].poll() is not None]
            if not done:
                time.sleep(0.5)
                continue
            t, proc, t0 = done[0]
            running.remove(done[0])
            out = (Path(tmp) / f"{t}.log").read_text(errors="replace")
            results[t] = _parse_atheris(t, out, proc.returncode, time.perf_counter() - t0)
            print(f"atheris {t}: {results[t].inputs} inputs, cov {results[t].cov}, "
                  f"{'CRASH' if results[t].crash else 'no crash'}, "
                  f"{results[t].seconds:.0f} s", file=sys.stderr, flush=True)
    return [results[t] for t in targets]


def run(args: argparse.Namespace) -> int:
    """Run the fuzzers, print a summary, write the results file."""
    from lab.bench.results import write_results
    from lab.fuzz.engine import EngineResult, run_engine
    from lab.fuzz.registry import TARGETS
    from lab.fuzz.smoke import SmokeResult, run_smoke

    load = os.getloadavg()
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    t_start = time.perf_counter()
    ath: list[AtherisResult] = []
    builtin: list[EngineResult] = []
    if args.engine in ("atheris", "both"):
        ath = run_atheris(args.targets, args.inputs, args.seed, args.jobs, args.max_seconds)
    if args.engine in ("builtin", "both"):
        for t in args.targets:
            r = run_engine(t, TARGETS[t], args.inputs, seed=args.seed)
            print(f"builtin {t}: {r.inputs} inputs, {r.crash_count} crashes, {r.hangs} hangs, "
                  f"{r.seconds:.0f} s", file=sys.stderr, flush=True)
            builtin.append(r)
    smoke: SmokeResult | None = None
    if not args.no_smoke:
        smoke = run_smoke(args.smoke_connections, seed=args.seed)
        print(f"smoke: {smoke.connections} connections, passed={smoke.passed}",
              file=sys.stderr, flush=True)
    text = _report(args, ath, builtin, smoke, load, started, time.perf_counter() - t_start)
    print(text)
    if args.write_results:
        write_results(args.write_results, "fuzz", text)
    failed = (any(r.crash for r in ath) or any(r.crash_count or r.hangs for r in builtin)
              or (smoke is not None and not smoke.passed))
    return 1 if failed else 0


def _argv(args: argparse.Namespace) -> str:
    parts = ["teletouch bench fuzz", f"--inputs {args.inputs}", f"--engine {args.engine}",
             f"--seed {args.seed}"]
    if args.targets != list(_TARGETS):
        parts.append("--targets " + " ".join(args.targets))
    if args.jobs != 1:
        parts.append(f"--jobs {args.jobs}")
    if args.max_seconds:
        parts.append(f"--max-seconds {args.max_seconds}")
    if args.no_smoke:
        parts.append("--no-smoke")
    else:
        parts.append(f"--smoke-connections {args.smoke_connections}")
    if args.write_results:
        parts.append(f"--write-results {os.path.relpath(args.write_results)}")
    return " ".join(parts)


def _report(args: argparse.Namespace, ath: list[AtherisResult], builtin: list[Any],
            smoke: Any, load: tuple[float, float, float], started: str, seconds: float) -> str:
    lines = ["# Fuzzing: decoder, session cores, relay", "",
             f"Command: `{_argv(args)}`  ", f"Started {started}; {seconds:.0f} s in all.  ",
             f"Machine: `nproc` = {os.cpu_count()}, load average {load[0]:.1f} / {load[1]:.1f}"
             f" / {load[2]:.1f} at the start (other jobs may share the machine: rates are "
             "indicative only).", "",
             "Targets (`lab/fuzz/`): `decoder` (one message, oracle: the doc's envelope rules, "
             "re-encode round trip, forwarding hops), `framing` (TCP length prefix in chunks "
             "of any size, against a reference parser), `station` (StationSession: welcome, "
             "refusals, pongs, liveness, queues), `peer` (relay-side PeerSession against a "
             "model written from docs/protocol.md §3/§6: every answer, in order, and the "
             "close code), `relay` (four connections through the relay's token check, session "
             "pairing and routing: roles, forwarding, no_peer/queue_full seq, stats, `lost`). "
             "Error codes, close codes and fatality come from the §6 table of "
             "docs/protocol.md, parsed at run time.", ""]
    if ath:
        lines += ["## atheris (coverage-guided, libFuzzer)", "",
                  "| target | inputs | crashes | cov (edges) | ft (features) | corpus | time s |"
                  " inputs/s | peak RSS MB |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in ath:
            rate = r.inputs / r.seconds if r.seconds else 0.0
            lines.append(f"| {r.target} | {r.inputs:,} | {1 if r.crash else 0} | {r.cov} | "
                         f"{r.ft} | {r.corpus} | {r.seconds:.0f} | {rate:.0f} | "
                         f"{r.peak_rss_mb} |")
        lines.append("")
        lines.append("libFuzzer stops at the first crash, so a crash row has fewer inputs. "
                     "`cov` counts the instrumented branch edges of `shared` and "
                     "`relay_server` reached (plus libFuzzer's own counters).")
        for r in ath:
            if r.crash:
                lines += ["", f"### atheris crash: {r.target}", "", "```", r.crash.strip(),
                          "```"]
        lines.append("")
    if builtin:
        lines += ["## builtin mutation engine (coverage-less)", "",
                  "| target | inputs | crashes | crash buckets | hangs | slowest input s | "
                  "time s | inputs/s |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in builtin:
            rate = r.inputs / r.seconds if r.seconds else 0.0
            lines.append(f"| {r.target} | {r.inputs:,} | {r.crash_count} | {len(r.crashes)} | "
                         f"{r.hangs} | {r.slowest_s:.3f} | {r.seconds:.0f} | {rate:.0f} |")
        for r in builtin:
            for c in r.crashes.values():
                lines += ["", f"### builtin crash: {r.target}: {c.bucket} ({c.count}x)", "",
                          "```", c.traceback.strip()[-2000:], "```"]
        lines.append("")
    if smoke is not None:
        lines += ["## Real sockets: relay subprocess, TCP and WebSocket", "",
                  f"{smoke.connections} connections (half TCP, half WebSocket; 70% with a valid "
                  f"hello first), {smoke.frames_sent} fuzzed frames, {smoke.answers} messages "
                  f"answered, in {smoke.seconds:.0f} s.  ",
                  "Error codes answered (transport:code): " + (", ".join(
                      f"`{k}` {v}" for k, v in sorted(smoke.error_codes.items())) or "none")
                  + ".  ",
                  f"Relay process alive afterwards: {smoke.relay_alive}; a good session "
                  f"(local TCP + remote WebSocket, one platform_state forwarded): "
                  f"{smoke.good_session}; `GET /status` 200: {smoke.status_ok}; traceback or "
                  f"ERROR lines in the relay log: {len(smoke.relay_log_errors)}.", ""]
        lines += [f"    {line}" for line in smoke.relay_log_errors[:20]]
    return "\n".join(lines).rstrip() + "\n"
