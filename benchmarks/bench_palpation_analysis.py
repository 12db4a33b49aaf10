"""Palpation analysis time per session, this tree against an earlier revision, same sessions.

What is timed: :func:`local_site.palpation.maps_and_findings` (the relief and stiffness maps,
detection and typing; what ``analyse_recording`` does after its lag correction, and what the
live view and the HTML report call) on recordings of the out-of-distribution benchmark's
sessions (``teletouch bench palpation --ood``: realistic world, simulated in-process once,
kept in ``--cache``), each in the workspace map corrected by the session's simulated fiducial
registration, as the benchmark analyses them.

How: the baseline revision is extracted with ``git archive`` into a temporary directory. Each
tree runs in a child process of its own (same interpreter and libraries, one BLAS thread) that
loads every recording, analyses it once to warm up, then ``--repeats`` times timed (CPU time of
the process, ``time.process_time``, so a child preempted by other jobs is not charged for
them), and reports the median per recording, its findings and its peak RSS (the whole
child's, imports included). Trees alternate
(ABBA) over ``--rounds``; the figure is the per-round ratio new/old of the summed medians,
since the machine's load moves the absolute figures. The findings of both trees are compared
field by field: a speed change must not change a result.

Usage::

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_palpation_analysis.py --baseline-rev dd55ce4 \\
        --cache /tmp/palp-analysis-cache --write benchmarks/results/palpation_analysis.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

FAMILIES = "size,type,count,free-operator,coverage,registration,noise"


def _child(tree: Path, cache: Path, repeats: int) -> dict[str, Any]:
    """Run inside the child: time the tree's analysis on every cached recording."""
    sys.path.insert(0, str(tree))
    import local_site
    from lab.bench.palpation_ood import _load

    where = Path(local_site.__file__).resolve()
    if not where.is_relative_to(tree.resolve()):
        raise SystemExit(f"the child imported {where}, not the tree under test {tree}")
    from local_site.palpation import maps_and_findings
    from shared.errors import InputDataError
    from shared.workspace import WorkspaceMap

    out: dict[str, Any] = {}
    for path in sorted(cache.glob("*.npz")):
        rec = _load(path)
        ws = WorkspaceMap()
        reg = path.with_suffix(".reg.json")
        if reg.exists():
            d = json.loads(reg.read_text())
            ws = WorkspaceMap().registered(d["dx_mm"], d["dy_mm"], d["yaw_deg"])
        try:
            _, findings = maps_and_findings(rec, ws)
        except InputDataError as err:  # nothing palpated: compared like the findings
            out[path.name] = {"error": repr(err)}
            continue
        ms = []
        for _ in range(repeats):
            t0 = time.process_time()
            maps_and_findings(rec, ws)
            ms.append((time.process_time() - t0) * 1e3)
        ms.sort()
        out[path.name] = {"ms": ms[len(ms) // 2], "frames": int(rec.frames),
                          "findings": [f.to_dict() for f in findings]}
    return {"recordings": out,
            "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def _simulate(cache: Path, families: list[str], runs: int, seed: int) -> int:
    """Put the sessions' recordings (and registrations) into ``cache``; return the count."""
    sys.path.insert(0, str(ROOT))
    from lab.bench.palpation_ood import make_case, run_case

    n = 0
    for family in families:
        for i in range(runs):
            case = make_case(family, i, runs, seed + i)
            run_case(case, cache, analyse=lambda rec, context: [])
            n += 1
    return n


def _run_tree(tree: Path, cache: Path, repeats: int) -> dict[str, Any]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONPATH="")
    proc = subprocess.run([sys.executable, "-P", __file__, "--child", str(tree), "--cache",
                           str(cache), "--repeats", str(repeats)],
                          capture_output=True, text=True, env=env, cwd=tree, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"child for {tree} failed:\n{proc.stderr[-3000:]}")
    return dict(json.loads(proc.stdout))


def _same(a: Any, b: Any) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline-rev", default="dd55ce4")
    parser.add_argument("--cache", default=None, help="recordings kept here (default: temp)")
    parser.add_argument("--families", default=FAMILIES)
    parser.add_argument("--runs", type=int, default=4, help="sessions per family")
    parser.add_argument("--seed", type=int, default=13000, help="first seed")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--write", default=None, metavar="FILE.md")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        json.dump(_child(Path(args.child), Path(args.cache), args.repeats), sys.stdout)
        return
    for name in ("runs", "rounds", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1")
    sys.path.insert(0, str(ROOT))
    from lab.bench.relay_cpu_impl import extract_revision
    from shared.errors import ConfigError
    from shared.report import format_table

    with tempfile.TemporaryDirectory() as tmp:
        old_tree = Path(tmp) / "old"
        old_tree.mkdir()
        try:  # first: a bad revision fails before minutes of simulation
            commit = extract_revision(args.baseline_rev, old_tree)
        except ConfigError as err:
            parser.error(str(err))
        cache = Path(args.cache) if args.cache else Path(tmp) / "cache"
        cache.mkdir(parents=True, exist_ok=True)
        families = [f for f in args.families.split(",") if f]
        t0 = time.monotonic()
        sessions = _simulate(cache, families, args.runs, args.seed)
        simulate_s = time.monotonic() - t0
        load_start = os.getloadavg()
        rounds = []
        for r in range(args.rounds):
            order = [("old", old_tree), ("new", ROOT)]
            if r % 2:
                order.reverse()
            rounds.append({name: _run_tree(tree, cache, args.repeats) for name, tree in order})
            print(f"round {r + 1}/{args.rounds} done", file=sys.stderr)
        load_end = os.getloadavg()
    names = sorted(rounds[0]["new"]["recordings"])
    identical = sum(_same(rounds[0]["new"]["recordings"][n].get("findings"),
                          rounds[0]["old"]["recordings"][n].get("findings"))
                    and "error" not in rounds[0]["new"]["recordings"][n] for n in names)
    timed = [n for n in names if "ms" in rounds[0]["new"]["recordings"][n]
             and "ms" in rounds[0]["old"]["recordings"][n]]
    rows = []
    ratios = []
    for i, rd in enumerate(rounds):
        old = sum(rd["old"]["recordings"][n]["ms"] for n in timed)
        new = sum(rd["new"]["recordings"][n]["ms"] for n in timed)
        ratios.append(new / old)
        rows.append({"round": i + 1, "old_ms_per_session": old / len(timed),
                     "new_ms_per_session": new / len(timed), "new_over_old": new / old,
                     "old_max_rss_mb": rd["old"]["max_rss_mb"],
                     "new_max_rss_mb": rd["new"]["max_rss_mb"]})
    ratios.sort()
    median = statistics.median(ratios)
    frames = [rounds[0]["new"]["recordings"][n]["frames"] for n in timed]
    head = (f"# Palpation analysis time per session: this tree against `{args.baseline_rev}`\n\n"
            f"Command: `OPENBLAS_NUM_THREADS=1 python benchmarks/bench_palpation_analysis.py "
            f"--baseline-rev {args.baseline_rev} --families {args.families} --runs {args.runs} "
            f"--seed {args.seed} --rounds {args.rounds} --repeats {args.repeats}`. "
            f"old = `{args.baseline_rev}` ({commit[:10]}), extracted with `git archive`; new = "
            f"this tree. Timed: `maps_and_findings` (maps, detection, typing), CPU time of "
            f"the child process, median of {args.repeats} per session after one warm-up run; "
            f"trees alternate ABBA. {sessions} OOD sessions (families {args.families}, "
            f"{args.runs} each, seeds from {args.seed}; realistic world; simulated in "
            f"{simulate_s:.0f} s), {min(frames)}-{max(frames)} tactile frames each. "
            f"{platform.python_implementation()} {platform.python_version()}, "
            f"{os.cpu_count()} cores, load average {load_start[0]:.2f} at the start, "
            f"{load_end[0]:.2f} at the end.\n\n")
    summary = (f"**new / old: {median:.2f}** (median over {len(ratios)} "
               f"rounds, range {ratios[0]:.2f}-{ratios[-1]:.2f}). Findings identical "
               f"(every field) in **{identical} of {len(names)}** sessions.\n\n")
    text = head + summary + format_table(rows) + "\n"
    print(text)
    if args.write:
        Path(args.write).write_text(text)


if __name__ == "__main__":
    main()
