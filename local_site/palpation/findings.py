"""Tumors found in the palpation maps: detection, location, type, severity, confidence.

* **Coverage**: a cell is covered when at least ``min_samples`` relief samples fell in it;
  ``PalpationMaps.relief_count`` is the coverage map.
* **Detection**: the relief map is smoothed with a Gaussian (``smooth_mm``) WEIGHTED BY
  EACH CELL'S SAMPLE COUNT (normalized convolution: untouched cells carry no weight and are
  not filled with anything). The healthy level and the cell-to-cell noise come from the
  LOWER part of the distribution (20th and 40th percentiles, :func:`_background`), so
  inclusions may cover most of the touched area. A cell is a candidate when its excess
  exceeds ``max(min_relief, noise_k * max(cell noise, standard error))``, the standard
  error being the within-cell sample spread over the square root of the samples under the
  kernel: sparsely sampled cells (the scan's edge) need a larger excess. Connected
  candidates form regions; regions smaller than ``min_area_mm2`` are noise.
* **Location**: the centroid of each region weighted by its relief excess (phantom mm).
* **Type**: from the boundary and the stiffness, with features whose expectation does not
  depend on how many frames were taken (a loaded machine delivers fewer; see
  :mod:`local_site.palpation.edge`). *Edge width* (mm): a blurred step fitted, by least
  squares weighted by each cell's sample count, to the RAW cell means against their signed
  distance from the finding's half-maximum contour, over the outer fall (1 mm inside to
  4 mm outside): a graded (infiltrating) boundary is wide. *Rim relief*: the
  sample-weighted mean relief just inside the contour (0.5-2.5 mm): the gel bulges more
  over stiffer tissue. The malignant score (:func:`malignant_score`) is
  ``(edge_width / ref_edge)^2 * (rim_relief / ref_rim)^rim_exponent`` (exponent 1);
  above 1 means malignant. Known limit: a SHARP benign inclusion that is stiff (>= ~10x),
  large (radius >= ~5.5 mm) or shallow scores malignant or ``uncertain``, because the rim
  relief grows with stiffness until the rigid-inclusion limit and the fitted width of a
  sharp edge grows with the relief too (development phantoms: 0.48 mm at 1.5x to 0.77 mm
  at 50x). Weighting the rim less (exponent 0.5, ref_edge 0.85 mm, set on development
  seeds) typed those correctly on held-out seeds (single-inclusion families 66 % -> 90-94 %)
  but typed 16-21 malignant inclusions graded over 0.8-1.05 mm benign (typed-pair
  families 76-82 % -> 66-71 %): the mechanical blur through 7 mm of tissue is as wide as
  such a boundary, so it stays an option, not the default
  (benchmarks/results/palpation_typing_stiff.md, docs/palpation_typing.md). Both carry
  a standard error. An optional size term ``(malignant_ref_radius_mm / equivalent
  radius)^malignant_size_exponent`` divides out the score's growth with the inclusion's
  size; on the median maps it did not beat the rule without it on fresh seeds
  (benchmarks/results/palpation_typing_size.md). By default the findings are TYPED from a
  second map normalised by the 20th percentile (``MapConfig.typing_signal_percentile``;
  ``find_tumors(..., typing_maps=...)``: the typing features of the overlapping region
  there), with exponent 3 and reference radius 5.15 mm; detection and location stay the
  median maps' (benchmarks/results/palpation_typing_hybrid.md). When the score
  is within ``type_uncertain_k`` standard errors
  of 1, or the edge could not be fitted, the finding is typed ``uncertain`` (its best
  guess is ``likely_kind``, itself ``uncertain`` when nothing could be measured: a finding
  seen only at its edge has no rim to measure). The measured secant-stiffness contrast
  (region's 90th percentile of the smoothed force/indentation map over the healthy
  median) and the older *boundary sharpness* (mean relief gradient on the region's edge
  over its peak, 1/mm; it drifts with the sampling density, which is why it no longer
  types) are reported. Outline irregularity is reported but not used: lobulated benign tumors
  exist. The reference levels were set on development phantoms (OOD ``type`` family,
  seeds 1000-1011 at 20 frames/s), never on the benchmark's held-out seeds.
* **Uncertain**: a finding whose disc (equivalent radius + ``coverage_margin_mm``) is less
  than ``min_coverage`` covered, or whose outer fall was sampled on less than
  ``min_boundary_coverage`` of its outline (``boundary_coverage``,
  :func:`local_site.palpation.edge.sampled_arc`; 0 by default: not used), is typed
  ``uncertain`` (its best guess is ``likely_kind``). Measured on development seeds 6000-6029
  and fresh seeds 7000-7029 (benchmarks/results/palpation_typing_coverage.md): the guesses
  withheld for coverage alone are right 93 %, but typing them (half the disc, half the
  outline) together with the calibrated margin below did not beat this rule on the fresh
  seeds, so the defaults stay. ``edge_sampled_arc_only`` fits the edge and the rim on the
  sampled sectors only (measured: little change, the fit already uses touched cells only;
  off).
* **Confidence** in [0, 1]: coverage x detection margin (peak over threshold) x typing
  margin (distance of the malignant score from 1, in log, over its standard error): a
  ranking aid, not a probability. ``type_confidence`` is one: the probability that the
  best guess's sign is right, ``Phi(margin / type_se_scale)``
  (:func:`type_probability`); the fit's standard error is ``type_se_scale`` (1.5, from the
  session-to-session scatter of one inclusion's score on development seeds) too small, and
  the resulting reliability table is in palpation_typing_coverage.md.
* **Severity**: the type first, as a clinician ranks lesions (a lesion typed malignant
  above an ``uncertain`` one, above one typed benign: malignancy outweighs size), then, among
  findings of one type, the integrated relief excess over the region (``severity_score``,
  mm^2), which grows with both the size and the hardness of the inclusion; rank 1 = least
  severe. (Ranking by the relief alone put a large benign tumor above a smaller malignant
  one, correctly typed, in 7 of 66 ranked pairs of the OOD benchmark's seeds 2000-2009.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from local_site.palpation.edge import (
    EdgeFit,
    edge_distance_mm,
    fit_edge,
    rim_level,
    sampled_arc,
)
from local_site.palpation.maps import PalpationMaps
from shared.errors import ConfigError

__all__ = ["DetectionConfig", "Finding", "find_tumors", "malignant_score", "rank_by_severity",
           "type_probability"]

#: the type's weight in the severity order (see the module docstring)
_SEVERITY_OF_KIND = {"benign": 0, "uncertain": 1, "malignant": 2}


@dataclass(frozen=True)
class DetectionConfig:
    """Detection and typing settings (see the module docstring)."""

    smooth_mm: float = 0.5
    min_relief: float = 0.05
    noise_k: float = 6.0
    min_area_mm2: float = 8.0
    min_samples: int = 3
    stiffness_smooth_mm: float = 2.0
    coverage_margin_mm: float = 2.0
    min_coverage: float = 0.9
    edge_band_mm: tuple[float, float] = (-1.0, 4.0)
    rim_band_mm: tuple[float, float] = (-2.5, -0.5)
    malignant_ref_edge_mm: float = 0.75
    malignant_ref_rim_relief: float = 1.0
    malignant_rim_exponent: float = 1.0
    type_uncertain_k: float = 2.0
    min_boundary_coverage: float = 0.0
    type_se_scale: float = 1.5
    edge_sampled_arc_only: bool = False
    #: the malignant score is multiplied by ``(malignant_ref_radius_mm / equivalent radius)
    #: ** malignant_size_exponent`` (0 = no size term). The defaults (3, 5.15 mm) were set
    #: for typing maps at the 20th percentile (``MapConfig.typing_signal_percentile``, the
    #: default); the rule before this one is 0 with typing from the median maps.
    malignant_size_exponent: float = 3.0
    malignant_ref_radius_mm: float = 5.15

    def __post_init__(self) -> None:
        """Every field checked here, so a bad value fails with its name, not deep inside
        the detection.

        Raises:
            ConfigError: a field that is not a finite number (bool for
                ``edge_sampled_arc_only``, int for ``min_samples``) or outside its range.
        """
        for name, (lo, lo_open, hi) in _DETECTION_RANGES.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"DetectionConfig.{name} must be a finite number, got {v!r}")
            if (v <= lo if lo_open else v < lo) or v > hi:
                raise ConfigError(f"DetectionConfig.{name} must be "
                                  f"{_range_text(lo, lo_open, hi)}, got {v!r}")
        if isinstance(self.min_samples, bool) or not isinstance(self.min_samples, int) \
                or self.min_samples < 1:
            raise ConfigError(f"DetectionConfig.min_samples must be an integer >= 1, got "
                              f"{self.min_samples!r}")
        if not isinstance(self.edge_sampled_arc_only, bool):
            raise ConfigError(f"DetectionConfig.edge_sampled_arc_only must be a bool, got "
                              f"{self.edge_sampled_arc_only!r}")
        for name, need in (("edge_band_mm", "inner < 0 < outer"),
                           ("rim_band_mm", "inner < outer")):
            band = getattr(self, name)
            ok = (isinstance(band, tuple) and len(band) == 2
                  and all(not isinstance(v, bool) and isinstance(v, (int, float))
                          and math.isfinite(v) for v in band)
                  and band[0] < band[1]
                  and (name != "edge_band_mm" or band[0] < 0.0 < band[1]))
            if not ok:
                raise ConfigError(f"DetectionConfig.{name} must be two finite numbers "
                                  f"(inner, outer) mm with {need}, got {band!r}")


#: DetectionConfig's number fields: name -> (lower bound, lower bound excluded, upper bound)
_DETECTION_RANGES: dict[str, tuple[float, bool, float]] = {
    "smooth_mm": (0.0, False, math.inf),
    "min_relief": (0.0, False, math.inf),
    "noise_k": (0.0, False, math.inf),
    "min_area_mm2": (0.0, False, math.inf),
    "stiffness_smooth_mm": (0.0, False, math.inf),
    "coverage_margin_mm": (0.0, False, math.inf),
    "min_coverage": (0.0, False, 1.0),
    "malignant_ref_edge_mm": (0.0, True, math.inf),
    "malignant_ref_rim_relief": (0.0, True, math.inf),
    "malignant_rim_exponent": (0.0, False, math.inf),
    "type_uncertain_k": (0.0, True, math.inf),
    "min_boundary_coverage": (0.0, False, 1.0),
    "type_se_scale": (0.0, True, math.inf),
    "malignant_size_exponent": (0.0, False, math.inf),
    "malignant_ref_radius_mm": (0.0, True, math.inf),
}


def _range_text(lo: float, lo_open: bool, hi: float) -> str:
    if math.isinf(hi):
        return f"{'>' if lo_open else '>='} {lo:g}"
    return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}]"


@dataclass(frozen=True)
class Finding:
    """One tumor as the operator's data show it (phantom coordinates, mm)."""

    center_mm: tuple[float, float]
    area_mm2: float
    equivalent_radius_mm: float
    peak_relief: float
    severity_score: float
    boundary_sharpness_per_mm: float
    irregularity: float
    stiffness_n_per_mm: float | None
    kind: str
    severity_rank: int = 0
    stiffness_contrast: float = 0.0
    coverage: float = 1.0
    confidence: float = 0.0
    likely_kind: str = ""
    edge_width_mm: float = math.nan
    edge_width_se_mm: float = math.inf
    rim_relief: float = math.nan
    malignant_score: float = math.nan
    malignant_score_log_se: float = math.inf
    boundary_coverage: float = 0.0
    type_confidence: float = 0.5

    def to_dict(self) -> dict[str, object]:
        """Plain JSON."""
        return {
            "center_mm": list(self.center_mm), "area_mm2": self.area_mm2,
            "equivalent_radius_mm": self.equivalent_radius_mm, "peak_relief": self.peak_relief,
            "severity_score": self.severity_score,
            "boundary_sharpness_per_mm": self.boundary_sharpness_per_mm,
            "irregularity": self.irregularity, "stiffness_n_per_mm": self.stiffness_n_per_mm,
            "kind": self.kind, "severity_rank": self.severity_rank,
            "stiffness_contrast": self.stiffness_contrast, "coverage": self.coverage,
            "confidence": self.confidence, "likely_kind": self.likely_kind,
            "edge_width_mm": _finite(self.edge_width_mm),
            "edge_width_se_mm": _finite(self.edge_width_se_mm),
            "rim_relief": _finite(self.rim_relief),
            "malignant_score": _finite(self.malignant_score),
            "malignant_score_log_se": _finite(self.malignant_score_log_se),
            "boundary_coverage": self.boundary_coverage,
            "type_confidence": self.type_confidence,
        }


