"""Motion-to-touch before/after, per link profile, against the floor of each profile.

Two checkouts (each with its own ``.venv``; e.g. a ``git worktree`` of the base commit beside
this one) run the default demo (``teletouch demo --headless --json --no-view --link P``)
alternately on the same machine in the same minutes (order ABBA over the rounds, profiles
interleaved), so machine load hits both sides alike. Per run it keeps the local station's
motion-to-touch ledger (``latency_ms``: ``end_to_end`` and the stages), the remote station's
capture counters and the 1-minute load average at the start of the run.

The **floor** of a profile is what no scheduling can remove: the profile's nominal round trip
(twice its one-way delay; jitter and loss only add) plus the stages that do work rather than
wait - ``remote_dispatch``, ``reconstruction_and_stiffness``, ``relay_forward_platform``,
``relay_forward_tactile`` and ``render`` - the sensor's own delivery, ``sensor_delivery`` (a
streaming camera's latency: no scheduling here removes it), and the wait the design's rates fix,
``uplink_sampling`` (the platform_state send period, and the states passed over until the
remote's frame schedule took one: ``shared/motion_to_touch.py``), taken at their p50 in the same
profile's *after* runs. What the measured p99 exceeds the floor by is waiting: the frame
clock or the pose wait and the simulated sensor's render (``arm_and_sensor``), jitter and
head-of-line blocking on the emulated links, and the processes being descheduled on a loaded
machine.

Run: ``python benchmarks/bench_motion_to_touch.py --before ../m2t-base --after . --rounds 3``
(writes ``benchmarks/results/motion_to_touch.{md,json,png}`` unless ``--no-write``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from lab.bench.results import median_known

RESULTS = Path(__file__).resolve().parent / "results"
#: stages that do work (not wait); their p50 joins the nominal round trip in the floor
WORK_STAGES = ("remote_dispatch", "reconstruction_and_stiffness", "relay_forward_platform",
               "relay_forward_tactile", "render")
#: waits the design fixes (the uplink's send period: a movement just after one message's
#: sample shows first in the next); their p50 joins the floor too
DESIGN_WAITS = ("uplink_sampling",)
#: the sensor's own delivery (a camera's known latency; 0 for a source that captures on
#: demand); in the floor too. Ledgers before 2026-12-06 had no such stage: it was part of
#: ``reconstruction_and_stiffness``, so a run without it adds nothing (not a missing stage)
SENSOR_STAGES = ("sensor_delivery",)
SIDES = ("before", "after")


def floor_ms(round_trip_ms: float, latencies: list[dict[str, Any] | None]) -> float | None:
    """The floor (see the module docstring): the nominal round trip plus, per stage of
    ``WORK_STAGES``, ``DESIGN_WAITS`` and ``SENSOR_STAGES``, the median of its p50 over the
    runs' latency tables that report it; None when no run reports one of the first two
    groups' stages (one of ``SENSOR_STAGES`` that no run reports adds 0: older ledgers)."""
    total = round_trip_ms
    for stage in (*WORK_STAGES, *DESIGN_WAITS, *SENSOR_STAGES):
        p50 = median_known(((lat or {}).get(stage) or {}).get("p50") for lat in latencies)
        if p50 is None and stage in SENSOR_STAGES:
            continue
        if p50 is None:
            return None
        total += float(p50)
    return total


def _nominal_rtt_ms(profile: str, root: Path) -> float:
    code = ("import json, sys; from lab.linkemu import get_profile; "
            f"print(get_profile({profile!r}).round_trip_ms)")
    out = subprocess.run([str(root / ".venv" / "bin" / "python"), "-c", code], cwd=root,
                         capture_output=True, text=True, check=True, timeout=120)
    return float(out.stdout.strip())


def _demo(root: Path, profile: str, duration_s: float) -> dict[str, Any]:
    cmd = [str(root / ".venv" / "bin" / "teletouch"), "--log-level", "WARNING", "demo",
           "--headless", "--json", "--no-view", "--link", profile, "--duration",
           f"{duration_s:g}"]
    load = os.getloadavg()[0]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=1200,
                          check=False)
    if proc.returncode != 0:
        return {"error": f"exit {proc.returncode}: {proc.stderr[-1500:]}", "load_1min": load}
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    frames = (report.get("remote") or {}).get("frames") or {}
    return {"load_1min": load, "wall_s": time.monotonic() - t0,
            "latency_ms": report.get("latency_ms", {}),
            "captures": frames.get("captures"), "capture": frames.get("capture"),
            "achieved_fps": frames.get("achieved_fps"),
            "tumors_found": report.get("tumors_found"),
            "tumors_expected": report.get("tumors_expected")}


