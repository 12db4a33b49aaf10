"""Is the palpation typing's abstention calibrated? Per-finding typing evidence on cached OOD
sessions (issue 10: type accuracy where coverage of a finding is incomplete).

For every inclusion of every CACHED session of the chosen OOD families (never simulated
here: a missing session is counted and skipped), the local station's analysis is run as the
benchmark runs it (:func:`lab.bench.palpation_ood.default_analysis`) and the matched
finding's typing evidence is recorded: its type, its forced guess (``likely_kind``, the
sign of the malignant score), the disc and outline coverage, the score's margin in standard
errors and the stated type confidence. The tables then answer:

* for the findings typed ``uncertain``, how often the forced guess was right, by coverage
  and by margin;
* a reliability table: stated type confidence against the observed accuracy of the guess;
* per family: accuracy, ``uncertain``, wrong, confusion, for the analysis as configured.

Usage::

  python -m lab.bench.palpation_typing_coverage --cache DIR --first-seed 6000 --runs 30 \\
      --families type,coverage --out records.json [--config min_coverage=0.5,...] \\
      [--map-config signal_percentile=20]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from lab.bench.palpation_ood import _load, _registration, config_overrides, make_case
from lab.scoring import score_findings
from local_site.palpation import DetectionConfig, MapConfig, analyse_recording
from remote_site.agent.world import world_for
from remote_site.phantom.phantom_file import phantom_from_dict
from shared.workspace import WorkspaceMap

__all__ = ["apply_rule", "collect", "family_table", "reliability_table", "se_scale",
           "sweep_table", "uncertain_table"]

TYPED_FAMILIES = ("type", "free-operator", "coverage", "registration", "noise", "frame-rate")


def collect(families: Iterable[str], first_seed: int, runs: int, cache: Path,
            detection: DetectionConfig | None = None,
            map_config: MapConfig | None = None) -> tuple[list[dict[str, Any]], int]:
    """Per-inclusion typing records of the cached sessions, and how many were missing."""
    records: list[dict[str, Any]] = []
    missing = 0
    for i in range(runs):
        for family in families:
            case = make_case(family, i, runs, first_seed + i)
            path = cache / f"{case.key}.npz"
            if not path.exists():
                missing += 1
                continue
            phantom = phantom_from_dict(case.phantom, case.seed, source=case.key)
            world = world_for(phantom, case.realism, case.seed, case.registration)
            est = _registration(world, path.with_suffix(".reg.json"))
            workspace = WorkspaceMap().registered(est.dx_mm, est.dy_mm, est.yaw_deg)
            findings = analyse_recording(_load(path), workspace, map_config, detection)
            truth = world.phantom.ground_truth()
            score = score_findings(findings, truth)
            by_center = {tuple(f.center_mm): f for f in findings}
            for m in score["matches"]:
                f = by_center[tuple(m["found_center_mm"])]
                records.append({
                    "family": family, "index": i, "seed": case.seed, "factor": case.factor,
                    "id": m["id"], "true_kind": m["true_kind"], "kind": f.kind,
                    "likely_kind": f.likely_kind, "coverage": f.coverage,
                    "boundary_coverage": f.boundary_coverage,
                    "score": f.malignant_score if math.isfinite(f.malignant_score) else None,
                    "log_se": (f.malignant_score_log_se
                               if math.isfinite(f.malignant_score_log_se) else None),
                    "type_confidence": f.type_confidence, "confidence": f.confidence,
                    "edge_width_mm": (f.edge_width_mm if math.isfinite(f.edge_width_mm)
                                      else None),
                    "rim_relief": f.rim_relief if math.isfinite(f.rim_relief) else None})
            for t in truth["tumors"]:
                if t["id"] not in {m["id"] for m in score["matches"]}:
                    records.append({"family": family, "index": i, "seed": case.seed,
                                    "factor": case.factor, "id": t["id"],
                                    "true_kind": t["kind"], "kind": None})
    return records, missing


def margin(r: dict[str, Any]) -> float:
    """The score's distance from 1 in log, over its standard error (0 when unmeasured)."""
    if r.get("score") is None or r.get("log_se") is None or r["log_se"] <= 0:
        return 0.0
    return abs(math.log(r["score"])) / float(r["log_se"])


