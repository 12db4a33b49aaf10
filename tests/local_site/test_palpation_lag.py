"""The image <-> position lag: estimated from passes in opposite directions and corrected.

Recordings synthesised from the phantom's contact model (``test_palpation.synthetic``: a
raster along x, 0.75 mm between frames, lines alternating direction), then every frame
stamped with the position of the frame ``k`` before it: a lag of ``0.75 k`` mm along the
motion, what a station that reads the arm some ms before it takes the image produces.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lab.scoring import score_findings
from local_site.palpation import (
    Recording,
    analyse_recording,
    correct_lag,
    estimate_lag_mm,
)
from local_site.palpation.lag import motion_directions
from shared.workspace import WorkspaceMap
from tests.local_site.test_palpation import synthetic

STEP_MM = 0.75


def lagged(rec: Recording, frames: int) -> Recording:
    centres = rec.frame_center_mm.copy()
    if frames:
        centres[frames:] = rec.frame_center_mm[:-frames]
    return replace(rec, frame_center_mm=centres)


def test_motion_directions_of_a_raster() -> None:
    rec, _ = synthetic("breast", 3)
    u = motion_directions(rec.frame_center_mm)
    norms = np.hypot(u[:, 0], u[:, 1])
    assert np.all((np.abs(norms - 1.0) < 1e-9) | (norms == 0))
    along_x = np.abs(u[:, 0]) > 0.99
    assert along_x.mean() > 0.9  # the line changes are the only frames not along x
    # 11 lines one way, 10 the other
    assert (u[along_x, 0] > 0).sum() == pytest.approx((u[along_x, 0] < 0).sum() * 1.1, rel=0.05)


@pytest.mark.parametrize("frames", [0, 1, 2])
def test_lag_estimated(frames: int) -> None:
    rec, _ = synthetic("breast", 3)
    lag = estimate_lag_mm(lagged(rec, frames), WorkspaceMap())
    assert lag is not None
    assert lag == pytest.approx(frames * STEP_MM, abs=0.1 + 0.1 * frames * STEP_MM)


def test_lagged_recording_corrected_types_and_locates_as_without_lag() -> None:
    rec, truth = synthetic("breast", 3)
    bad = lagged(rec, 2)  # 1.5 mm
    raw = analyse_recording(bad, WorkspaceMap(), lag_correction=False)
    fixed = analyse_recording(bad, WorkspaceMap())
    clean = score_findings(analyse_recording(rec, WorkspaceMap()), truth)
    got = score_findings(fixed, truth)
    assert got["types_correct"] == clean["types_correct"] == 2
    assert got["localization_error_mm"]["max"] < 0.6
    # uncorrected, every edge is smeared along x by the alternating passes
    width = {f.center_mm: f.edge_width_mm for f in raw}
    fixed_width = {f.center_mm: f.edge_width_mm for f in fixed}
    assert min(width.values()) > max(fixed_width.values()) or np.mean(
        list(width.values())) > 1.15 * np.mean(list(fixed_width.values()))


def test_no_estimate_without_opposite_passes() -> None:
    rec, _ = synthetic("breast", 3)
    u = motion_directions(rec.frame_center_mm)
    one_way = u[:, 0] >= 0
    fields = ("frame_center_mm", "frame_pitch_mm", "frame_contact", "frame_force_n",
              "frame_indentation_mm", "frame_height_mm")
    single = replace(rec, **{k: getattr(rec, k)[one_way] for k in fields})
    # the kept frames jump back between lines, but no pass runs the other way
    assert estimate_lag_mm(single, WorkspaceMap()) is None
    same = correct_lag(rec, 0.0)
    np.testing.assert_array_equal(same.frame_center_mm, rec.frame_center_mm)