def _fig(run: dict[str, Any], stage: str, key: str) -> float | None:
    value = ((run.get("latency_ms") or {}).get(stage) or {}).get(key)
    return None if value is None else float(value)


def _f(v: float | None, digits: int = 1) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def summarise(runs: dict[str, dict[str, list[dict[str, Any]]]],
              rtt_ms: dict[str, float]) -> tuple[list[str], dict[str, Any]]:
    """Markdown table rows and the figures per profile (medians over the runs)."""
    rows, figures = [], {}
    for profile, sides in runs.items():
        med = {side: {k: median_known([_fig(r, "end_to_end", k) for r in sides[side]])
                      for k in ("p50", "p99")} for side in SIDES}
        work = {s: median_known([_fig(r, s, "p50") for r in sides["after"]])
                for s in (*WORK_STAGES, *DESIGN_WAITS, *SENSOR_STAGES)}
        floor = floor_ms(rtt_ms[profile], [r.get("latency_ms") for r in sides["after"]])
        p99_after = med["after"]["p99"]
        figures[profile] = {"nominal_rtt_ms": rtt_ms[profile], "work_stages_p50_ms": work,
                            "floor_ms": floor, "median": med}
        ratio: dict[str, float | None] = {}
        for k in ("p50", "p99"):
            a, b = med["after"][k], med["before"][k]
            ratio[k] = a / b if a is not None and b else None
        rows.append(
            f"| {profile} | {len(sides['before'])} / {len(sides['after'])} | "
            f"{_f(med['before']['p50'])} / {_f(med['before']['p99'])} | "
            f"{_f(med['after']['p50'])} / {_f(med['after']['p99'])} | "
            f"{_f(ratio['p50'], 2)} / {_f(ratio['p99'], 2)} | {_f(rtt_ms[profile])} | "
            f"{_f(floor)} | "
            f"{_f(None if p99_after is None or floor is None else p99_after - floor)} |")
    return rows, figures


def stage_rows(runs: dict[str, dict[str, list[dict[str, Any]]]]) -> list[str]:
    """Per profile and stage: median p50 / p99 before and after."""
    rows = []
    for profile, sides in runs.items():
        names: list[str] = []
        for side in SIDES:
            for r in sides[side]:
                names += [n for n in (r.get("latency_ms") or {}) if n not in names]
        for name in names:
            cells = []
            for side in SIDES:
                p50 = median_known([_fig(r, name, "p50") for r in sides[side]])
                p99 = median_known([_fig(r, name, "p99") for r in sides[side]])
                count = median_known([_fig(r, name, "count") for r in sides[side]])
                cells.append(f"{_f(p50, 2)} / {_f(p99, 2)} ({_f(count, 0)})")
            rows.append(f"| {profile} | `{name}` | {cells[0]} | {cells[1]} |")
    return rows


