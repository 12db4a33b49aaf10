"""Palpation typing against the number of tactile frames (issue 10), before and after.

A loaded machine delivers fewer tactile frames to the analysis; the demo's benign tumor was
then typed malignant. This reproduces that without loading the machine: sessions are
simulated in-process (:func:`lab.bench.palpation_session.simulate_session`, the station's
own pipeline in simulated time) at several frame rates and analysed by the local station's
analysis. Each finding is typed twice from the same analysis run:

* ``before``: the typing of commit 836b4a8, from an analysis without the lag correction
  (malignant score
  ``(0.22 / sharpness)^2 sqrt(peak) sqrt((1 + contrast) / 1.35)``, sharpness = mean
  gradient of the smoothed relief on the region's edge over its peak), recomputed from the
  fields the findings still report (``boundary_sharpness_per_mm``, ``peak_relief``,
  ``stiffness_contrast``, ``coverage``); detection is unchanged, so this is that commit's
  result;
* ``after``: the finding's own ``kind`` (edge width and rim relief, see
  ``local_site/palpation/findings.py``), from the analysis as it is now (with the lag
  correction of ``local_site/palpation/lag.py``).

Three tables:

1. the demo's session (breast seed 0, the demo test's small raster, no registration error)
   at 6-120 frames/s;
2. development phantoms (OOD ``type`` family, seeds 1000-1011: the seeds the reference
   levels were set on, at 20 frames/s) at 5, 10, 20, 60 frames/s: does the score move
   with the rate? (the held-out check is the OOD ``frame-rate`` family, seeds 2000-2009);
3. the demo's 120 frames/s session with each frame's position lagging its image by 0-25 ms
   (at 45 mm/s): a timing skew between the arm's pose and the image, which a loaded
   station also produces, widens the boundary; the new typing without and with the lag
   correction.

Usage::

    python benchmarks/bench_palpation_density.py --cache /tmp/density-cache \\
        --write benchmarks/results/palpation_density.md

writes ``palpation_density.md`` (the tables), ``.json`` (every finding's figures) and
``.png`` (the scores against the frame rate and the lag).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lab.bench.palpation_ood import _load, _save, make_case, run_case
from lab.bench.palpation_session import Operator, simulate_session
from lab.scoring import score_findings
from local_site.palpation import Finding, analyse_recording
from local_site.recording import Recording
from remote_site.agent.world import REALISTIC, Registration, world_for
from remote_site.phantom.phantom_file import resolve_phantom
from shared.workspace import WorkspaceMap

DEMO_RASTER = Operator(region=(20.0, 52.0, 4.0, 36.0), spacing_mm=4.0, speed_mm_s=45.0,
                       press_z_mm=10.0)
FRAME_FIELDS = ("frame_center_mm", "frame_pitch_mm", "frame_contact", "frame_force_n",
                "frame_indentation_mm", "frame_height_mm", "frame_rx_us", "frame_seq")


def before_score(f: Finding) -> float:
    """The malignant score of commit 836b4a8 (see the module docstring)."""
    return ((0.22 / max(f.boundary_sharpness_per_mm, 1e-3)) ** 2
            * math.sqrt(f.peak_relief / 1.0)
            * math.sqrt((1.0 + max(f.stiffness_contrast, -0.9)) / 1.35))


def before_kind(f: Finding) -> str:
    if f.coverage < 0.9:
        return "uncertain"
    return "malignant" if before_score(f) > 1.0 else "benign"


def _match(findings: list[Finding], truth: dict[str, Any]) -> dict[str, Finding]:
    score = score_findings(findings, truth)
    return {m["id"]: min(findings, key=lambda f: math.dist(f.center_mm, m["found_center_mm"]))
            for m in score["matches"]}


def _typed(before: list[Finding], after: list[Finding], truth: dict[str, Any],
           unlagged: list[Finding] | None = None) -> list[dict[str, Any]]:
    """Per true tumor: the before / after kinds and scores (``unlagged``: the after typing
    without the lag correction, when given)."""
    mb, ma = _match(before, truth), _match(after, truth)
    mu = _match(unlagged, truth) if unlagged is not None else {}
    out = []
    for t in truth["tumors"]:
        row: dict[str, Any] = {"id": t["id"], "kind": t["kind"], "found": t["id"] in ma}
        if t["id"] in mb:
            fb = mb[t["id"]]
            row.update(before=before_kind(fb), before_score=before_score(fb),
                       sharpness=fb.boundary_sharpness_per_mm)
        if t["id"] in ma:
            f = ma[t["id"]]
            row.update(after=f.kind, after_score=f.malignant_score, edge_mm=f.edge_width_mm,
                       edge_se_mm=f.edge_width_se_mm, coverage=f.coverage)
        if t["id"] in mu:
            row.update(after_no_lag_correction=mu[t["id"]].kind,
                       after_no_lag_correction_score=mu[t["id"]].malignant_score)
        out.append(row)
    return out


def _both(rec: Recording, ws: WorkspaceMap, truth: dict[str, Any],
          unlagged: bool = False) -> list[dict[str, Any]]:
    """Analyse ``rec`` as commit 836b4a8 did (no lag correction) and as now."""
    before = analyse_recording(rec, ws, lag_correction=False)
    return _typed(before, analyse_recording(rec, ws), truth, before if unlagged else None)


def _demo_session(rate_hz: float, cache: Path) -> tuple[Recording, dict[str, Any]]:
    world = world_for(resolve_phantom("breast", 0), REALISTIC, 0, Registration())
    path = cache / f"demo-breast-s0-{rate_hz:g}hz.npz"
    if path.exists():
        rec = _load(path)
    else:
        rec = simulate_session(world, DEMO_RASTER, workspace=WorkspaceMap(),
                               frame_rate_hz=rate_hz)
        _save(rec, path)
    return rec, world.phantom.ground_truth()


def _fmt(v: Any, d: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{d}f}" if isinstance(v, float) else str(v)


def demo_table(rates: list[float], cache: Path) -> tuple[str, list[dict[str, Any]]]:
    rows: list[dict[str, Any]] = []
    for hz in rates:
        rec, truth = _demo_session(hz, cache)
        rows.append({"rate_hz": hz, "frames": rec.frames,
                     "tumors": _both(rec, WorkspaceMap(), truth)})
    lines = ["| frames/s | frames | benign: before score | before | after edge mm | "
             "after score | after | malignant: before | after |", "|" + "---|" * 9]
    for r in rows:
        b = next(t for t in r["tumors"] if t["id"] == "benign")
        m = next(t for t in r["tumors"] if t["id"] == "malignant")
        edge = (f"{b['edge_mm']:.3f} +- {b['edge_se_mm']:.3f}" if b["found"] else "-")
        lines.append(
            f"| {r['rate_hz']:g} | {r['frames']} | {_fmt(b.get('before_score'))} | "
            f"{b.get('before', 'missed')} | {edge} | {_fmt(b.get('after_score'))} | "
            f"{b.get('after', 'missed')} | {m.get('before', 'missed')} | "
            f"{m.get('after', 'missed')} |")
    return "\n".join(lines), rows


def dev_table(seeds: list[int], rates: list[float],
              cache: Path) -> tuple[str, list[dict[str, Any]]]:
    rows: list[dict[str, Any]] = []
    for hz in rates:
        incs: list[dict[str, Any]] = []
        for i, seed in enumerate(seeds):
            case = replace(make_case("type", i, len(seeds), seed), frame_rate_hz=hz)
            got: dict[str, Any] = {}

            def analyse(rec: Recording, ctx: dict[str, Any], got: dict[str, Any] = got
                        ) -> list[Finding]:
                est = ctx["registration"]
                ws = (WorkspaceMap().registered(est.dx_mm, est.dy_mm, est.yaw_deg)
                      if est is not None else WorkspaceMap())
                got["typed"] = _both(rec, ws, ctx["world"].phantom.ground_truth())
                return []

            run_case(case, cache, analyse)
            incs += got["typed"]
        rows.append({"rate_hz": hz, "inclusions": incs})
    lines = ["| frames/s | inclusions | before: b->b b->m m->b m->m unc. | after: b->b b->m "
             "m->b m->m unc. | before score benign / malignant (median) | after score "
             "benign / malignant (median) |", "|" + "---|" * 6]
    for r in rows:
        found = [t for t in r["inclusions"] if t["found"]]

        def conf(key: str, found: list[dict[str, Any]] = found) -> str:
            c = [sum(1 for t in found if t["kind"] == k and t[key] == g)
                 for k in ("benign", "malignant") for g in ("benign", "malignant")]
            unc = sum(1 for t in found if t[key] == "uncertain")
            return " ".join(map(str, c)) + f" {unc}"

        def med(key: str, kind: str, found: list[dict[str, Any]] = found) -> str:
            v = [t[key] for t in found if t["kind"] == kind and math.isfinite(t[key])]
            return _fmt(float(np.median(v))) if v else "-"

        lines.append(f"| {r['rate_hz']:g} | {len(r['inclusions'])} ({len(found)} found) | "
                     f"{conf('before')} | {conf('after')} | {med('before_score', 'benign')} "
                     f"/ {med('before_score', 'malignant')} | {med('after_score', 'benign')} "
                     f"/ {med('after_score', 'malignant')} |")
    return "\n".join(lines), rows


def lag_table(lags_ms: list[float], rate_hz: float,
              cache: Path) -> tuple[str, list[dict[str, Any]]]:
    rec, truth = _demo_session(rate_hz, cache)
    rows: list[dict[str, Any]] = []
    for lag in lags_ms:
        k = round(lag * rate_hz / 1000.0)
        centres = rec.frame_center_mm.copy()
        if k:
            centres[k:] = rec.frame_center_mm[:-k]
        typed = _both(replace(rec, frame_center_mm=centres), WorkspaceMap(), truth,
                      unlagged=True)
        rows.append({"lag_ms": k * 1000.0 / rate_hz, "tumors": typed})
    lines = ["| lag ms | lag at 45 mm/s, mm | benign: before score | before | after without "
             "lag correction: score | kind | after edge mm | after score | after |",
             "|" + "---|" * 9]
    for r in rows:
        b = next(t for t in r["tumors"] if t["id"] == "benign")
        lines.append(f"| {r['lag_ms']:.1f} | {r['lag_ms'] * 0.045:.2f} | "
                     f"{_fmt(b.get('before_score'))} | {b.get('before', 'missed')} | "
                     f"{_fmt(b.get('after_no_lag_correction_score'))} | "
                     f"{b.get('after_no_lag_correction', 'missed')} | "
                     f"{_fmt(b.get('edge_mm'), 3)} | {_fmt(b.get('after_score'))} | "
                     f"{b.get('after', 'missed')} |")
    return "\n".join(lines), rows


def plot(demo: list[dict[str, Any]], dev: list[dict[str, Any]], lag: list[dict[str, Any]],
         path: Path) -> None:
    """Malignant score against the frame rate (demo, development phantoms) and the lag."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    ax = axes[0]
    for key, style, label in (("before_score", "rs--", "before"), ("after_score", "go-",
                                                                   "after")):
        pts = [(r["rate_hz"], t[key]) for r in demo for t in r["tumors"]
               if t["id"] == "benign" and t["found"]]
        ax.plot(*zip(*pts, strict=True), style, label=label)
    ax.set_title("demo's benign tumor", fontsize=9)
    ax.set_xscale("log")
    ax.set_xlabel("frames/s")
    ax.set_ylabel("malignant score (> 1: malignant)")
    ax.legend(fontsize=8)
    ax = axes[1]
    for key, marker, label in (("before_score", "s", "before"), ("after_score", "o", "after")):
        for kind, colour in (("benign", "tab:blue"), ("malignant", "tab:red")):
            pts = [(r["rate_hz"] * (0.93 if key == "before_score" else 1.07), t[key])
                   for r in dev for t in r["inclusions"]
                   if t["found"] and t["kind"] == kind and math.isfinite(t[key])]
            ax.plot(*zip(*pts, strict=True), marker, color=colour, mfc="none"
                    if key == "before_score" else colour, ms=4, alpha=0.7,
                    label=f"{label}: {kind}")
    ax.set_title("development phantoms (seeds 1000-1011)", fontsize=9)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("frames/s")
    ax.legend(fontsize=7)
    ax = axes[2]
    for key, style, label in (("before_score", "rs--", "before"), ("after_score", "go-",
                                                                   "after")):
        pts = [(r["lag_ms"], t[key]) for r in lag for t in r["tumors"]
               if t["id"] == "benign" and t["found"]]
        ax.plot(*zip(*pts, strict=True), style, label=label)
    ax.set_title("demo's benign tumor, position lagging the image", fontsize=9)
    ax.set_xlabel("lag, ms (45 mm/s)")
    for a in axes:
        a.axhline(1.0, color="k", lw=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cache", required=True, help="simulated recordings are kept here")
    p.add_argument("--write", default=None, help="write the results (.md, and .json beside)")
    p.add_argument("--demo-rates", default="6,10,20,30,60,120")
    p.add_argument("--dev-seeds", default="1000-1011")
    p.add_argument("--dev-rates", default="5,10,20,60")
    p.add_argument("--lags-ms", default="0,8.33,16.67,25")
    args = p.parse_args(argv)
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    lo, hi = (int(v) for v in args.dev_seeds.split("-"))
    load0 = os.getloadavg()[0]
    t0 = time.monotonic()
    demo_md, demo = demo_table([float(v) for v in args.demo_rates.split(",")], cache)
    dev_md, dev = dev_table(list(range(lo, hi + 1)),
                            [float(v) for v in args.dev_rates.split(",")], cache)
    lag_md, lag = lag_table([float(v) for v in args.lags_ms.split(",")], 120.0, cache)
    elapsed = time.monotonic() - t0
    command = "python benchmarks/bench_palpation_density.py " + " ".join(sys.argv[1:])
    head = (f"Command: `{command}` ({elapsed:.0f} s; `nproc` {os.cpu_count()}, load average "
            f"{load0:.1f} at start, other jobs may share the machine; the figures are "
            "simulated-time results and do not depend on the load).")
    text = "\n\n".join([head, "### 1. The demo's session against the frame rate", demo_md,
                        "### 2. Development phantoms against the frame rate", dev_md,
                        "### 3. A lag between the frame's image and its position", lag_md])
    print(text)
    if args.write:
        out = Path(args.write)
        out.write_text(text + "\n")
        out.with_suffix(".json").write_text(json.dumps(
            {"demo": demo, "dev": dev, "lag": lag, "command": command}, indent=1,
            default=float))
        plot(demo, dev, lag, out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