def apply_rule(records: list[dict[str, Any]], min_coverage: float, min_arc: float,
               k: float) -> list[dict[str, Any]]:
    """The records re-typed offline by the finding's rule with other thresholds: the forced
    guess when the disc coverage >= ``min_coverage``, the outline coverage >= ``min_arc``
    and the margin >= ``k`` standard errors, else ``uncertain`` (the features are as
    recorded, so only the thresholds change)."""
    out = []
    for r in records:
        if r["kind"] is not None:
            ok = (r["coverage"] >= min_coverage and r["boundary_coverage"] >= min_arc
                  and r.get("log_se") is not None and margin(r) >= k)
            r = {**r, "kind": r["likely_kind"] if ok else "uncertain"}
        out.append(r)
    return out


def sweep_table(records: list[dict[str, Any]],
                rules: Iterable[tuple[float, float, float]]) -> str:
    """Accuracy, ``uncertain`` and wrong over the found inclusions, per threshold set
    ``(min_coverage, min_arc, k)``, plus how often the guesses the stricter main rule
    withheld but this one makes are right."""
    lines = ["| min disc coverage | min outline coverage | k (SE) | accuracy | uncertain | "
             "wrong | newly typed: right |", "|---|---|---|---|---|---|---|"]
    base = apply_rule(records, 0.9, 0.0, 2.0)
    for c, a, k in rules:
        rs = apply_rule(records, c, a, k)
        found = [(b, r) for b, r in zip(base, rs, strict=True) if r["kind"] is not None]
        ok = sum(r["kind"] == r["true_kind"] for _, r in found)
        unc = sum(r["kind"] == "uncertain" for _, r in found)
        new = [r for b, r in found if b["kind"] == "uncertain" and r["kind"] != "uncertain"]
        new_ok = sum(r["kind"] == r["true_kind"] for r in new)
        lines.append(f"| {c:g} | {a:g} | {k:g} | {_pct(ok, len(found))} | {unc} | "
                     f"{len(found) - ok - unc} | {_pct(new_ok, len(new))} |")
    return "\n".join(lines)


