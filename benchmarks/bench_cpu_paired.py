"""`teletouch bench cpu` for several sides in the same minutes, per link profile: paired runs.

A *side* is a checkout with its own ``.venv`` (e.g. a ``git worktree`` of the base commit
beside this one) and, optionally, extra flags for the remote station (a setting to compare
on the same code). Per round and profile every side runs once (``teletouch bench cpu
--no-profile --link P``); the order of the sides reverses every round (ABBA...) so that the
machine's load hits all alike. ``--burners N`` runs N CPU-bound processes beside every run
(``--burner-nice K``: at nice K; they share the demo's scheduling group, so this is not how
a deployed station's nice would work under autogroup: docs/speed.md section 34).
``--cgroups`` puts the burners in a CPU group of their own at weight 100 (systemd's default
``CPUWeight=``) and each side's runs in another, at the side's ``cgroup:W`` flag (default
100), with a real-time budget for the display loop's ``SCHED_FIFO`` thread: how a deployment
ranks the stations above other jobs (``lab/bench/cgroups.py``; needs root and cgroup v1's
``cpu`` controller).

Per run the table keeps what issue 12's targets are about: all processes' cores, the local
and remote stations' cores, the remote's achieved frame rate, the display loop's rate and
period jitter p99 (``fps`` is the session's average, idle stretches included;
``period_p50`` the remote's median frame period in ms, the rate while commands flow),
motion-to-touch end to end (p50 / p99; ``cap_p99``: the p99 from the sample the frame answers,
``from_capture``, where the side reports it) and its ``arm_and_sensor`` stage,
and the remote's wait from a command to the capture that answers it (``arm_command_to_capture``
in its summary, where the side reports it). ``switches`` is the context switches per second
of all processes (where the side's ``bench cpu`` records them): wake-ups and preemptions, each
worth tens of us of CPU on this machine (``benchmarks/bench_wakeup_cost.py``). ``wait``:
all threads' time on a run queue per second, i.e. the mean number waiting to run
(``schedstat``; where the side records it). ``replaced``:
the tactile frames the local station's hand-overs to its display loop replaced before the
pins showed them, over the whole session (where the side records it). ``steal``: the
cores the host took from this machine's CPUs over the window (``/proc/stat``; where the
side records it). ``ref_us`` and ``mem_gbs``: the machine's own speed just before and after
the demo (``reference_speed`` in ``lab/bench/cpu_impl.py``: CPU us of a fixed interpreter
loop, GB/s of an array pass larger than the caches; the mean of the two; where the side
records it). Then the
medians per side and profile, and each side's median ratio to the first side over the pairs.

Run: ``python benchmarks/bench_cpu_paired.py --side base=../m2t-base --side new=. --link lan
--link city-1000km --rounds 3 --out benchmarks/results/DIR`` (``--report-only`` rebuilds
``DIR/README.md``'s table from the saved runs; ``--side NAME=ROOT::--flag::value`` passes
remote flags, separated by ``::``, ``local:--flag=value`` a flag of the local station and
``bench:--flag=value`` one of ``bench cpu`` itself, e.g. ``bench:--display=sim``, and
``cgroup:W`` the side's CPU weight under ``--cgroups``).
``local`` counts the local station with its child processes (platform reader, display loop).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lab.bench.cgroups import DEFAULT_WEIGHT, CpuGroups
from lab.bench.cpu_report import reference_values, waiting_threads
from lab.bench.results import median_known

#: (column, unit format) per run
COLUMNS = ("load", "cores", "local", "remote", "switches", "wait", "fps", "period_p50", "loop_hz",
           "jitter_p99",
           "m2t_p50", "m2t_p99", "cap_p99", "arm_sensor_p50", "arm_sensor_p99",
           "cmd_to_capture_p50", "replaced", "steal", "ref_us", "mem_gbs")


def _side(text: str) -> tuple[str, Path, list[str]]:
    name, _, rest = text.partition("=")
    root, *flags = rest.split("::")
    if not name or not root:
        raise argparse.ArgumentTypeError(f"--side NAME=ROOT[::FLAG...], got {text!r}")
    return name, Path(root).resolve(), flags


def side_weight(flags: list[str]) -> int:
    """The side's CPU weight under ``--cgroups`` (its ``cgroup:W`` flag; default 100)."""
    weights = [int(f.removeprefix("cgroup:")) for f in flags if f.startswith("cgroup:")]
    return weights[-1] if weights else DEFAULT_WEIGHT


