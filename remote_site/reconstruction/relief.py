"""Rim-referenced relief: an object's height above the rim of its contact, not above the free gel.

Why: a reconstruction's zero level is the undeformed gel far from the contact (see
:mod:`.reconstructor`). An object pressed into an elastic gel drags the gel around it down
too (the *drape*): the surface at the edge of the contact already sits below the free gel,
by about half the indentation for an elastic half-space (Hertz: the surface at r = a is at
delta/2), less for a thin gel on a rigid backing. Heights inside the contact measured from
the free gel therefore carry the drape on top of the object's own relief (on the real
GelSight Mini: +0.1..+0.3 mm on 0.3..0.66 mm ball caps). The object's relief is its height
above the contact *rim*: where the gel stops conforming to the object.

Where the rim is, found from the reconstruction itself (no labels at run time): inside the
contact of a convex object the slope grows outwards (a sphere: r / R); beyond the rim the
drape flattens out again, so the rim is where the surface is steepest. The rim height is
the slope-weighted mean height over the raised region (weights ``|grad h| ** power``, power 2):
a soft, grid-independent "height where the gel is steepest" that needs no contour tracing and
no argmax over noisy bins. The reconstruction is smooth at the rim (colour blur, block
pooling, and a calibration that never trains on the outer ``trim_px`` of each contact), so its
steepest contour lies *inside* the true contact edge; the reference is therefore the tangent
continued outwards by ``extension_mm``::

    level = h_rim - extension_mm * s_rim            (clamped to [0, peak])
    relief = max(height - level, 0)

with ``s_rim`` the same-weighted mean slope. ``extension_mm`` is the one fitted parameter:
fitted at calibration on the labelled *training* presses (so that the relief peak equals the
labelled cap depth d = R - sqrt(R^2 - a^2), median over presses), one value per pooling factor
because pooling blunts the slope maximum (:func:`fit_rim_extension`, used by
:mod:`.relief_fit`). Heights below the rim level (the drape) are shown as 0: they are gel,
not object.

Where it applies: objects smaller than the pad pressed into the gel (a ball, a bead, a key:
shape exploration). Not palpation with a pad pressed flat into tissue (the whole pad in
contact, relief = inclusions): there the free-gel zero is right. So it is a calibration
setting (``relief="rim"`` saved by ``teletouch sensor calibrate --relief rim``), never chosen
from the data source. With several separate contacts one level is used for all (the steepest
contours dominate); with a flat indenter the rim is its edge, as wanted.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from shared.errors import CalibrationError, ConfigError

__all__ = ["MAX_FACTOR_BEYOND_FIT", "RELIEF_MODES", "RIM_SLOPE_POWER", "RimStats",
           "extension_for_factor",
           "fit_rim_extension", "rim_level", "rim_stats", "rim_step"]

#: ``"plane"``: heights above the free gel (default); ``"rim"``: above the contact rim.
RELIEF_MODES = ("plane", "rim")
#: weight exponent of the slope in the rim estimate
RIM_SLOPE_POWER = 2.0


class RimStats(NamedTuple):
    """The soft rim of one height map."""

    height_mm: float
    """Slope-weighted mean height of the raised region, mm."""
    slope: float
    """Slope-weighted mean slope magnitude there (dimensionless)."""
    peak_mm: float
    """Highest point of the map, mm."""


def rim_step(shape_hw: tuple[int, ...]) -> int:
    """Subsampling step of the rim estimate: ~60 samples across the short side (the zero
    level's grid); at full resolution 16x fewer pixels for the same rim to ~1e-3 mm."""
    return max(1, min(shape_hw[:2]) // 60)


def rim_stats(height_mm: np.ndarray, gx: np.ndarray, gy: np.ndarray, threshold_mm: float,
              power: float = RIM_SLOPE_POWER, step: int = 1) -> RimStats | None:
    """The soft rim of the raised region (heights above ``threshold_mm``).

    Args:
        height_mm: heights above the free gel, mm.
        gx, gy: slopes dh/dx, dh/dy on the same grid (dimensionless).
        threshold_mm: the raised region is ``height_mm > threshold_mm``.
        power: weight exponent of the slope magnitude.
        step: estimate on every ``step``-th row and column (the peak uses every pixel).

    Returns:
        The :class:`RimStats`, or None when nothing is raised or nothing is sloped (no rim).

    Raises:
        ValueError: shapes differ.
    """
    if height_mm.shape != gx.shape or height_mm.shape != gy.shape:
        raise ValueError(f"height {height_mm.shape} and slopes {gx.shape}, {gy.shape} differ")
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    sub_h = height_mm[::step, ::step]
    raised = sub_h > threshold_mm
    if not raised.any():
        return None
    h = sub_h[raised].astype(np.float64)
    s = np.hypot(gx[::step, ::step][raised].astype(np.float64),
                 gy[::step, ::step][raised].astype(np.float64))
    w = s**power
    total = float(w.sum())
    if not (math.isfinite(total) and total > 0.0):
        return None
    return RimStats(float(w @ h) / total, float(w @ s) / total, float(height_mm.max()))


def rim_level(height_mm: np.ndarray, gx: np.ndarray, gy: np.ndarray, threshold_mm: float,
              extension_mm: float, power: float = RIM_SLOPE_POWER, step: int = 1) -> float:
    """Height of the contact rim above the free gel, mm (0 when there is no rim).

    ``h_rim - extension_mm * s_rim``, clamped to [0, peak]: never below the free gel and
    never above the highest point.
    """
    stats = rim_stats(height_mm, gx, gy, threshold_mm, power, step)
    if stats is None:
        return 0.0
    level = stats.height_mm - extension_mm * stats.slope
    return float(min(max(level, 0.0), stats.peak_mm))


def fit_rim_extension(stats: Sequence[RimStats], depths_mm: Sequence[float]) -> float:
    """The tangent extension making each relief peak equal the known depth (median).

    For a press whose peak above the free gel is ``p``, soft rim ``(h, s)`` and known
    object depth ``d``: ``p - (h - e * s) = d`` gives ``e = (d - p + h) / s``; the median over
    presses is robust to a few mislabelled ones.

    Raises:
        CalibrationError: no usable press (none with a positive rim slope), or lengths differ.
    """
    if len(stats) != len(depths_mm):
        raise CalibrationError(f"{len(stats)} rim statistics but {len(depths_mm)} depths")
    values = [(d - st.peak_mm + st.height_mm) / st.slope
              for st, d in zip(stats, depths_mm, strict=True)
              if st.slope > 0 and math.isfinite(d)]
    if not values:
        raise CalibrationError("no press with a usable contact rim to fit the rim extension")
    return float(np.median(values))


#: a factor coarser than the coarsest fitted one by more than this ratio has no rim reference
MAX_FACTOR_BEYOND_FIT = 1.5


def extension_for_factor(table: Mapping[int, float], factor: int) -> float | None:
    """The fitted extension for a pooling factor: the entry nearest in log(factor); None
    for a grid coarser than the coarsest fitted one (by more than ``MAX_FACTOR_BEYOND_FIT``):
    there the contact spans too few cells for a rim, and heights stay above the free gel.

    Raises:
        ConfigError: an empty table.
    """
    if not table:
        raise ConfigError("relief 'rim' needs a fitted rim extension; recalibrate with "
                          "`teletouch sensor calibrate --relief rim`")
    if factor > MAX_FACTOR_BEYOND_FIT * max(table):
        return None
    best = min(table, key=lambda f: (abs(math.log(f) - math.log(max(factor, 1))), f))
    return float(table[best])
