"""Palpation benchmark: many random phantoms per scene and link profile, through the real system.

Each run is a full :func:`~lab.demo.orchestrator.run_demo` session (separate relay,
link-emulator and station processes over real sockets). Per scene and link profile it
reports detection rate, localization error (mean, p95), type accuracy, Kendall's tau and
the motion-to-touch latency (p50/p99 of the per-run p50/p99, and the worst p99).

With ``--ood`` it runs the out-of-distribution benchmark instead
(:mod:`lab.bench.palpation_ood`): phantom families varying one factor at a time, each session
simulated in-process (the station's pipeline in simulated time, no network), scored in
phantom coordinates; results in ``palpation_ood.md`` / ``.json`` / ``.png``.

examples:
  teletouch bench palpation --runs 20 --write-results benchmarks/results
  teletouch bench palpation --quick --json
  teletouch bench palpation --ood --runs 10 --first-seed 2000 --write-results benchmarks/results
  teletouch bench palpation --ood --quick
"""

from __future__ import annotations

import argparse
import math
import platform
import time
from pathlib import Path
from typing import Any

__all__ = ["configure_parser", "run", "summarise"]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's flags."""
    parser.add_argument("--runs", type=int, default=20,
                        help="random phantoms (seeds) per scene and profile (default 20)")
    parser.add_argument("--scenes", default="localization,severity,breast",
                        help="comma-separated scenes (default: all three)")
    parser.add_argument("--links", default="lan,city-1000km",
                        help="comma-separated link profiles (default lan,city-1000km)")
    parser.add_argument("--first-seed", type=int, default=100,
                        help="seeds are first-seed .. first-seed + runs - 1 (default 100)")
    parser.add_argument("--quick", action="store_true", help="2 runs per cell")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--write-results", default=None, metavar="DIR",
                        help="write palpation.md, palpation.json and palpation.png there "
                             "(--ood: palpation_ood.*)")
    parser.add_argument("--ood", action="store_true",
                        help="out-of-distribution families, simulated in-process (fast)")
    parser.add_argument("--families", default=None,
                        help="--ood: comma-separated families (default: all)")
    parser.add_argument("--ideal", action="store_true",
                        help="--ood: the noise-free world (default: realistic)")
    parser.add_argument("--no-register", dest="register", action="store_false",
                        help="--ood: no fiducial registration (analyse in the designed map)")
    parser.add_argument("--cache", default=None, metavar="DIR",
                        help="--ood: keep simulated recordings here and reuse them")
    parser.add_argument("--map-config", default="", metavar="NAME=VALUE,...",
                        help="--ood: MapConfig overrides for the analysis, e.g. "
                             "signal_percentile=50")
    parser.add_argument("--detection-config", default="", metavar="NAME=VALUE,...",
                        help="--ood: DetectionConfig overrides for the analysis, e.g. "
                             "malignant_ref_edge_mm=0.75")


def _pct(values: list[float], q: float) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if not finite:
        return None
    import numpy as np

    return float(np.percentile(finite, q))