def _run(name: str, root: Path, flags: list[str], link: str, label: str, out: Path,
         preexec: Callable[[], None] | None = None) -> None:
    cmd = [str(root / ".venv" / "bin" / "teletouch"), "bench", "cpu", "--no-profile",
           "--label", label, "--out-dir", str(out)]
    if link != "none":  # none: the stations straight to the relay
        cmd += ["--link", link]
    for flag in flags:
        if flag.startswith("cgroup:"):  # the side's CPU weight: applied by preexec
            continue
        if flag.startswith("bench:"):  # an option of `bench cpu` itself, e.g. --display=sim
            cmd.append(flag.removeprefix("bench:"))
        elif flag.startswith("local:"):
            cmd.append(f"--local-arg={flag.removeprefix('local:')}")
        else:
            cmd.append(f"--remote-arg={flag}")
    # a session of its own: on a timeout the whole run (stations, relay, links) is killed,
    # so that nothing is left running, nor in a CPU group that is to be removed
    proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, preexec_fn=preexec)
    try:
        _out, err = proc.communicate(timeout=900)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _out, err = proc.communicate()
        err += "\n(killed after 900 s)"
    if proc.returncode != 0:
        print(f"{label}: exit {proc.returncode}: {err[-800:]}", file=sys.stderr)


def figures(path: Path) -> dict[str, float | None]:
    """One run's row (None where the run does not report the figure)."""
    run = json.loads(path.read_text())
    lat, procs = run.get("latency_ms") or {}, run.get("processes") or {}
    remote_lat = run.get("remote_latency_ms") or {}

    def pick(table: dict[str, Any], stage: str, q: str) -> float | None:
        value = (table.get(stage) or {}).get(q)
        return None if value is None else float(value)

    return {
        "load": float(run["load_start"][0]),
        "cores": sum(p["cores"] for p in procs.values()),
        # the local station with its child processes (platform reader, display loop)
        "local": sum(procs.get(name, {}).get("cores") or 0.0
                     for name in ("local", "platform", "display")) or None,
        "remote": procs.get("remote", {}).get("cores"),
        "switches": (sum(p["switches_per_s"] for p in procs.values())
                     if procs and all("switches_per_s" in p for p in procs.values()) else None),
        "wait": waiting_threads(run) if procs else None,
        "fps": (run.get("remote_frames") or {}).get("achieved_fps"),
        "period_p50": pick(remote_lat, "frame_period", "p50"),
        "loop_hz": (run.get("display_loop") or {}).get("rate_hz"),
        "jitter_p99": (run.get("display_loop") or {}).get("jitter_p99_ms"),
        "m2t_p50": pick(lat, "end_to_end", "p50"), "m2t_p99": pick(lat, "end_to_end", "p99"),
        "cap_p99": pick(lat, "from_capture", "p99"),
        "arm_sensor_p50": pick(lat, "arm_and_sensor", "p50"),
        "arm_sensor_p99": pick(lat, "arm_and_sensor", "p99"),
        "cmd_to_capture_p50": pick(remote_lat, "arm_command_to_capture", "p50"),
        "replaced": run.get("local_frames_superseded"),
        "steal": (run.get("host") or {}).get("steal_cores"),
        # the machine's speed just before and after the demo (``reference_speed``), mean
        "ref_us": _reference(run, "python_us"), "mem_gbs": _reference(run, "memory_gb_s"),
    }


def _reference(run: dict[str, Any], key: str) -> float | None:
    known = [v for v in reference_values(run, key) if v is not None]
    return sum(known) / len(known) if known else None


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}" if abs(value) < 10 else f"{value:.1f}"


def run_prefix(burners: int, burner_nice: int = 0, cgroups: bool = False) -> str:
    """The label prefix of runs beside ``burners`` CPU burners at nice ``burner_nice``
    (``cg``: each in a CPU group of its own)."""
    groups = "cg" if cgroups else ""
    if not burners:
        return f"{groups}-" if groups else ""
    return f"b{burners}{f'n{burner_nice}' if burner_nice else ''}{groups}-"