def se_scale(records: list[dict[str, Any]]) -> tuple[int, float, float]:
    """How far the stated standard error of the log score is from the real scatter.

    The typed families palpate the SAME phantom per index and seed (the pair depends only on
    them), so one inclusion is measured in up to six sessions. For every pair of its
    sessions, ``z = (log s1 - log s2) / sqrt(se1^2 + se2^2)`` would be standard normal if the
    standard errors were right. Returns (pairs, RMS of z, robust scale 1.4826 * median |z|).
    """
    by_inclusion: dict[tuple[int, str], list[tuple[float, float]]] = {}
    for r in records:
        if r["kind"] is not None and r.get("score") and r.get("log_se"):
            by_inclusion.setdefault((r["seed"], r["id"]), []).append(
                (math.log(r["score"]), float(r["log_se"])))
    zs = [(a[0] - b[0]) / math.hypot(a[1], b[1])
          for ms in by_inclusion.values() for a, b in itertools.combinations(ms, 2)]
    if not zs:
        return 0, math.nan, math.nan
    rms = math.sqrt(sum(z * z for z in zs) / len(zs))
    return len(zs), rms, 1.4826 * float(sorted(abs(z) for z in zs)[len(zs) // 2])


def _pct(n: int, d: int) -> str:
    return f"{100.0 * n / d:.0f} % ({n}/{d})" if d else "-"


def family_table(records: list[dict[str, Any]], families: Iterable[str]) -> str:
    """Per family: typed accuracy over the found inclusions, ``uncertain``, wrong, confusion."""
    lines = ["| family | found | accuracy | uncertain | wrong | confusion b->b b->m m->b m->m |",
             "|---|---|---|---|---|---|"]
    fams = list(families)
    for family in [*fams, "all"]:
        rs = [r for r in records if r["kind"] is not None
              and (r["family"] == family or (family == "all" and r["family"] in fams))]
        ok = sum(r["kind"] == r["true_kind"] for r in rs)
        unc = sum(r["kind"] == "uncertain" for r in rs)
        conf = " ".join(str(sum(r["true_kind"] == t and r["kind"] == k for r in rs))
                        for t, k in (("benign", "benign"), ("benign", "malignant"),
                                     ("malignant", "benign"), ("malignant", "malignant")))
        lines.append(f"| {family} | {len(rs)} | {_pct(ok, len(rs))} | {unc} | "
                     f"{len(rs) - ok - unc} | {conf} |")
    return "\n".join(lines)


def _binned(rs: list[dict[str, Any]], key: Callable[[dict[str, Any]], float],
            edges: list[float], label: str) -> list[str]:
    lines = [f"| {label} | findings | guess right | guess unmeasured |", "|---|---|---|---|"]
    for lo, hi in itertools.pairwise(edges):
        b = [r for r in rs if lo <= key(r) < hi]
        right = sum(r["likely_kind"] == r["true_kind"] for r in b)
        none = sum(r["likely_kind"] == "uncertain" for r in b)
        lines.append(f"| {lo:g}-{hi:g} | {len(b)} | {_pct(right, len(b))} | {none} |")
    return lines


def uncertain_table(records: list[dict[str, Any]]) -> str:
    """The findings typed ``uncertain``: how often their forced guess was right, by disc
    coverage, outline coverage and margin."""
    rs = [r for r in records if r["kind"] == "uncertain"]
    out = _binned(rs, lambda r: r["coverage"], [0, 0.5, 0.7, 0.8, 0.9, 1.01],
                  "disc coverage")
    out += ["", *_binned(rs, lambda r: r["boundary_coverage"],
                         [0, 0.25, 0.5, 0.75, 0.9, 1.01], "outline coverage")]
    out += ["", *_binned(rs, margin, [0, 0.5, 1, 1.5, 2, 1e9], "margin (SE)")]
    return "\n".join(out)


def reliability_table(records: list[dict[str, Any]], confidence: Callable[
        [dict[str, Any]], float] = lambda r: float(r["type_confidence"]),
        typed_only: bool = False) -> str:
    """Stated type confidence against the observed accuracy of the forced guess (all found
    inclusions with a measured score, or only those the rule typed)."""
    rs = [r for r in records if r["kind"] is not None and r.get("score") is not None
          and (not typed_only or r["kind"] != "uncertain")]
    lines = ["| stated confidence | findings | mean stated | observed accuracy |",
             "|---|---|---|---|"]
    for lo, hi in ((0.5, 0.6), (0.6, 0.7), (0.7, 0.8), (0.8, 0.9), (0.9, 0.95),
                   (0.95, 0.99), (0.99, 1.01)):
        b = [r for r in rs if lo <= confidence(r) < hi]
        if not b:
            lines.append(f"| {lo:g}-{min(hi, 1):g} | 0 | - | - |")
            continue
        right = sum(r["likely_kind"] == r["true_kind"] for r in b)
        stated = sum(confidence(r) for r in b) / len(b)
        lines.append(f"| {lo:g}-{min(hi, 1):g} | {len(b)} | {stated:.2f} | "
                     f"{_pct(right, len(b))} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Collect records (``--out``) and print the tables."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cache", required=True, type=Path)
    p.add_argument("--first-seed", type=int, required=True)
    p.add_argument("--runs", type=int, required=True)
    p.add_argument("--families", default=",".join(TYPED_FAMILIES))
    p.add_argument("--config", default="", help="DetectionConfig overrides: name=value,...")
    p.add_argument("--map-config", default="", help="MapConfig overrides: name=value,...")
    p.add_argument("--out", type=Path)
    args = p.parse_args(argv)
    families = args.families.split(",")
    records, missing = collect(families, args.first_seed, args.runs, args.cache,
                               config_overrides(DetectionConfig, args.config),
                               config_overrides(MapConfig, args.map_config))
    if args.out:
        args.out.write_text(json.dumps({"missing": missing, "records": records}))
    print(f"missing sessions: {missing}")
    print(family_table(records, families))
    print()
    print(uncertain_table(records))
    print()
    print(reliability_table(records))
    return 0


if __name__ == "__main__":
    sys.exit(main())
