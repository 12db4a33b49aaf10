"""The remote station's CPU, before/after, paired: two checkouts in the same minutes.

Each run is one ``teletouch bench cpu`` (the default demo; per-process and per-thread CPU
exact from ``/proc``, the split over stages by py-spy, see :mod:`lab.bench.cpu_impl`) of one
checkout, run as ``python -m lab.cli`` with that checkout first on ``PYTHONPATH`` (so a plain
source tree such as ``git archive BASE | tar -x -C DIR`` will do; the interpreter and
libraries are this one's). The two sides alternate ABBA... over the rounds so that the
machine's load (other jobs) hits both alike; the 1-minute load average is kept per run.

Per run: the remote process' cores, its product and simulated-hardware shares (py-spy
stages, ``sim:`` apart), its CPU per tactile frame (cores / session frame rate), every
remote thread's cores by name, the other processes' cores. The report gives the medians per
side and after/before ratios of the medians.

Run: ``python benchmarks/bench_remote_cpu.py --before /tmp/base --after . --rounds 2``
(writes ``benchmarks/results/remote_cpu[_TAG].{md,json}`` unless ``--no-write``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from lab.bench.results import median_known, write_results

RESULTS = Path(__file__).resolve().parent / "results"
SIDES = ("before", "after")
_SIM = ("sim:", "bench/")


def _run(root: Path, label: str, window_s: float, out_dir: Path, keep: Path | None = None,
         note: str = "") -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(root)}
    cmd = [sys.executable, "-m", "lab.cli", "bench", "cpu", "--label", label, "--window-s",
           f"{window_s:g}", "--out-dir", str(out_dir)]
    load = os.getloadavg()[0]
    proc = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True,
                          timeout=900, check=False)
    path = out_dir / f"cpu-{label}.json"
    if proc.returncode != 0 or not path.exists():
        return {"label": label, "error": f"exit {proc.returncode}: {proc.stderr[-1500:]}",
                "load_1min": load}
    run = json.loads(path.read_text())
    if keep is not None:  # the full run beside the others, for cpu.md (--report-only)
        run["note"] = note
        (keep / f"cpu-{label}.json").write_text(json.dumps(run, indent=1, default=str))
    remote = run["stages"].get("remote", {})
    fps = (run.get("remote_frames") or {}).get("achieved_fps") or 0.0
    cores = run["processes"]["remote"]["cores"]
    return {
        "label": label, "load_1min": load, "load_end": run["load_end"][0],
        "remote_cores": cores,
        "remote_product": sum(v for k, v in remote.items() if not k.startswith(_SIM)),
        "remote_sim": sum(v for k, v in remote.items() if k.startswith(_SIM)),
        "remote_ms_per_frame": cores / fps * 1000.0 if fps else None,
        "achieved_fps": fps,
        "captures": (run.get("remote_frames") or {}).get("captures"),
        "stages": remote,
        "threads": (run.get("threads") or {}).get("remote", []),
        "processes": {k: v["cores"] for k, v in run["processes"].items()},
        "top": run.get("top", {}).get("remote", []),
    }


def _f(v: float | None, digits: int = 3) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


METRICS = (("remote process (cores)", "remote_cores"),
           ("remote product code (cores)", "remote_product"),
           ("remote simulated hardware (cores)", "remote_sim"),
           ("remote CPU per tactile frame (ms)", "remote_ms_per_frame"),
           ("tactile frames / s (session)", "achieved_fps"))


def _report(runs: dict[str, list[dict[str, Any]]], args: argparse.Namespace) -> str:
    lines = [f"# Remote station CPU, paired before/after ({args.tag or 'run'})", "",
             f"`python benchmarks/bench_remote_cpu.py --before {args.before} --after "
             f"{args.after} --rounds {args.rounds} --window-s {args.window_s:g}"
             f"{' --tag ' + args.tag if args.tag else ''}`", "",
             f"Machine: {platform.machine()}, nproc {os.cpu_count()}, Python "
             f"{platform.python_version()}. Other jobs may share the machine "
             "(1-minute load average per run below): compare the sides by their medians and "
             "ratios from the same minutes, not with other files' absolute figures.", "",
             f"Before: {args.before_note}. After: {args.after_note}.", "",
             "| metric | before (median) | after (median) | after / before |",
             "|---|---|---|---|"]
    for name, key in METRICS:
        b = median_known([r.get(key) for r in runs["before"]])
        a = median_known([r.get(key) for r in runs["after"]])
        ratio = a / b if a is not None and b else None
        lines.append(f"| {name} | {_f(b)} | {_f(a)} | {_f(ratio, 2)} |")
    lines += ["", "## Runs", "", "| run | load 1 min (start/end) | remote | product | sim hw | "
              "ms / frame | frames/s | local | relay |", "|---|---|---|---|---|---|---|---|---|"]
    order = sorted((r for side in SIDES for r in runs[side]), key=lambda r: r["order"])
    for r in order:
        if "error" in r:
            lines.append(f"| {r['label']} | {r['load_1min']:.1f} | failed: "
                         f"{r['error'][:120]!r} | | | | | | |")
            continue
        p = r["processes"]
        lines.append(f"| {r['label']} | {r['load_1min']:.1f} / {r['load_end']:.1f} | "
                     f"{_f(r['remote_cores'])} | {_f(r['remote_product'])} | "
                     f"{_f(r['remote_sim'])} | {_f(r['remote_ms_per_frame'], 2)} | "
                     f"{r['achieved_fps']:.0f} | {_f(p.get('local'))} | {_f(p.get('relay'))} |")
    lines += ["", "## Remote stages (cores, median per side)", "",
              "| stage | before | after |", "|---|---|---|"]
    stages = sorted({s for side in SIDES for r in runs[side] for s in r.get("stages", {})})
    for s in stages:
        vals = [median_known([r.get("stages", {}).get(s, 0.0) for r in runs[side]
                              if "error" not in r]) for side in SIDES]
        lines.append(f"| {s} | {_f(vals[0])} | {_f(vals[1])} |")
    lines += ["", "## Remote threads (cores, exact per thread; name: root function)", ""]
    for r in order:
        if "error" in r:
            continue
        named = ", ".join(f"{t['runs']} {t['cores']:.3f}" for t in r["threads"]
                          if t["cores"] >= 0.002)
        lines.append(f"- **{r['label']}**: {named}")
    lines += ["", "## Top remote functions (py-spy busy samples; GIL and lock waits included)", ""]
    for r in order:
        if "error" in r:
            continue
        lines.append(f"- **{r['label']}**: " + "; ".join(f"{f} {n}" for f, n in r["top"][:8]))
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", type=Path, required=True, help="the base checkout")
    ap.add_argument("--after", type=Path, required=True, help="the changed checkout")
    ap.add_argument("--before-note", default="base commit")
    ap.add_argument("--after-note", default="this branch")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--window-s", type=float, default=12.0)
    ap.add_argument("--tag", default="")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--keep-runs", action="store_true",
                    help="also save each run's full JSON as results/cpu-LABEL.json (cpu.md)")
    args = ap.parse_args()
    roots = {"before": args.before.resolve(), "after": args.after.resolve()}
    runs: dict[str, list[dict[str, Any]]] = {s: [] for s in SIDES}
    n = 0
    with tempfile.TemporaryDirectory(prefix="remote-cpu-") as tmp:
        for i in range(args.rounds):
            for side in (SIDES if i % 2 == 0 else SIDES[::-1]):
                label = f"{args.tag + '-' if args.tag else ''}{side}-{i + 1}"
                note = args.before_note if side == "before" else args.after_note
                run = _run(roots[side], label, args.window_s, Path(tmp),
                           RESULTS if args.keep_runs else None, note)
                run["order"] = n
                n += 1
                runs[side].append(run)
                print(f"{label}: load {run['load_1min']:.1f} remote "
                      f"{_f(run.get('remote_cores'))} cores, "
                      f"{_f(run.get('remote_ms_per_frame'), 2)} ms/frame", flush=True)
    text = _report(runs, args)
    if not args.no_write:
        write_results(RESULTS, f"remote_cpu{'_' + args.tag if args.tag else ''}", text,
                      data=runs)
    print(text)  # after writing: a closed pipe must not lose the results
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