def _finite(v: float) -> float | None:
    """JSON has no NaN or Inf: an unknown figure is null."""
    return float(v) if math.isfinite(v) else None


def _irregularity(excess: NDArray[np.float64], region: NDArray[np.bool_], peak: float,
                  cx: float, cy: float, cell: float) -> float:
    half = ndimage.binary_fill_holes((excess >= peak / 2.0) & region)
    if half is None or half.sum() < 4:
        return 0.0
    boundary = half & ~ndimage.binary_erosion(half)
    rows, cols = np.nonzero(boundary)
    r = np.hypot(cols - cx, rows - cy) * cell
    mean = float(r.mean())
    return float(r.std() / mean) if mean > 0 else 0.0


@dataclass(frozen=True)
class _Boundary:
    edge: EdgeFit
    rim: float
    rim_se: float
    arc: float


def _boundary(excess: NDArray[np.float64], raw_excess: NDArray[np.float64],
              counts: NDArray[np.float64], region: NDArray[np.bool_],
              lesion: NDArray[np.bool_], covered: NDArray[np.bool_], peak: float,
              center_rc: tuple[float, float], cell: float, cfg: DetectionConfig) -> _Boundary:
    """Edge width and rim relief of one region (cells near other regions left out)."""
    inside = ndimage.binary_fill_holes((excess >= peak / 2.0) & region)
    if inside is None or not inside.any():
        inside = region
    others = lesion & ~region
    reach = max(-cfg.edge_band_mm[0], cfg.edge_band_mm[1], -cfg.rim_band_mm[0])
    if others.any():
        others = ndimage.binary_dilation(others, iterations=max(1, round(reach / cell)))
    distance = edge_distance_mm(inside, cell)
    arc, in_sampled_arc = sampled_arc(covered, distance, ~others, center_rc,
                                      (0.0, cfg.edge_band_mm[1]))
    use = ~others & in_sampled_arc if cfg.edge_sampled_arc_only and arc > 0 else ~others
    edge = fit_edge(raw_excess, counts, distance, use, cfg.edge_band_mm)
    rim, rim_se = rim_level(raw_excess, counts, distance, use, cfg.rim_band_mm)
    return _Boundary(edge, rim, rim_se, arc)


