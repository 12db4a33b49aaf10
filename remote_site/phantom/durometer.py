"""The type 00 durometer: which Young's modulus reads a given Shore 00 (simulator physics).

From the durometer standard (ASTM D2240, type 00): a hemispherical indenter of radius
1.19 mm (3/32 in diameter), full extension 2.54 mm, reading ``H = 100 (1 - d / 2.54 mm)``,
spring force ``0.203 N + 0.00908 N * H``. At equilibrium the spring balances the Hertz force
of the sphere on an incompressible half-space, ``F = 16/9 E sqrt(R) d^{3/2}``, which gives
``E(H)`` in closed form. For example E = 50 kPa reads about Shore 00 13 and 300 kPa about 55.
Assumption: linear elasticity at the durometer's large strains.

The simulator uses it to make reference blocks of known hardness
(:mod:`remote_site.phantom.reference_presses`); product code never does: it reads the
hardness from a stiffness calibration.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from remote_site.phantom.mechanics import KPA_TO_N_PER_MM2
from shared.errors import InputDataError

__all__ = ["durometer_modulus_kpa"]


def durometer_modulus_kpa(shore00: ArrayLike, *, indenter_radius_mm: float = 1.19,
                          extension_mm: float = 2.54, spring_zero_n: float = 0.203,
                          spring_full_n: float = 1.111) -> NDArray[np.float64]:
    """Young's modulus (kPa) that reads ``shore00`` on a type 00 durometer (Hertz balance).

    Args:
        shore00: reading(s) in [0, 100).
        indenter_radius_mm: radius of the hemispherical indenter.
        extension_mm: indenter extension at a reading of 0.
        spring_zero_n: spring force at a reading of 0.
        spring_full_n: spring force at a reading of 100.

    Returns:
        The modulus per reading (kPa).

    Raises:
        InputDataError: a reading outside [0, 100) or not finite.
    """
    h = np.asarray(shore00, dtype=float)
    if not np.isfinite(h).all() or np.any(h < 0) or np.any(h >= 100):
        raise InputDataError("Shore 00 readings must be finite and in [0, 100)")
    depth = extension_mm * (1.0 - h / 100.0)
    force = spring_zero_n + (spring_full_n - spring_zero_n) * h / 100.0
    e_n_per_mm2 = force / (16.0 / 9.0 * math.sqrt(indenter_radius_mm) * depth ** 1.5)
    return np.asarray(e_n_per_mm2 / KPA_TO_N_PER_MM2, dtype=float)
