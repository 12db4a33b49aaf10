"""Tumor inclusions of the silicone phantom and their footprint on a column model.

A tumor is a (perturbed) sphere embedded in the layer. Benign tumors are round with a
sharp boundary; malignant ones have an irregular outline (a seeded sum of radial harmonics
``R(theta) = r (1 + sum A_m cos(m theta + phi_m))``), an uneven top surface and a graded
boundary whose modulus contrast fades over ``boundary_width_mm``.

For the contact model every surface point (x, y) sees a vertical column of the layer. A
tumor occupies the part of that column between ``depth - half`` and ``depth + half``
(``half`` is the chord half-thickness). :func:`tumor_column_fraction` returns the
depth-weighted share of the column's compliance that the tumor takes, times its boundary
membership (1 inside, graded to 0 outside).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.special import erfc

from remote_site.phantom.mechanics import depth_weight_integral
from shared.errors import ConfigError

__all__ = ["FIDUCIAL", "TUMOR_KINDS", "Tumor", "tumor_column_fraction"]

TUMOR_KINDS = frozenset({"benign", "malignant"})
#: a registration marker (see :attr:`remote_site.phantom.phantom.Phantom.fiducials`)
FIDUCIAL = "fiducial"
_SQRT2 = math.sqrt(2.0)


@dataclass(frozen=True)
class Tumor:
    """One inclusion, in phantom coordinates (mm; surface at z = 0, depth positive down).

    Attributes:
        tumor_id: name used in the ground truth.
        kind: ``benign`` or ``malignant``.
        center_mm: (x, y) of the centre.
        depth_mm: depth of the centre below the surface.
        radius_mm: mean radius.
        modulus_kpa: Young's modulus of the inclusion material.
        material: free text for the ground truth (``silicone``, ``pla``).
        boundary_width_mm: width of the graded boundary (small = distinct boundary).
        harmonics: (order, relative amplitude, phase rad) of the outline perturbation.
        surface_roughness: relative amplitude of the top-surface unevenness.
        surface_phase_rad: phase of the top-surface pattern.
        severity_rank: 1 = least severe, or None when the scene does not rank.
    """

    tumor_id: str
    kind: str
    center_mm: tuple[float, float]
    depth_mm: float
    radius_mm: float
    modulus_kpa: float
    material: str = "silicone"
    boundary_width_mm: float = 0.05
    harmonics: tuple[tuple[int, float, float], ...] = field(default=())
    surface_roughness: float = 0.0
    surface_phase_rad: float = 0.0
    severity_rank: int | None = None

    def __post_init__(self) -> None:
        if self.kind not in TUMOR_KINDS | {FIDUCIAL}:
            raise ConfigError(f"tumor kind must be one of {sorted(TUMOR_KINDS)}, got {self.kind!r}")
        nums = (*self.center_mm, self.depth_mm, self.radius_mm, self.modulus_kpa,
                self.boundary_width_mm, self.surface_roughness)
        if not all(math.isfinite(v) for v in nums):
            raise ConfigError(f"tumor {self.tumor_id}: parameters must be finite")
        if self.radius_mm <= 0 or self.modulus_kpa <= 0 or self.boundary_width_mm <= 0:
            raise ConfigError(f"tumor {self.tumor_id}: radius, modulus and boundary width > 0")
        if self.depth_mm < 0:
            raise ConfigError(f"tumor {self.tumor_id}: depth_mm must be >= 0")
        amp = sum(abs(a) for _, a, _ in self.harmonics)
        if amp >= 0.5 or not 0 <= self.surface_roughness < 0.5:
            raise ConfigError(f"tumor {self.tumor_id}: perturbations must stay below 0.5")

    @property
    def reach_mm(self) -> float:
        """Largest distance from the centre at which the tumor has any effect."""
        amp = sum(abs(a) for _, a, _ in self.harmonics)
        return self.radius_mm * (1.0 + amp) + 4.0 * self.boundary_width_mm

    def outline_radius_mm(self, theta_rad: NDArray[np.float64]) -> NDArray[np.float64]:
        """Outline radius ``R(theta)`` (mm)."""
        r = np.ones_like(theta_rad)
        for order, amp, phase in self.harmonics:
            r = r + amp * np.cos(order * theta_rad + phase)
        return self.radius_mm * r

    def to_dict(self) -> dict[str, object]:
        """Plain-JSON description for the ground-truth file."""
        return {
            "id": self.tumor_id, "kind": self.kind, "material": self.material,
            "center_mm": [float(c) for c in self.center_mm], "depth_mm": self.depth_mm,
            "radius_mm": self.radius_mm, "modulus_kpa": self.modulus_kpa,
            "boundary_width_mm": self.boundary_width_mm,
            "harmonics": [list(h) for h in self.harmonics],
            "surface_roughness": self.surface_roughness, "severity_rank": self.severity_rank,
        }


def tumor_column_fraction(tumor: Tumor, dx_mm: NDArray[np.float64], dy_mm: NDArray[np.float64],
                          weight_radius_mm: float, thickness_mm: float) -> NDArray[np.float64]:
    """Depth-weighted share of each column occupied by the tumor, times boundary membership.

    Args:
        tumor: the inclusion.
        dx_mm, dy_mm: offsets of the column from the tumor centre (broadcastable arrays).
        weight_radius_mm: radius of the loaded disc that sets the depth weighting.
        thickness_mm: layer thickness (the column spans [0, thickness]).

    Returns:
        Values in [0, 1], the broadcast shape of ``dx_mm`` and ``dy_mm``.
    """
    rho = np.hypot(dx_mm, dy_mm)
    theta = np.arctan2(dy_mm, dx_mm)
    r_out = tumor.outline_radius_mm(theta)
    w = tumor.boundary_width_mm
    r_ext = r_out + 3.0 * w
    q = np.minimum(rho / r_ext, 1.0)
    half = r_out * np.sqrt(1.0 - q * q)
    if tumor.surface_roughness > 0:
        half = half * (1.0 + tumor.surface_roughness
                       * np.cos(7.0 * theta + tumor.surface_phase_rad)
                       * np.cos(3.0 * np.pi * rho / tumor.radius_mm))
    membership = 0.5 * erfc((rho - r_out) / (_SQRT2 * w))
    z1 = np.clip(tumor.depth_mm - half, 0.0, thickness_mm)
    z2 = np.clip(tumor.depth_mm + half, 0.0, thickness_mm)
    total = float(depth_weight_integral(thickness_mm, weight_radius_mm))
    share = (depth_weight_integral(z2, weight_radius_mm)
             - depth_weight_integral(z1, weight_radius_mm)) / total
    return np.clip(share * membership, 0.0, 1.0)
