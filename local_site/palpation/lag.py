"""A lag between each frame's image and the position it is stamped with: estimated, corrected.

When the remote station stamps a frame with the arm's position read a little before (or
after) the image was taken, everything felt while moving is displaced along the motion by
``speed x lag``: backward on a pass in one direction, forward on the way back. On a loaded
machine the gap between the two reads grows (ms of preemption), and a displacement that
alternates with the raster's passes widens every boundary as a graded (malignant) one
would. The recording itself shows it: the relief seen from the passes in one direction is
shifted against the relief seen from the passes in the other by twice the lag distance.

:func:`estimate_lag_mm` builds the maps of the frames moving forward and of those moving
backward along the main motion axis, finds the tumors in each, and returns half of their
mean displacement (matched by nearest centre, weighted by severity) projected on the axis
(platform mm, positive = the stamps lag behind the images). The findings' centroids are
used, not a cross-correlation of the whole relief: the relief also carries patterns tied
to the scanned area's outline, which do not move with the lag and pull a correlation
toward zero.
:func:`correct_lag` moves every frame forward along its own direction of motion by that
distance (a constant speed is assumed, as in a raster). Where the estimate is not
possible (too few frames either way, no finding seen from both) it returns None and
nothing is corrected.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from local_site.palpation.findings import find_tumors
from local_site.palpation.maps import MapConfig, PalpationMaps, build_maps
from local_site.recording import Recording
from shared.errors import InputDataError
from shared.workspace import WorkspaceMap

__all__ = ["correct_lag", "estimate_lag_mm", "motion_directions"]

_MIN_COVERAGE = 0.9
_FRAME_FIELDS = ("frame_center_mm", "frame_pitch_mm", "frame_contact", "frame_force_n",
                 "frame_indentation_mm", "frame_height_mm")


def motion_directions(centers_mm: NDArray[np.float64], min_step_mm: float = 0.05
                      ) -> NDArray[np.float64]:
    """Unit direction of motion of each frame (central differences of the stamped
    centres); zero where the frame moved less than ``min_step_mm`` per frame."""
    if centers_mm.shape[0] < 3:
        return np.zeros_like(centers_mm)
    step = np.gradient(centers_mm, axis=0)
    norm = np.hypot(step[:, 0], step[:, 1])
    out = np.zeros_like(centers_mm)
    moving = norm >= min_step_mm
    out[moving] = step[moving] / norm[moving, None]
    return out


def _subset(rec: Recording, keep: NDArray[np.bool_]) -> Recording:
    fields = {k: getattr(rec, k)[keep] for k in _FRAME_FIELDS}
    fields["frame_rx_us"] = rec.frame_rx_us[keep] if rec.frame_rx_us.size else rec.frame_rx_us
    fields["frame_seq"] = rec.frame_seq[keep] if rec.frame_seq.size else rec.frame_seq
    return replace(rec, frame_stiffness_k=None, frame_stiffness_n_per_mm=None, **fields)


def _shift_mm(a: PalpationMaps, b: PalpationMaps, match_mm: float) -> NDArray[np.float64] | None:
    """Mean shift (phantom x, y mm) of the findings of map ``a`` against the same findings
    in map ``b`` (matched by nearest centre, each at least 90 % covered in both), weighted
    by their severity; None if none."""
    # only findings wholly felt in both: a partly felt one's centroid moves with what was
    # felt of it, not with the lag
    fa = [f for f in find_tumors(a) if f.coverage >= _MIN_COVERAGE]
    fb = [f for f in find_tumors(b) if f.coverage >= _MIN_COVERAGE]
    shifts, weights = [], []
    for f in fa:
        if not fb:
            break
        g = min(fb, key=lambda g: math.dist(f.center_mm, g.center_mm))
        if math.dist(f.center_mm, g.center_mm) <= match_mm:
            shifts.append(np.subtract(f.center_mm, g.center_mm))
            weights.append(min(f.severity_score, g.severity_score))
    if not shifts:
        return None
    return np.average(np.asarray(shifts), axis=0, weights=np.asarray(weights))


def estimate_lag_mm(rec: Recording, workspace: WorkspaceMap,
                    config: MapConfig | None = None, *, min_frames: int = 30,
                    match_mm: float = 4.0) -> float | None:
    """The lag distance (platform mm along the motion; positive when the stamped position
    is behind the image), or None when it cannot be estimated (module docstring)."""
    u = motion_directions(rec.frame_center_mm)
    moving = np.hypot(u[:, 0], u[:, 1]) > 0
    if moving.sum() < 2 * min_frames:
        return None
    # main motion axis (sign-free): the leading eigenvector of sum u u^T
    _, vecs = np.linalg.eigh(u[moving].T @ u[moving])
    axis = vecs[:, -1]
    along = u @ axis
    forward, backward = moving & (along > 0.7), moving & (along < -0.7)
    if forward.sum() < min_frames or backward.sum() < min_frames:
        return None
    cfg = config or MapConfig()
    try:
        fwd = build_maps(_subset(rec, forward), workspace, cfg)
        bwd = build_maps(_subset(rec, backward), workspace, cfg)
    except InputDataError:
        return None
    shift = _shift_mm(fwd, bwd, match_mm)
    if shift is None:
        return None
    # the axis in phantom coordinates (the map's linear part)
    z = workspace.config.z_surface_mm
    p0 = workspace.forward_unclamped(np.array([[0.0, 0.0, z], [axis[0], axis[1], z]]))
    axis_ph = p0[1, :2] - p0[0, :2]
    scale = float(np.hypot(*axis_ph))
    # forward frames stamped behind: their features appear moved by -lag along the axis
    return -float(np.dot(shift, axis_ph / scale)) / 2.0 / scale


def correct_lag(rec: Recording, lag_mm: float) -> Recording:
    """The recording with every moving frame's centre moved ``lag_mm`` along its motion."""
    u = motion_directions(rec.frame_center_mm)
    return replace(rec, frame_center_mm=rec.frame_center_mm + lag_mm * u)