def summarise(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (scene, link) from individual run reports."""
    cells: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in runs:
        cells.setdefault((r["scene"], r["link"]), []).append(r)
    rows = []
    for (scene, link), rs in sorted(cells.items()):
        ok = [r for r in rs if "error" not in r]
        expected = sum(r["tumors_expected"] for r in ok)
        found = sum(r["tumors_found"] for r in ok)
        errors = [e for r in ok for e in r["localization_error_mm"]["per_tumor"].values()]
        taus = [r["kendall_tau"] for r in ok if r["kendall_tau"] is not None]
        e2e = [r["latency_ms"].get("end_to_end", {}) for r in ok]
        rows.append({
            "scene": scene, "link": link, "runs": len(rs), "failed_runs": len(rs) - len(ok),
            "detection_rate": found / expected if expected else None,
            "false_positives": sum(r["false_positives"] for r in ok),
            "loc_error_mean_mm": sum(errors) / len(errors) if errors else None,
            "loc_error_p95_mm": _pct(errors, 95),
            "type_accuracy": (sum(r["types_correct"] for r in ok)
                              / max(1, sum(r["types_total"] for r in ok))),
            "tau_mean": sum(taus) / len(taus) if taus else None,
            "tau_min": min(taus) if taus else None,
            "e2e_p50_ms": _pct([x.get("p50") for x in e2e], 50),
            "e2e_p99_ms_median": _pct([x.get("p99") for x in e2e], 50),
            "e2e_p99_ms_worst": max((x.get("p99") or 0.0 for x in e2e), default=None),
        })
    return rows


def _plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    labels = [f"{r['scene']}\n{r['link']}" for r in rows]
    axes[0].bar(labels, [r["loc_error_mean_mm"] or 0 for r in rows], label="mean")
    axes[0].plot(labels, [r["loc_error_p95_mm"] or 0 for r in rows], "k^", label="p95")
    axes[0].axhline(1.5, color="r", ls="--", label="target mean 1.5 mm")
    axes[0].set_ylabel("localization error (mm)")
    axes[0].legend()
    axes[1].bar(labels, [r["e2e_p99_ms_median"] or 0 for r in rows], label="p99 (median run)")
    axes[1].plot(labels, [r["e2e_p99_ms_worst"] or 0 for r in rows], "k^", label="p99 worst run")
    axes[1].axhline(50, color="r", ls="--", label="target p99 50 ms (city)")
    axes[1].set_ylabel("motion-to-touch latency (ms)")
    axes[1].legend()
    for ax in axes:
        ax.tick_params(axis="x", labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _write(out: Path, runs: list[dict[str, Any]], command: str, elapsed_s: float) -> None:
    from lab.bench.results import write_results
    from shared.report import format_table

    rows = summarise(runs)
    write_results(out, "palpation", (
        "# Palpation benchmark\n\n"
        f"Machine: {platform.machine()} {platform.system()}, 2 cores shared, no GPU. "
        f"Command: `{command}` ({len(runs)} runs, {elapsed_s:.0f} s). Each run is a full "
        "`teletouch demo` session (relay, link emulators, both stations as processes); "
        "latency is the local station's motion-to-touch ledger, per run p50/p99, then the "
        "median (or worst) over runs.\n\n" + format_table(rows)),
        data={"rows": rows, "runs": runs}, plot=lambda path: _plot(rows, path))


def _run_ood(args: argparse.Namespace) -> int:
    import logging
    import os

    for name in ("shared.devices", "remote_site"):  # one line per session is enough
        logging.getLogger(name).setLevel(logging.WARNING)

    from lab.bench.palpation_ood import (
        FAMILIES,
        config_overrides,
        configured_analysis,
        failures,
        make_case,
        plot_ood,
        run_case,
        summarise_ood,
    )
    from shared.report import emit, emit_json, format_table

    n = 2 if args.quick else args.runs
    families = args.families.split(",") if args.families else list(FAMILIES)
    unknown = sorted(set(families) - set(FAMILIES))
    if unknown:
        from shared.errors import ConfigError

        raise ConfigError(f"unknown OOD families {unknown}; known: {list(FAMILIES)}")
    cache = Path(args.cache) if args.cache else None
    from local_site.palpation import DetectionConfig, MapConfig

    analyse = configured_analysis(config_overrides(MapConfig, args.map_config),
                                  config_overrides(DetectionConfig, args.detection_config))
    command = (f"teletouch bench palpation --ood --runs {n} --first-seed {args.first_seed}"
               + (f" --families {args.families}" if args.families else "")
               + (" --ideal" if args.ideal else "")
               + ("" if args.register else " --no-register")
               + (f" --map-config {args.map_config}" if args.map_config else "")
               + (f" --detection-config {args.detection_config}"
                  if args.detection_config else ""))
    load_start = os.getloadavg()[0]
    started = time.monotonic()
    runs: list[dict[str, Any]] = []
    for i in range(n):  # indices outermost: an interrupted run covers every family
        for family in families:
            case = make_case(family, i, n, args.first_seed + i, ideal=args.ideal)
            result = run_case(case, cache, analyse, register=args.register)
            runs.append(result)
            emit(f"[{time.monotonic() - started:6.0f} s] {family} #{i} factor "
                 f"{case.factor:.3g}: " + (result.get("error", "") or
                 f"found {sum(x['found'] for x in result['inclusions'])}/"
                 f"{len(result['inclusions'])}, fp {result['false_positives']}"))
    rows = summarise_ood(runs)
    if args.write_results:
        from lab.bench.results import write_results
        from shared.report import format_table as table

        elapsed = time.monotonic() - started
        lines = "\n".join(f"- {f}" for f in failures(runs)) or "- none"
        write_results(args.write_results, "palpation_ood", (
            "# Out-of-distribution palpation benchmark\n\n"
            f"Command: `{command}` ({len(runs)} sessions, {elapsed:.0f} s). Machine: "
            f"{platform.machine()} {platform.system()}, {os.cpu_count()} cores, "
            f"load average {load_start:.1f} at start. Each session is simulated "
            "in-process (lab/bench/palpation_session.py: the station's pipeline in simulated "
            "time, no network) and analysed with the local station's analysis; errors are in "
            "PHANTOM coordinates. Families: lab/bench/palpation_ood.py. `detection_target`: "
            "inclusions with radius >= 3 mm, depth <= 12 mm, contrast >= 2x.\n\n"
            + table(rows) + "\n\n## Failures\n\n" + lines),
            data={"rows": rows, "runs": runs}, plot=lambda path: plot_ood(runs, path))
    if args.json:
        emit_json({"rows": rows})
    else:
        emit(format_table(rows))
    return 0


def run(args: argparse.Namespace) -> int:
    """Run the benchmark."""
    if args.ood:
        return _run_ood(args)
    from lab.demo.orchestrator import DemoConfig, DemoError, run_demo
    from shared.report import emit, emit_json, format_table

    n = 2 if args.quick else args.runs
    scenes = [s for s in args.scenes.split(",") if s]
    links = [s for s in args.links.split(",") if s]
    runs: list[dict[str, Any]] = []
    started = time.monotonic()
    command = (f"teletouch bench palpation --runs {n} --scenes {args.scenes} --links "
               f"{args.links} --first-seed {args.first_seed}"
               + (f" --write-results {args.write_results}" if args.write_results else ""))
    # seeds outermost: an interrupted run still has results for every cell
    for seed in range(args.first_seed, args.first_seed + n):
        for link in links:
            for scene in scenes:
                try:
                    report = run_demo(DemoConfig(scene=scene, seed=seed, link=link))
                    report = {k: v for k, v in report.items()
                              if k not in ("local", "remote", "relay", "findings")}
                except DemoError as err:
                    report = {"scene": scene, "link": link, "seed": seed, "error": str(err)}
                runs.append(report)
                emit(f"[{time.monotonic() - started:6.0f} s] {scene} seed {seed} {link}: "
                     + (report.get("error", "")[:200] or
                        f"found {report['tumors_found']}/{report['tumors_expected']}, "
                        f"err {report['localization_error_mm']['mean']}, "
                        f"tau {report['kendall_tau']}"))
                if args.write_results:
                    _write(Path(args.write_results), runs, command, time.monotonic() - started)
    rows = summarise(runs)
    if args.json:
        emit_json({"rows": rows})
    else:
        emit(format_table(rows))
    return 0
