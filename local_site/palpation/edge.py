"""A finding's boundary as a width in mm, fitted to the raw cell means around its outline.

The relief of an inclusion falls from its plateau to the healthy level across its outline.
How wide that fall is tells a sharply bounded inclusion from one whose stiffness fades
into the tissue. The width is estimated so that its EXPECTATION does not depend on how
many frames were taken (a loaded machine delivers fewer):

* every cell near the outline is placed at its signed distance ``d`` (mm) from the
  finding's half-maximum contour (negative inside), whatever the outline's shape (a
  lobulated outline is followed, not averaged out as a radial profile would);
* the cells' RAW mean relief (not a smoothed map: smoothing widens the edge by an amount
  that depends on which cells were sampled) is fitted with
  ``y(d) = amplitude * Phi(-(d - shift) / width)`` (``Phi`` the normal CDF) by weighted
  least squares, each cell weighted by its sample count (its mean's variance is the
  per-sample variance over the count). Fewer samples make the estimate noisier, not
  biased;
* the fit's standard error of the width is returned, so a caller can say the boundary
  was not measured well enough instead of guessing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, optimize, special

__all__ = ["EdgeFit", "arc_coverage", "edge_distance_mm", "fit_edge", "rim_level", "sampled_arc",
           "step_model"]

_SQRT2 = math.sqrt(2.0)


@dataclass(frozen=True)
class EdgeFit:
    """A fitted boundary.

    Attributes:
        width_mm: the edge's standard width (the fall from 84 % to 16 % of the amplitude
            spans two widths).
        width_se_mm: its standard error (inf when the fit failed).
        amplitude: the plateau's relief excess at the outline.
        shift_mm: where the fitted half level lies from the given contour (+ = outside).
        cells: cells used.
        samples: relief samples in those cells.
    """

    width_mm: float
    width_se_mm: float
    amplitude: float
    shift_mm: float
    cells: int
    samples: int

    @property
    def relative_se(self) -> float:
        """Standard error of the width over the width (inf when unknown)."""
        if not (math.isfinite(self.width_se_mm) and self.width_mm > 0):
            return math.inf
        return self.width_se_mm / self.width_mm


def step_model(d_mm: NDArray[np.float64], amplitude: float, shift_mm: float,
               width_mm: float) -> NDArray[np.float64]:
    """``amplitude * Phi(-(d - shift) / width)``: a blurred step, high inside (d < 0)."""
    return amplitude * 0.5 * special.erfc((d_mm - shift_mm) / (_SQRT2 * width_mm))


def edge_distance_mm(inside: NDArray[np.bool_], cell_mm: float) -> NDArray[np.float64]:
    """Signed distance (mm) of every cell centre from the boundary of ``inside``:
    negative inside, positive outside, +-cell/2 for the cells on either side of it."""
    outside_d = ndimage.distance_transform_edt(~inside)
    inside_d = ndimage.distance_transform_edt(inside)
    return np.asarray(np.where(inside, -(inside_d - 0.5), outside_d - 0.5),
                      np.float64) * cell_mm


def fit_edge(values: NDArray[np.float64], counts: NDArray[np.float64],
             distance_mm: NDArray[np.float64], use: NDArray[np.bool_],
             band_mm: tuple[float, float] = (-1.0, 4.0)) -> EdgeFit:
    """Fit the blurred step to the cells ``use`` whose distance lies in ``band_mm``.

    The default band is the OUTER fall (1 mm inside the half-maximum contour to 4 mm
    outside): inside, the relief of a round inclusion keeps rising toward its centre (the
    inclusion is thicker there), which is no part of the boundary.

    Args:
        values: raw mean relief excess per cell (NaN where untouched).
        counts: samples per cell.
        distance_mm: signed distance from the contour (:func:`edge_distance_mm`).
        use: cells that may belong to this finding (others' cells excluded).
        band_mm: (inner, outer) limits of the fitted band, mm (inner < 0 < outer).

    Returns:
        The fit; ``width_se_mm`` is inf when too few cells or the fit did not converge.
    """
    lo, hi = band_mm
    sel = (use & (counts > 0) & np.isfinite(values) & (distance_mm >= lo)
           & (distance_mm <= hi))
    d = distance_mm[sel]
    y = values[sel]
    n = counts[sel].astype(np.float64)
    cells, samples = int(sel.sum()), int(n.sum())
    inner, outer = d < 0, d > 0
    if cells < 8 or inner.sum() < 3 or outer.sum() < 3:
        return EdgeFit(math.nan, math.inf, math.nan, math.nan, cells, samples)
    a0 = 2.0 * float(np.average(y[np.abs(d) <= 0.5], weights=n[np.abs(d) <= 0.5])
                     if (np.abs(d) <= 0.5).any() else np.max(y))
    try:
        params, cov = optimize.curve_fit(
            step_model, d, y, p0=(max(a0, 1e-3), 0.0, 1.0), sigma=1.0 / np.sqrt(n),
            bounds=((0.0, lo, 0.05), (np.inf, hi, hi - lo)), maxfev=2000)
    except (RuntimeError, ValueError):
        return EdgeFit(math.nan, math.inf, math.nan, math.nan, cells, samples)
    # sigma were relative weights: curve_fit scales the covariance by the residual variance
    se = float(np.sqrt(cov[2, 2])) if np.isfinite(cov[2, 2]) else math.inf
    return EdgeFit(float(params[2]), se, float(params[0]), float(params[1]), cells, samples)


def rim_level(values: NDArray[np.float64], counts: NDArray[np.float64],
              distance_mm: NDArray[np.float64], use: NDArray[np.bool_],
              band_mm: tuple[float, float] = (-2.5, -0.5)) -> tuple[float, float]:
    """The sample-weighted mean relief just inside the contour, and its standard error.

    Each cell's mean counts with its sample count, so the result is the mean of all the
    samples that fell in the band: its expectation does not depend on how many there were.

    Returns:
        (level, standard error); (nan, inf) when the band holds fewer than 2 cells.
    """
    lo, hi = band_mm
    sel = (use & (counts > 0) & np.isfinite(values) & (distance_mm >= lo)
           & (distance_mm <= hi))
    if sel.sum() < 2:
        return math.nan, math.inf
    y, n = values[sel], counts[sel].astype(np.float64)
    level = float(np.average(y, weights=n))
    # cells differ by more than their sampling noise (the relief varies along the rim):
    # the spread of the cell means, with the effective number of cells
    spread = float(np.sqrt(np.average((y - level) ** 2, weights=n)))
    n_eff = float(n.sum() ** 2 / (n ** 2).sum())
    return level, spread / math.sqrt(max(n_eff - 1.0, 1.0))


def _sector_map(shape: tuple[int, ...], center_rc: tuple[float, float],
                sectors: int) -> NDArray[np.int64]:
    rows, cols = np.indices(shape)
    angle = np.arctan2(rows - center_rc[0], cols - center_rc[1])
    return np.minimum(((angle + math.pi) / (2 * math.pi) * sectors).astype(np.int64),
                      sectors - 1)


def sampled_arc(covered: NDArray[np.bool_], distance_mm: NDArray[np.float64],
                use: NDArray[np.bool_], center_rc: tuple[float, float],
                band_mm: tuple[float, float] = (0.0, 4.0), sectors: int = 16,
                min_share: float = 0.5) -> tuple[float, NDArray[np.bool_]]:
    """Where a finding's outer fall was sampled: the share of its outline, and the cells
    of the sampled angular sectors.

    The cells ``use`` whose signed distance from the outline lies in ``band_mm`` (by default
    the outer fall, where the relief drops to the healthy level) are split into ``sectors``
    equal angular sectors about ``center_rc`` (row, column); a sector counts as sampled when
    at least ``min_share`` of its band cells are ``covered``. A sector holding no band cell
    is left out of the share (a small outline has fewer band cells than sectors).

    Returns:
        (sampled sectors over the sectors holding band cells, in [0, 1] and 0 when the band
        holds no cell; a mask of every cell, at any distance, lying in a sampled sector).
    """
    lo, hi = band_mm
    sector = _sector_map(covered.shape, center_rc, sectors)
    band = use & (distance_mm > lo) & (distance_mm <= hi)
    if not band.any():
        return 0.0, np.zeros(covered.shape, bool)
    total = np.bincount(sector[band], minlength=sectors)
    hit = np.bincount(sector[band], weights=covered[band].astype(float), minlength=sectors)
    present = total > 0
    sampled = present & (hit >= min_share * total)
    return float(sampled.sum() / present.sum()), np.asarray(sampled[sector], bool)


def arc_coverage(covered: NDArray[np.bool_], distance_mm: NDArray[np.float64],
                 use: NDArray[np.bool_], center_rc: tuple[float, float],
                 band_mm: tuple[float, float] = (0.0, 4.0), sectors: int = 16,
                 min_share: float = 0.5) -> float:
    """The share of a finding's outline around which its outer fall was sampled
    (:func:`sampled_arc`'s first value)."""
    return sampled_arc(covered, distance_mm, use, center_rc, band_mm, sectors, min_share)[0]