def malignant_score(width_mm: float, width_se_mm: float, rim: float, rim_se: float,
                    cfg: DetectionConfig | None = None,
                    radius_mm: float = math.nan) -> tuple[float, float]:
    """``(width / ref_edge)^2 * (rim / ref_rim)^rim_exponent * (ref_radius / radius)^b``
    (``b = malignant_size_exponent``; 0 by default: no size term, ``radius_mm`` unused) and
    the standard error of its log (first-order propagation of the width's and the rim's
    standard errors; the radius is taken as exact); (nan, inf) when a feature it uses is
    unmeasured (not finite or not positive)."""
    c = cfg or DetectionConfig()
    a, b = c.malignant_rim_exponent, c.malignant_size_exponent
    if not (math.isfinite(width_mm) and width_mm > 0):
        return math.nan, math.inf
    size = 1.0
    if b != 0.0:
        if not (math.isfinite(radius_mm) and radius_mm > 0):
            return math.nan, math.inf
        size = (c.malignant_ref_radius_mm / radius_mm) ** b
    if a == 0.0:  # the boundary alone: the rim need not be measured
        return (width_mm / c.malignant_ref_edge_mm) ** 2 * size, 2.0 * width_se_mm / width_mm
    if not (math.isfinite(rim) and rim > 0):
        return math.nan, math.inf
    score = ((width_mm / c.malignant_ref_edge_mm) ** 2
             * (rim / c.malignant_ref_rim_relief) ** a) * size
    return score, math.hypot(2.0 * width_se_mm / width_mm, a * rim_se / rim)