def plot(figures: dict[str, Any], runs: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(figures), figsize=(5 * len(figures), 4))
    axes = axes if len(figures) > 1 else [axes]
    for ax, (profile, fig_data) in zip(axes, figures.items(), strict=True):
        for i, side in enumerate(SIDES):
            for j, key in enumerate(("p50", "p99")):
                vals = [_fig(r, "end_to_end", key) for r in runs[profile][side]]
                xs = [i * 2 + j] * len(vals)
                ax.scatter(xs, vals, color=("tab:gray", "tab:blue")[i], alpha=0.7)
        ax.axhline(fig_data["floor_ms"], color="tab:red", ls="--", label="floor")
        ax.set_xticks(range(4), ["before p50", "before p99", "after p50", "after p99"])
        ax.set_ylabel("motion-to-touch (ms)")
        ax.set_yscale("log")
        ax.set_title(profile)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", type=Path, required=True, help="checkout before the change")
    parser.add_argument("--after", type=Path, default=Path("."), help="checkout after it")
    parser.add_argument("--profiles", nargs="+", default=["lan", "city-1000km"])
    parser.add_argument("--rounds", type=int, default=2, help="runs per side and profile")
    parser.add_argument("--duration-s", type=float, default=60.0,
                        help="the demo operator's time limit (the default sweep ends sooner)")
    parser.add_argument("--tag", default="", help="results file suffix: motion_to_touch_TAG")
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args()
    roots = {"before": args.before.resolve(), "after": args.after.resolve()}
    load_start = os.getloadavg()
    runs: dict[str, dict[str, list[dict[str, Any]]]] = {
        p: {s: [] for s in SIDES} for p in args.profiles}
    for i in range(args.rounds):
        order = list(SIDES) if i % 2 == 0 else list(reversed(SIDES))
        for profile in args.profiles:
            for side in order:
                run = _demo(roots[side], profile, args.duration_s)
                run["round"] = i + 1
                runs[profile][side].append(run)
                error = run.get("error", "")[:200]
                print(f"round {i + 1}/{args.rounds} {profile} {side}: load "
                      f"{run['load_1min']:.1f}, e2e p50/p99 {_fig(run, 'end_to_end', 'p50')} / "
                      f"{_fig(run, 'end_to_end', 'p99')} ms {error}", file=sys.stderr, flush=True)
    rtt = {p: _nominal_rtt_ms(p, roots["after"]) for p in args.profiles}
    rows, figures = summarise(runs, rtt)
    errors = [f"- {p} {s} round {r['round']}: {r['error'][:300]}"
              for p, sides in runs.items() for s in SIDES for r in sides[s] if "error" in r]
    loads = [r["load_1min"] for sides in runs.values() for s in SIDES for r in sides[s]]
    lines = [
        "# Motion-to-touch: before / after, and the floor of each profile",
        "",
        f"Command: `python benchmarks/bench_motion_to_touch.py --before "
        f"{os.path.relpath(roots['before'])} --after {os.path.relpath(roots['after'])} "
        f"--rounds {args.rounds}{' --tag ' + args.tag if args.tag else ''}` (the default "
        "demo: breast scene, raster operator, 120 Hz sensor frames, 1 kHz display loop).",
        "",
        f"Machine: {platform.machine()}, nproc {os.cpu_count()}, Python "
        f"{platform.python_version()}. Other jobs may share the machine: 1-min load average "
        f"{load_start[0]:.1f} at the start, {min(loads):.1f}-{max(loads):.1f} at the start of "
        f"the runs, {os.getloadavg()[0]:.1f} at the end. Sides alternate (ABBA) within each "
        "profile, so load hits both alike; each figure is the median over the runs of that "
        "side.",
        "",
        "| profile | runs before / after | before p50 / p99 ms | after p50 / p99 ms | "
        "after / before p50 / p99 | nominal RTT ms | floor ms | after p99 - floor ms |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "Floor = nominal round trip + the p50 of the stages that work rather than wait ("
        + ", ".join(f"`{s}`" for s in WORK_STAGES) + "), of the sensor's own delivery ("
        + ", ".join(f"`{s}`" for s in SENSOR_STAGES) + "; 0 where not reported) and of the "
        "waits the design fixes ("
        + ", ".join(f"`{s}`" for s in DESIGN_WAITS) + ") in the after runs.",
        "",
        "## Stages (median over runs of p50 / p99 ms, and the frame count)",
        "",
        "`unaligned` / `incomplete` (after only): frames whose stages were not counted "
        "(a clock offset not yet known / a stamp missing); before, such frames appeared under "
        "merged names like `relay.relay_out>relay.relay_in`.",
        "",
        "| profile | stage | before | after |",
        "|---|---|---|---|",
        *stage_rows(runs),
        "",
        *(["## Failed runs", "", *errors, ""] if errors else []),
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.no_write:
        RESULTS.mkdir(parents=True, exist_ok=True)
        stem = "motion_to_touch" + (f"_{args.tag}" if args.tag else "")
        (RESULTS / f"{stem}.json").write_text(json.dumps(
            {"load_start": load_start, "figures": figures, "runs": runs}, indent=1))
        plot(figures, runs, RESULTS / f"{stem}.png")
        text += f"\n![motion-to-touch per run against the floor]({stem}.png)\n"
        (RESULTS / f"{stem}.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
