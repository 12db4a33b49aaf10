"""Where a press's image puts its contact circle, independently of any calibration.

A ball pressed into the gel shows a ring where the colour change falls off sharply: the
contact edge, where the gel leaves the ball. This module finds that ring from the frame and
the no-contact background alone (no colour-to-slope model, no integration), to check hand
labels against the image they were drawn on:

1. the relative colour change's magnitude ``m`` (:func:`.features.relative_change`, already
   smoothed) and its gradient magnitude ``|grad m|`` (Sobel);
2. along ``N_RAYS`` rays from the current centre, the radius in ``SEARCH`` x the current
   radius where ``|grad m|`` peaks, refined to a fraction of a pixel by a parabola through
   the peak and its neighbours; rays that leave the frame are skipped;
3. a least-squares circle through those points (Kasa's algebraic fit), refitted once without
   the points further than ``OUTLIER_MAD`` robust deviations from it;
4. steps 2-3 again from the new circle, ``ITERATIONS`` times in all, so the result does not
   hang on where the search started.

:func:`refine_centre` moves a hand label's centre onto that circle when the fit is
trustworthy (tight, and near the label); the calibration trains on the moved centres by
default (:func:`.calibration.fit_calibration`, ``centres="edge"``). The radius stays as
labelled: it only bounds the training region (after ``trim_px``), while the centre sets every
training slope.

Checked against simulated presses with known centres, under two light layouts
(``tests/remote_site/test_contact_edge.py``), and on the kit's real GelSight Mini presses
against their hand labels (``benchmarks/bench_label_agreement.py``).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import cv2
import numpy as np

from remote_site.reconstruction.labels import BallLabel

__all__ = ["MAX_FIT_RMS_PX", "MAX_MOVE_FRACTION", "MIN_RAYS", "ContactEdge",
           "fit_contact_edge", "refine_centre"]

#: rays cast from the centre
N_RAYS = 90
#: radii searched along a ray, as a fraction of the current radius
SEARCH = (0.6, 1.4)
#: radial sampling step along a ray, pixels
STEP_PX = 0.25
#: fits of the circle, each searching around the previous one
ITERATIONS = 3
#: edge points further from the circle than this many robust deviations are dropped once
OUTLIER_MAD = 3.0
#: fewer rays inside the frame than this and there is no fit (a contact mostly off the frame)
MIN_RAYS = 24
#: circles smaller than this (px) are not searched: too few samples along a ray
MIN_RADIUS_PX = 3.0
#: a refined centre is used only if the edge points lie this close to their circle (RMS) ...
MAX_FIT_RMS_PX = 2.5
#: ... and it moves the centre by at most this fraction of the labelled radius
MAX_MOVE_FRACTION = 0.25


class ContactEdge(NamedTuple):
    """The contact circle seen in a frame, pixels."""

    center_x: float
    center_y: float
    radius_px: float
    #: rays whose edge point was used in the last fit
    rays: int
    #: RMS distance of those points from the circle
    rms_px: float


def fit_contact_edge(change_pct: np.ndarray, start: BallLabel) -> ContactEdge | None:
    """The contact edge nearest ``start`` (a rough circle, e.g. a hand label), or None.

    Args:
        change_pct: (H, W, 3) relative colour change of the press from its background,
            percent (:func:`.features.relative_change`).
        start: where to look first; its centre and radius seed the search.

    Returns:
        None when fewer than ``MIN_RAYS`` rays stay inside the frame.
    """
    magnitude = np.linalg.norm(np.asarray(change_pct, np.float32), axis=2)
    edge = cv2.magnitude(cv2.Sobel(magnitude, cv2.CV_32F, 1, 0, ksize=3),
                         cv2.Sobel(magnitude, cv2.CV_32F, 0, 1, ksize=3))
    cx, cy, radius = float(start.center_x), float(start.center_y), float(start.radius_px)
    fit: ContactEdge | None = None
    for _ in range(ITERATIONS):
        points = _edge_points(edge, cx, cy, radius)
        if len(points) < MIN_RAYS:
            return fit
        fit = _robust_circle(points)
        cx, cy, radius = fit.center_x, fit.center_y, fit.radius_px
    return fit


def refine_centre(change_pct: np.ndarray, label: BallLabel) -> BallLabel | None:
    """``label`` with its centre on the contact edge the image shows, or None when the edge
    fit is missing, loose (RMS above ``MAX_FIT_RMS_PX``) or far from the label (more than
    ``MAX_MOVE_FRACTION`` of its radius): then the label is kept as it is.

    On the kit's GelSight Mini presses the fit moves the hand-labelled centres by 1.75 px on
    average (up to 4.2 px) and none is refused (``benchmarks/results/label_agreement.md``).
    """
    edge = fit_contact_edge(change_pct, label)
    if edge is None or edge.rms_px > MAX_FIT_RMS_PX:
        return None
    moved = float(np.hypot(edge.center_x - label.center_x, edge.center_y - label.center_y))
    if moved > MAX_MOVE_FRACTION * label.radius_px:
        return None
    return dataclasses.replace(label, center_x=edge.center_x, center_y=edge.center_y)


def _edge_points(edge: np.ndarray, cx: float, cy: float, radius: float) -> np.ndarray:
    """(n, 2) x, y of the strongest edge along each ray that stays inside the frame."""
    h, w = edge.shape
    if not (np.isfinite([cx, cy, radius]).all() and radius >= MIN_RADIUS_PX):
        return np.empty((0, 2))  # a degenerate circle (a start or a fit): nothing to search
    theta = np.linspace(0.0, 2.0 * np.pi, N_RAYS, endpoint=False)
    radii = np.arange(SEARCH[0] * radius, SEARCH[1] * radius, STEP_PX, dtype=np.float32)
    xs = cx + np.cos(theta)[:, None] * radii[None, :]
    ys = cy + np.sin(theta)[:, None] * radii[None, :]
    inside = ((xs >= 1) & (xs <= w - 2) & (ys >= 1) & (ys <= h - 2)).all(axis=1)
    if not inside.any():
        return np.empty((0, 2))
    xs, ys = xs[inside], ys[inside]
    values = cv2.remap(edge, xs.astype(np.float32), ys.astype(np.float32), cv2.INTER_LINEAR)
    peak = np.argmax(values, axis=1)
    # a peak at either end of the search is the search's limit, not an edge
    keep = (peak > 0) & (peak < len(radii) - 1)
    rows = np.nonzero(keep)[0]
    peak = peak[keep]
    left, mid, right = (values[rows, peak - 1], values[rows, peak], values[rows, peak + 1])
    curvature = left - 2.0 * mid + right
    with np.errstate(divide="ignore", invalid="ignore"):
        offset = np.where(curvature < 0, 0.5 * (left - right) / curvature, 0.0)
    r = radii[peak] + np.clip(offset, -0.5, 0.5) * STEP_PX
    angle = theta[inside][rows]
    return np.column_stack([cx + r * np.cos(angle), cy + r * np.sin(angle)])


def _circle(points: np.ndarray) -> tuple[float, float, float]:
    """Kasa's algebraic least-squares circle (centre x, y, radius)."""
    a = np.column_stack([2.0 * points, np.ones(len(points))])
    b = (points**2).sum(axis=1)
    (x, y, c), *_ = np.linalg.lstsq(a, b, rcond=None)
    return float(x), float(y), float(np.sqrt(max(c + x * x + y * y, 0.0)))


def _robust_circle(points: np.ndarray) -> ContactEdge:
    x, y, r = _circle(points)
    dist = np.hypot(points[:, 0] - x, points[:, 1] - y) - r
    mad = 1.4826 * float(np.median(np.abs(dist - np.median(dist))))
    keep = np.abs(dist) <= OUTLIER_MAD * max(mad, 0.1)
    if MIN_RAYS <= keep.sum() < len(points):
        points = points[keep]
        x, y, r = _circle(points)
        dist = np.hypot(points[:, 0] - x, points[:, 1] - y) - r
    return ContactEdge(x, y, r, len(points), float(np.sqrt(np.mean(dist**2))))