def report(out: Path, sides: list[str], links: list[str], prefix: str) -> str:
    """The markdown table of every saved run in ``out`` whose label starts with ``prefix``,
    medians and ratios."""
    lines = ["| run | " + " | ".join(COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
    medians: dict[tuple[str, str], dict[str, float | None]] = {}
    pairs: dict[tuple[str, str], list[dict[str, float | None]]] = {}
    for link in links:
        for side in sides:
            runs = sorted(out.glob(f"cpu-{prefix}{side}-{link}-*.json"),
                          key=lambda p: int(p.stem.rsplit("-", 1)[1]))
            rows = [figures(p) for p in runs]
            pairs[(side, link)] = rows
            for p, row in zip(runs, rows, strict=True):
                lines.append(f"| {p.stem[4:]} | " + " | ".join(_fmt(row[c]) for c in COLUMNS)
                             + " |")
            medians[(side, link)] = {c: median_known([r[c] for r in rows]) for c in COLUMNS}
    lines += ["", "Medians per side and profile (ratio to the first side's median over the "
              "same rounds in brackets):", "",
              "| side | profile | runs | " + " | ".join(COLUMNS[1:]) + " |",
              "|---" * (len(COLUMNS) + 2) + "|"]
    for link in links:
        first = medians.get((sides[0], link), {})
        for side in sides:
            med = medians[(side, link)]
            cells = []
            for c in COLUMNS[1:]:
                v, b = med[c], first.get(c)
                ratio = f" (x{v / b:.2f})" if side != sides[0] and v is not None and b else ""
                cells.append(_fmt(v) + ratio)
            lines.append(f"| {side} | {link} | {len(pairs[(side, link)])} | "
                         + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=_side, action="append", required=True,
                    help="NAME=ROOT[::FLAG...]: remote flags, local:FLAG, bench:FLAG (repeat; "
                         "the first is the reference)")
    ap.add_argument("--link", action="append", required=True,
                    help="link profile, or none for no link emulator (repeat)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--first-round", type=int, default=1,
                    help="number of the first round (to interleave invocations of other "
                         "settings round by round into one directory)")
    ap.add_argument("--burners", type=int, default=0, help="CPU-bound processes beside runs")
    ap.add_argument("--burner-nice", type=int, default=0,
                    help="the burners' nice value (above 0: ranked below the demo)")
    ap.add_argument("--cgroups", action="store_true",
                    help="burners and each side in CPU groups of their own (weights: a side's "
                         "cgroup:W flag, burners 100)")
    ap.add_argument("--out", type=Path, required=True, help="results directory")
    ap.add_argument("--report-only", action="store_true")
    args = ap.parse_args(argv)
    args.out = args.out.resolve()  # the runs work in their own checkouts
    args.out.mkdir(parents=True, exist_ok=True)
    names = [s[0] for s in args.side]
    prefix = run_prefix(args.burners, args.burner_nice, args.cgroups)
    if not args.report_only:
        groups = CpuGroups() if args.cgroups else None  # CgroupError: a clear refusal
        burn = f"import os\nos.nice({args.burner_nice})\nwhile True: pass"
        burners: list[subprocess.Popen[bytes]] = []
        try:
            if groups is not None:
                groups.make("others", DEFAULT_WEIGHT)
                for name, _root, flags in args.side:
                    # the display loop's SCHED_FIFO thread takes ~0.1 core; the sides share
                    # 0.8 of the root's 0.95 s of real time per second
                    groups.make(f"side-{name}", side_weight(flags),
                                rt_runtime_us=800_000 // len(args.side))
            def placed(group: str) -> Callable[[], None] | None:
                """A child's ``preexec_fn`` that enters ``group`` (None without groups)."""
                return None if groups is None else functools.partial(groups.enter, group)

            burners = [subprocess.Popen([sys.executable, "-c", burn], preexec_fn=placed("others"))
                       for _ in range(args.burners)]
            for i in range(args.first_round, args.first_round + args.rounds):
                for link in args.link:
                    order = args.side if i % 2 else list(reversed(args.side))
                    for name, root, flags in order:
                        _run(name, root, flags, link, f"{prefix}{name}-{link}-{i}", args.out,
                             placed(f"side-{name}"))
        finally:
            for b in burners:
                b.kill()
                b.wait()
            if groups is not None:
                groups.close()
    table = report(args.out, names, args.link, prefix)
    print(table)
    (args.out / f"table{'-' + prefix.rstrip('-') if prefix else ''}.md").write_text(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