def _type(b: _Boundary, radius_mm: float, cfg: DetectionConfig) -> tuple[float, float]:
    """The malignant score and the standard error of its log (inf when unmeasured)."""
    return malignant_score(b.edge.width_mm, b.edge.width_se_mm, b.rim, b.rim_se, cfg,
                           radius_mm)


def type_probability(margin: float, se_scale: float = 1.0) -> float:
    """The probability that the sign of the log malignant score is right, for a score
    ``margin`` standard errors from 1 whose standard error is ``se_scale`` times too small:
    ``Phi(margin / se_scale)``, in [0.5, 1] (0.5 for a margin of 0: a coin toss)."""
    if not (math.isfinite(margin) and margin > 0):
        return 0.5
    return 0.5 * math.erfc(-margin / (se_scale * math.sqrt(2.0)))


def _background(values: NDArray[np.float64]) -> tuple[float, float]:
    """Healthy level and cell noise from the LOWER part of the relief distribution.

    Stiff inclusions only raise the relief, so the healthy tissue is the lower part of the
    distribution even when inclusions cover most of the touched area. The lower half's
    median-to-20th-percentile spread gives sigma (for a normal distribution the 20th
    percentile is 0.84 sigma below the mean); the level is the 20th percentile plus
    0.84 sigma. Needs only the lowest ~40 % of the touched cells to be healthy.
    """
    p20, p40 = (float(v) for v in np.percentile(values, [20, 40]))
    sigma = max((p40 - p20) / (0.842 - 0.253), 1e-6)
    return p20 + 0.842 * sigma, sigma


