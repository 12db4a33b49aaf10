"""The demo's two tumors typed from fewer frames, deterministically (issue 10).

A loaded machine delivers fewer tactile frames to the analysis. Instead of loading the
machine, the demo's session (breast seed 0, the small raster of ``test_demo_cli``) is
simulated in-process (:func:`lab.bench.palpation_session.simulate_session`, the station's
own pipeline in simulated time) at a low and a high frame rate. The typing must not move
with the rate: the benign tumor is typed benign at both; the malignant one, only partly
inside the raster, is never called benign.
"""

from __future__ import annotations

import functools
import math

import pytest

from lab.bench.palpation_session import Operator, simulate_session
from lab.scoring import score_findings
from local_site.palpation import Finding, analyse_recording
from remote_site.agent.world import REALISTIC, Registration, world_for
from remote_site.phantom.phantom_file import resolve_phantom
from shared.workspace import WorkspaceMap

#: the demo test's SMALL_RASTER (platform mm), without its initial 3 s hold
DEMO_RASTER = Operator(region=(20.0, 52.0, 4.0, 36.0), spacing_mm=4.0, speed_mm_s=45.0,
                       press_z_mm=10.0)


@functools.cache
def _session(rate_hz: float) -> tuple[list[Finding], dict]:
    world = world_for(resolve_phantom("breast", 0), REALISTIC, 0, Registration())
    rec = simulate_session(world, DEMO_RASTER, workspace=WorkspaceMap(), frame_rate_hz=rate_hz)
    findings = analyse_recording(rec, WorkspaceMap())
    return findings, world.phantom.ground_truth()


def _matched(rate_hz: float, tumor_id: str) -> Finding:
    findings, truth = _session(rate_hz)
    score = score_findings(findings, truth)
    m = next(m for m in score["matches"] if m["id"] == tumor_id)
    return min(findings, key=lambda f: math.dist(f.center_mm, m["found_center_mm"]))


@pytest.mark.parametrize("rate_hz", [6.0, 30.0])
def test_demo_benign_typed_benign_at_low_and_high_frame_rate(rate_hz: float) -> None:
    findings, truth = _session(rate_hz)
    score = score_findings(findings, truth)
    assert score["false_positives"] == 0
    benign = _matched(rate_hz, "benign")
    assert benign.kind == "benign", benign
    # the malignant tumor lies at the raster's corner: at 30 frames/s it is found and, its
    # disc less than 90 % covered and its rim unmeasured, typed uncertain; at 6 frames/s
    # (49 frames) it is missed. Never is it called benign.
    assert all(m["found_kind"] != "benign" for m in score["matches"] if m["id"] == "malignant")


def test_partly_felt_malignant_is_uncertain_not_mistyped() -> None:
    findings, truth = _session(30.0)
    assert score_findings(findings, truth)["tumors_found"] == 2
    malignant = _matched(30.0, "malignant")
    assert malignant.coverage < 0.9 and malignant.kind == "uncertain"
    assert malignant.likely_kind in ("malignant", "uncertain")


def test_benign_score_does_not_move_with_the_frame_rate() -> None:
    low, high = _matched(6.0, "benign"), _matched(30.0, "benign")
    # 5x fewer frames: the edge width and the score stay within their noise
    assert abs(low.edge_width_mm - high.edge_width_mm) <= 4.0 * math.hypot(
        low.edge_width_se_mm, high.edge_width_se_mm)
    assert low.malignant_score == pytest.approx(high.malignant_score, rel=0.15)
