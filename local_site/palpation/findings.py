"""Tumors found in the palpation maps: detection, location, type and severity.

* **Detection**: the relief map is smoothed (Gaussian, ``smooth_mm``), its background and
  noise are estimated robustly over the touched cells (median and MAD), and cells above
  ``max(min_relief, background + noise_k * MAD)`` form connected regions; regions smaller than
  ``min_area_mm2`` are noise.
* **Location**: the centroid of each region weighted by its relief excess (phantom mm).
* **Type**: benign tumors are round with a distinct boundary; malignant ones have an irregular
  outline and a graded boundary. Two dimensionless measures: *boundary sharpness*, the mean
  relief gradient on the region's edge divided by its peak excess (1/mm), and *outline
  irregularity*, the coefficient of variation of the half-peak contour's radius around the
  centroid. A region is malignant when it is soft-edged or irregular beyond the thresholds.
* **Severity**: the integrated relief excess over the region (mm^2), which grows with both
  the size and the hardness of the inclusion; rank 1 = least severe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from local_site.palpation.maps import PalpationMaps

__all__ = ["DetectionConfig", "Finding", "find_tumors"]


@dataclass(frozen=True)
class DetectionConfig:
    """Detection and typing thresholds (see the module docstring)."""

    smooth_mm: float = 0.5
    min_relief: float = 0.05
    noise_k: float = 6.0
    min_area_mm2: float = 8.0
    malignant_max_sharpness_per_mm: float = 0.1
    malignant_min_irregularity: float = 0.15


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

    def to_dict(self) -> dict[str, object]:
        """Plain JSON."""
        return {
            "center_mm": list(self.center_mm), "area_mm2": self.area_mm2,
            "equivalent_radius_mm": self.equivalent_radius_mm, "peak_relief": self.peak_relief,
            "severity_score": self.severity_score,
            "boundary_sharpness_per_mm": self.boundary_sharpness_per_mm,
            "irregularity": self.irregularity, "stiffness_n_per_mm": self.stiffness_n_per_mm,
            "kind": self.kind, "severity_rank": self.severity_rank,
        }


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


def find_tumors(maps: PalpationMaps, config: DetectionConfig | None = None) -> list[Finding]:
    """Detect and characterise tumors in the maps.

    Args:
        maps: relief and stiffness maps of a session.
        config: thresholds.

    Returns:
        Findings, most severe last, each with its severity rank (1 = least severe).
    """
    cfg = config or DetectionConfig()
    cell = maps.cell_mm
    touched = np.isfinite(maps.relief)
    if not touched.any():
        return []
    background = float(np.median(maps.relief[touched]))
    mad = float(np.median(np.abs(maps.relief[touched] - background)))
    filled = np.where(touched, maps.relief, background)
    smooth = ndimage.gaussian_filter(filled, cfg.smooth_mm / cell)
    excess = smooth - background
    threshold = max(cfg.min_relief, cfg.noise_k * 1.4826 * mad)
    labels, count = ndimage.label((excess > threshold) & touched)
    grad_y, grad_x = np.gradient(excess, cell)
    grad = np.hypot(grad_x, grad_y)
    findings: list[Finding] = []
    for label in range(1, count + 1):
        region = labels == label
        area = float(region.sum()) * cell * cell
        if area < cfg.min_area_mm2:
            continue
        weights = np.where(region, excess, 0.0)
        cy, cx = ndimage.center_of_mass(weights)
        peak = float(excess[region].max())
        edge = region & ~ndimage.binary_erosion(region)
        sharpness = float(grad[edge].mean() / peak) if edge.any() and peak > 0 else 0.0
        irregularity = _irregularity(excess, region, peak, cx, cy, cell)
        x_mm = float(np.interp(cx, np.arange(maps.x_mm.size), maps.x_mm))
        y_mm = float(np.interp(cy, np.arange(maps.y_mm.size), maps.y_mm))
        k_cells = maps.stiffness_n_per_mm[region]
        k_cells = k_cells[np.isfinite(k_cells)]
        stiffness = float(np.percentile(k_cells, 90)) if k_cells.size else None
        malignant = (sharpness < cfg.malignant_max_sharpness_per_mm
                     or irregularity > cfg.malignant_min_irregularity)
        findings.append(Finding(
            center_mm=(x_mm, y_mm), area_mm2=area,
            equivalent_radius_mm=math.sqrt(area / math.pi), peak_relief=peak,
            severity_score=float(weights.sum()) * cell * cell,
            boundary_sharpness_per_mm=sharpness, irregularity=irregularity,
            stiffness_n_per_mm=stiffness, kind="malignant" if malignant else "benign"))
    findings.sort(key=lambda f: f.severity_score)
    return [Finding(**{**f.__dict__, "severity_rank": i + 1}) for i, f in enumerate(findings)]
