"""Closed-form contact mechanics used by the phantom and by the stiffness stage.

Units: lengths in mm, moduli in kPa, forces in N, stiffness in N/mm
(1 kPa = 1e-3 N/mm^2).

* Flat circular punch of radius ``a`` on an incompressible (nu = 0.5) half-space:
  ``F = 2 a E* d`` with ``E* = E / (1 - nu^2) = 4 E / 3``, so ``k = 8 a E / 3`` (linear in
  depth, which is why the paper's stiffness = force / depth is well defined for a flat pad).
* Finite, bonded layer of thickness ``h``: the half-space result is multiplied by the
  polynomial thin-layer correction of Dimitriadis et al. (Biophys. J. 2002) for a bonded,
  incompressible sample, ``1 + 1.133 c + 1.283 c^2 + 0.769 c^3 + 0.0975 c^4`` with
  ``c = a / h``. (Dimitriadis derive it for a sphere with ``c = sqrt(R d) / h``, the contact
  radius over the thickness; we apply it with the flat punch's fixed contact radius. This is an
  approximation, stated here once; it is exact in the half-space limit ``h -> inf``.)
* Depth weighting: the axial stress under a uniformly loaded disc of radius ``a`` decays as
  ``w(z) = 1 - z^3 / (a^2 + z^2)^{3/2}`` (Boussinesq). Its integral
  ``W(z) = z - sqrt(a^2 + z^2) - a^2 / sqrt(a^2 + z^2) + 2 a`` weights how much a stiff
  inclusion between depths ``z1`` and ``z2`` stiffens the column above it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.errors import InputDataError

__all__ = [
    "KPA_TO_N_PER_MM2",
    "depth_weight_integral",
    "punch_modulus_kpa",
    "punch_stiffness_n_per_mm",
    "thin_layer_correction",
]

KPA_TO_N_PER_MM2 = 1.0e-3
_DIMITRIADIS = (1.0, 1.133, 1.283, 0.769, 0.0975)


def _positive(name: str, value: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=float)
    if not np.isfinite(arr).all() or np.any(arr <= 0):
        raise InputDataError(f"{name} must be finite and > 0")
    return arr


def thin_layer_correction(radius_mm: ArrayLike, thickness_mm: ArrayLike) -> NDArray[np.float64]:
    """Bonded-layer correction factor (>= 1) for a punch of ``radius_mm`` on ``thickness_mm``.

    Args:
        radius_mm: contact radius a (mm), > 0.
        thickness_mm: layer thickness h (mm), > 0; ``np.inf`` gives the half-space (1.0).

    Returns:
        The factor ``1 + 1.133 c + 1.283 c^2 + 0.769 c^3 + 0.0975 c^4``, ``c = a / h``.

    Raises:
        InputDataError: a non-positive or NaN radius or thickness.
    """
    a = _positive("radius_mm", radius_mm)
    h = np.asarray(thickness_mm, dtype=float)
    if np.isnan(h).any() or np.any(h <= 0):
        raise InputDataError("thickness_mm must be > 0")
    c = a / h
    return np.asarray(np.polynomial.polynomial.polyval(c, _DIMITRIADIS), dtype=float)


def punch_stiffness_n_per_mm(modulus_kpa: ArrayLike, radius_mm: float,
                             thickness_mm: float) -> NDArray[np.float64]:
    """Contact stiffness of a flat punch on a bonded incompressible layer.

    Args:
        modulus_kpa: Young's modulus E of the layer (kPa), >= 0.
        radius_mm: punch radius a (mm).
        thickness_mm: layer thickness h (mm).

    Returns:
        ``k = 8/3 * a * E * correction(a/h)`` in N/mm.

    Raises:
        InputDataError: NaN or negative modulus, non-positive radius or thickness.
    """
    e = np.asarray(modulus_kpa, dtype=float)
    if not np.isfinite(e).all() or np.any(e < 0):
        raise InputDataError("modulus_kpa must be finite and >= 0")
    corr = thin_layer_correction(radius_mm, thickness_mm)
    return 8.0 / 3.0 * float(radius_mm) * e * KPA_TO_N_PER_MM2 * corr


def punch_modulus_kpa(stiffness_n_per_mm: ArrayLike, radius_mm: float,
                      thickness_mm: float) -> NDArray[np.float64]:
    """Inverse of :func:`punch_stiffness_n_per_mm`: the apparent modulus for a stiffness.

    Raises:
        InputDataError: NaN or negative stiffness.
    """
    k = np.asarray(stiffness_n_per_mm, dtype=float)
    if not np.isfinite(k).all() or np.any(k < 0):
        raise InputDataError("stiffness_n_per_mm must be finite and >= 0")
    unit = punch_stiffness_n_per_mm(1.0, radius_mm, thickness_mm)
    return k / unit


def depth_weight_integral(z_mm: ArrayLike, radius_mm: float) -> NDArray[np.float64]:
    """``W(z)``: integral over [0, z] of the Boussinesq axial-stress weight under a disc.

    Monotone increasing from ``W(0) = 0`` towards ``2 a`` as ``z -> inf``.

    Args:
        z_mm: depth(s) below the surface (mm), clipped at 0.
        radius_mm: loaded disc radius a (mm), > 0.
    """
    a = float(radius_mm)
    z = np.maximum(np.asarray(z_mm, dtype=float), 0.0)
    r = np.sqrt(a * a + z * z)
    return 2.0 * a - a * a / (z + r) - a * a / r  # z - r = -a^2 / (z + r), no cancellation