def _normalized_smooth(values: NDArray[np.float64], counts: NDArray[np.float64],
                       sigma_cells: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sample-count-weighted Gaussian smoothing; untouched cells carry no weight (they are
    not filled with anything). Returns the smoothed values and the smoothed counts."""
    weight = ndimage.gaussian_filter(counts, sigma_cells)
    total = ndimage.gaussian_filter(np.where(counts > 0, values, 0.0) * counts, sigma_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(weight > 1e-9, total / weight, np.nan), weight


def _disc(maps: PalpationMaps, cx_mm: float, cy_mm: float, r_mm: float) -> NDArray[np.bool_]:
    return ((maps.x_mm[None, :] - cx_mm) ** 2 + (maps.y_mm[:, None] - cy_mm) ** 2
            <= r_mm ** 2)


@dataclass(frozen=True, eq=False)
class _Detection:
    """What the detection computes on one set of maps (see :func:`_detect`)."""

    labels: NDArray[np.int32]
    count: int
    excess: NDArray[np.float64]
    raw_excess: NDArray[np.float64]
    counts: NDArray[np.float64]
    covered: NDArray[np.bool_]
    lesion: NDArray[np.bool_]
    threshold: NDArray[np.float64]


def _detect(maps: PalpationMaps, cfg: DetectionConfig) -> _Detection | None:
    """Candidate regions of ``maps`` (None when no cell is covered)."""
    cell = maps.cell_mm
    counts = maps.relief_count.astype(np.float64)
    covered = maps.relief_count >= cfg.min_samples
    if not covered.any():
        return None
    s_cells = cfg.smooth_mm / cell
    smooth, weight = _normalized_smooth(np.nan_to_num(maps.relief), counts, s_cells)
    valid = covered & np.isfinite(smooth)
    background, cell_sigma = _background(smooth[valid])
    # per-sample noise: the median within-cell spread; the smoothed mean's standard error
    # falls with the samples under the kernel (effective kernel area 4 pi s^2 cells)
    spread = maps.relief_sample_std[np.isfinite(maps.relief_sample_std)
                                    & (maps.relief_count >= 5)]
    sample_sigma = float(np.median(spread)) if spread.size else cell_sigma
    with np.errstate(divide="ignore"):
        std_error = sample_sigma / np.sqrt(np.maximum(weight * 4 * np.pi * s_cells ** 2, 1.0))
    excess = np.where(valid, smooth - background, 0.0)
    threshold = np.maximum(cfg.min_relief, cfg.noise_k * np.maximum(cell_sigma, std_error))
    labels, count = ndimage.label((excess > threshold) & valid)
    raw_excess = np.where(maps.relief_count > 0, maps.relief - background, np.nan)
    return _Detection(labels=labels, count=int(count), excess=excess, raw_excess=raw_excess,
                      counts=counts, covered=covered, lesion=labels > 0, threshold=threshold)


def _region_boundary(det: _Detection, region: NDArray[np.bool_], cell: float,
                     cfg: DetectionConfig) -> _Boundary:
    """Edge and rim of one region of ``det`` (centre: its excess-weighted centroid)."""
    weights = np.where(region, det.excess, 0.0)
    cy, cx = ndimage.center_of_mass(weights)
    peak = float(det.excess[region].max())
    return _boundary(det.excess, det.raw_excess, det.counts, region, det.lesion,
                     det.covered, peak, (cy, cx), cell, cfg)


def _typing_from(typing: _Detection, region: NDArray[np.bool_], cell: float,
                 cfg: DetectionConfig) -> tuple[_Boundary, float] | None:
    """The boundary and equivalent radius of the region of the TYPING maps that overlaps
    ``region`` (a finding of the detection maps) most, among regions of at least
    ``min_area_mm2``; None when none overlaps it."""
    hits = typing.labels[region]
    hits = hits[hits > 0]
    if hits.size == 0:
        return None
    labels, overlap = np.unique(hits, return_counts=True)
    for i in np.argsort(-overlap, kind="stable"):
        candidate = typing.labels == labels[i]
        area = float(candidate.sum()) * cell * cell
        if area >= cfg.min_area_mm2:
            return (_region_boundary(typing, candidate, cell, cfg),
                    math.sqrt(area / math.pi))
    return None


def _check_grid(maps: PalpationMaps) -> None:
    """Refuse a grid the detection cannot measure on (see :func:`find_tumors`)."""
    x, y = np.asarray(maps.x_mm, np.float64), np.asarray(maps.y_mm, np.float64)
    if x.ndim != 1 or y.ndim != 1 or maps.relief.shape != (y.size, x.size):
        raise ValueError(f"the maps' grid ({y.size} x {x.size} cells) does not match their "
                         f"relief's shape {maps.relief.shape}")
    steps = np.concatenate([np.diff(x), np.diff(y)])
    if steps.size and not (np.all(np.isfinite(steps)) and steps.min() > 0
                           and np.allclose(steps, steps[0], rtol=1e-6, atol=0.0)):
        raise ValueError("the maps' grid must ascend evenly with one cell size on x and y "
                         f"(steps from {steps.min():g} to {steps.max():g} mm)")


def find_tumors(maps: PalpationMaps, config: DetectionConfig | None = None,
                typing_maps: PalpationMaps | None = None) -> list[Finding]:
    """Detect and characterise tumors in the maps.

    Args:
        maps: relief and stiffness maps of a session.
        config: thresholds.
        typing_maps: maps of the same session on the same grid (e.g. another
            ``MapConfig.signal_percentile``) to TYPE the findings from: the findings, their
            centres, areas, peak, severity score, coverage and stiffness are those of
            ``maps``; each is typed (edge width, rim relief, malignant score, with the size
            term's radius) from the region of ``typing_maps`` found by the same detection
            that overlaps it most, and ``uncertain`` when none does. None (default): typed
            from ``maps``.

    Returns:
        Findings, most severe last, each with its severity rank (1 = least severe); none
        on a map with fewer than 2 cells on a side (no cell size, no gradient: nothing
        has an outline there).

    Raises:
        ValueError: ``typing_maps`` is not on the grid of ``maps``, or the grid does not
            ascend evenly with one cell size on both axes, or does not match the maps' shape
            (a descending grid gave a negative cell size to the gradients and smoothing).
    """
    cfg = config or DetectionConfig()
    _check_grid(maps)
    cell = maps.cell_mm
    if typing_maps is not None and not (
            typing_maps.x_mm.shape == maps.x_mm.shape and typing_maps.y_mm.shape == maps.y_mm.shape
            and np.array_equal(typing_maps.x_mm, maps.x_mm)
            and np.array_equal(typing_maps.y_mm, maps.y_mm)):
        raise ValueError("typing_maps must be on the grid of maps")
    if maps.relief.ndim != 2 or min(maps.relief.shape) < 2:
        return []
    det = _detect(maps, cfg)
    if det is None:
        return []
    typing = _detect(typing_maps, cfg) if typing_maps is not None else None
    labels, count, excess, threshold = det.labels, det.count, det.excess, det.threshold
    covered, lesion = det.covered, det.lesion
    grad_y, grad_x = np.gradient(excess, cell)
    grad = np.hypot(grad_x, grad_y)
    k_map, _ = _normalized_smooth(np.nan_to_num(maps.stiffness_n_per_mm),
                                  np.isfinite(maps.stiffness_n_per_mm).astype(float),
                                  cfg.stiffness_smooth_mm / cell)
    healthy_k = k_map[np.isfinite(k_map) & ~ndimage.binary_dilation(lesion, iterations=8)]
    k_background = (float(np.median(healthy_k)) if healthy_k.size
                    else maps.background_stiffness_n_per_mm)
    findings: list[Finding] = []
    for label in range(1, count + 1):
        region = labels == label
        area = float(region.sum()) * cell * cell
        if area < cfg.min_area_mm2:
            continue
        weights = np.where(region, excess, 0.0)
        cy, cx = ndimage.center_of_mass(weights)
        peak = float(excess[region].max())
        rim = region & ~ndimage.binary_erosion(region)
        sharpness = float(grad[rim].mean() / peak) if rim.any() and peak > 0 else 0.0
        irregularity = _irregularity(excess, region, peak, cx, cy, cell)
        x_mm = float(np.interp(cx, np.arange(maps.x_mm.size), maps.x_mm))
        y_mm = float(np.interp(cy, np.arange(maps.y_mm.size), maps.y_mm))
        radius = math.sqrt(area / math.pi)
        if typing is None:
            boundary = _boundary(excess, det.raw_excess, det.counts, region, lesion, covered,
                                 peak, (cy, cx), cell, cfg)
            malignant_score, log_se = _type(boundary, radius, cfg)
        else:
            typed_from = _typing_from(typing, region, cell, cfg)
            if typed_from is None:
                boundary = _Boundary(EdgeFit(math.nan, math.inf, math.nan, math.nan, 0, 0),
                                     math.nan, math.inf, 0.0)
                malignant_score, log_se = math.nan, math.inf
            else:
                boundary = typed_from[0]
                malignant_score, log_se = _type(boundary, typed_from[1], cfg)
        k_cells = k_map[region & np.isfinite(k_map)]
        stiffness = float(np.percentile(k_cells, 90)) if k_cells.size else None
        contrast = (stiffness / k_background - 1.0
                    if stiffness is not None and k_background > 0 else 0.0)
        around = _disc(maps, x_mm, y_mm, radius + cfg.coverage_margin_mm)
        coverage = float(covered[around].mean()) if around.any() else 0.0
        significance = peak / max(float(threshold[region].max()), 1e-9)
        # a graded boundary (wide edge) is the main cue, a stiffer inclusion (higher rim
        # relief) adds to it; a score within k standard errors of 1 is not a type
        guess = ("uncertain" if not math.isfinite(malignant_score)
                 else "malignant" if malignant_score > 1.0 else "benign")
        type_margin = (abs(math.log(malignant_score)) / log_se
                       if math.isfinite(log_se) and log_se > 0 else 0.0)
        typed = math.isfinite(log_se) and type_margin >= cfg.type_uncertain_k
        confidence = (coverage * (1.0 - math.exp(-max(significance - 1.0, 0.0) * 2.0))
                      * (1.0 - math.exp(-type_margin / cfg.type_uncertain_k)))
        # the fit's standard error is type_se_scale too small (session-to-session scatter)
        type_confidence = type_probability(type_margin, cfg.type_se_scale)
        enough = coverage >= cfg.min_coverage and boundary.arc >= cfg.min_boundary_coverage
        kind = guess if enough and typed else "uncertain"
        findings.append(Finding(
            center_mm=(x_mm, y_mm), area_mm2=area, equivalent_radius_mm=radius,
            peak_relief=peak, severity_score=float(weights.sum()) * cell * cell,
            boundary_sharpness_per_mm=sharpness, irregularity=irregularity,
            stiffness_n_per_mm=stiffness, kind=kind, stiffness_contrast=contrast,
            coverage=coverage, confidence=confidence, likely_kind=guess,
            edge_width_mm=boundary.edge.width_mm,
            edge_width_se_mm=boundary.edge.width_se_mm, rim_relief=boundary.rim,
            malignant_score=malignant_score, malignant_score_log_se=log_se,
            boundary_coverage=boundary.arc, type_confidence=type_confidence))
    return rank_by_severity(findings)


def rank_by_severity(findings: list[Finding]) -> list[Finding]:
    """The findings, least severe first, each with its ``severity_rank`` (1 = least severe):
    by type (benign, ``uncertain``, malignant), then by ``severity_score``."""
    ordered = sorted(findings, key=lambda f: (_SEVERITY_OF_KIND[f.kind], f.severity_score))
    return [Finding(**{**f.__dict__, "severity_rank": i + 1}) for i, f in enumerate(ordered)]
