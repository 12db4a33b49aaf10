"""Score palpation findings against a phantom's ground truth.

Findings are matched one-to-one to ground-truth tumors by minimum total distance (Hungarian
assignment, :func:`scipy.optimize.linear_sum_assignment`); a pair further apart than
``max_match_mm`` is no match. Severity agreement is Kendall's tau-b
(:func:`scipy.stats.kendalltau`) between the true ``severity_rank`` and the finding's rank
over the matched tumors that have a true rank.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.stats import kendalltau

from local_site.palpation.findings import Finding
from shared.errors import InputDataError

__all__ = ["score_findings"]


def _tumors(ground_truth: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    tumors = ground_truth.get("tumors")
    if not isinstance(tumors, list):
        raise InputDataError("ground truth has no 'tumors' list")
    for t in tumors:
        if not isinstance(t, Mapping) or "center_mm" not in t or "id" not in t:
            raise InputDataError("each ground-truth tumor needs 'id' and 'center_mm'")
    return tumors


def score_findings(findings: Sequence[Finding], ground_truth: Mapping[str, Any], *,
                   max_match_mm: float = 8.0) -> dict[str, Any]:
    """Compare findings with the ground truth.

    Args:
        findings: what the analysis found (phantom coordinates).
        ground_truth: the phantom's ground-truth JSON (``tumors`` with ``id``,
            ``center_mm``, ``kind`` and optional ``severity_rank``).
        max_match_mm: largest distance at which a finding counts as that tumor.

    Returns:
        A JSON-able dict: ``tumors_expected``, ``tumors_found``, ``false_positives``,
        ``localization_error_mm`` (``mean``, ``max``, ``per_tumor``), ``types_correct``,
        ``types_total``, ``kendall_tau`` (None when fewer than two ranked matches) and
        ``matches`` (per tumor: found position, error, true and found kind and rank).

    Raises:
        InputDataError: a malformed ground truth.
    """
    tumors = _tumors(ground_truth)
    truth_xy = np.array([[float(c) for c in t["center_mm"]] for t in tumors]).reshape(-1, 2)
    found_xy = np.array([f.center_mm for f in findings], dtype=float).reshape(-1, 2)
    pairs: list[tuple[int, int, float]] = []
    if len(tumors) and len(findings):
        dist = np.hypot(truth_xy[:, None, 0] - found_xy[None, :, 0],
                        truth_xy[:, None, 1] - found_xy[None, :, 1])
        rows, cols = linear_sum_assignment(dist)
        pairs = [(int(r), int(c), float(dist[r, c])) for r, c in zip(rows, cols, strict=True)
                 if dist[r, c] <= max_match_mm]
    matches = []
    errors: dict[str, float] = {}
    types_correct = 0
    ranked_true: list[int] = []
    ranked_found: list[int] = []
    for r, c, d in pairs:
        t, f = tumors[r], findings[c]
        errors[str(t["id"])] = d
        types_correct += int(t.get("kind") == f.kind)
        if t.get("severity_rank") is not None:
            ranked_true.append(int(t["severity_rank"]))
            ranked_found.append(f.severity_rank)
        matches.append({"id": t["id"], "true_center_mm": [float(v) for v in t["center_mm"]],
                        "found_center_mm": list(f.center_mm), "error_mm": d,
                        "true_kind": t.get("kind"), "found_kind": f.kind,
                        "true_severity_rank": t.get("severity_rank"),
                        "found_severity_rank": f.severity_rank})
    tau: float | None = None
    if len(ranked_true) >= 2:
        value = kendalltau(ranked_true, ranked_found).statistic
        tau = float(value) if math.isfinite(value) else None
    errs = list(errors.values())
    return {
        "tumors_expected": len(tumors),
        "tumors_found": len(pairs),
        "false_positives": len(findings) - len(pairs),
        "localization_error_mm": {
            "mean": float(np.mean(errs)) if errs else None,
            "max": float(np.max(errs)) if errs else None,
            "per_tumor": errors,
        },
        "types_correct": types_correct,
        "types_total": len(pairs),
        "kendall_tau": tau,
        "matches": matches,
    }
