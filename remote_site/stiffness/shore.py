"""Probe stiffness (N/mm) -> apparent modulus (kPa) -> Shore 00 -> display k.

Two documented steps, both configurable through :class:`ShoreConversion`:

1. Probe to modulus, by inverting the phantom's own contact model
   (:func:`remote_site.phantom.mechanics.punch_modulus_kpa`): a flat pad of effective radius
   ``a`` on a bonded layer of thickness ``h`` has ``k = 8/3 a E c(a/h)``, so
   ``E = k / (8/3 a c(a/h))``. Assumption: the tissue is a bonded, incompressible layer and
   the apparent modulus averages what lies under the pad.
2. Modulus to Shore 00, from the durometer standard (ASTM D2240, type 00): a hemispherical
   indenter of radius 1.19 mm (3/32 in diameter), full extension 2.54 mm, reading
   ``H = 100 (1 - d / 2.54 mm)``, spring force ``0.203 N + 0.00908 N * H``. At equilibrium the
   spring balances the Hertz force of the sphere on an incompressible half-space,
   ``F = 16/9 E sqrt(R) d^{3/2}``, which gives ``E(H)`` in closed form; we tabulate it and
   invert by interpolation (clamped to 0..100). For example E = 50 kPa reads about Shore 00 13
   and 300 kPa about 55. Assumption: linear elasticity at the durometer's large strains.
3. Shore 00 to the display's k with :class:`shared.hardness.HardnessTable`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from remote_site.phantom.mechanics import KPA_TO_N_PER_MM2, punch_modulus_kpa
from remote_site.phantom.phantom import SensorPad, SiliconeLayer
from shared.errors import ConfigError, InputDataError
from shared.hardness import HardnessTable

__all__ = ["ShoreConversion", "durometer_modulus_kpa"]


def durometer_modulus_kpa(shore00: ArrayLike, *, indenter_radius_mm: float = 1.19,
                          extension_mm: float = 2.54, spring_zero_n: float = 0.203,
                          spring_full_n: float = 1.111) -> NDArray[np.float64]:
    """Young's modulus (kPa) that reads ``shore00`` on a type 00 durometer (Hertz balance).

    Args:
        shore00: reading(s) in [0, 100).

    Raises:
        InputDataError: a reading outside [0, 100) or not finite.
    """
    h = np.asarray(shore00, dtype=float)
    if not np.isfinite(h).all() or np.any(h < 0) or np.any(h >= 100):
        raise InputDataError("Shore 00 readings must be finite and in [0, 100)")
    depth = extension_mm * (1.0 - h / 100.0)
    force = spring_zero_n + (spring_full_n - spring_zero_n) * h / 100.0
    e_n_per_mm2 = force / (16.0 / 9.0 * math.sqrt(indenter_radius_mm) * depth ** 1.5)
    return e_n_per_mm2 / KPA_TO_N_PER_MM2


@dataclass(frozen=True)
class ShoreConversion:
    """Probe stiffness -> Shore 00 -> k, for one pad and layer (see the module docstring).

    Attributes:
        pad_radius_mm: effective radius of the pad (default: the sim pad's).
        layer_thickness_mm: tissue thickness under the pad (default: the sim phantom's).
        indenter_radius_mm, extension_mm, spring_zero_n, spring_full_n: the durometer.
        table: the display's Shore 00 <-> k calibration.
    """

    pad_radius_mm: float = SensorPad().effective_radius_mm
    layer_thickness_mm: float = SiliconeLayer().thickness_mm
    indenter_radius_mm: float = 1.19
    extension_mm: float = 2.54
    spring_zero_n: float = 0.203
    spring_full_n: float = 1.111
    table: HardnessTable = field(default_factory=HardnessTable)

    def __post_init__(self) -> None:
        vals = (self.pad_radius_mm, self.layer_thickness_mm, self.indenter_radius_mm,
                self.extension_mm, self.spring_zero_n, self.spring_full_n)
        if not all(math.isfinite(v) and v > 0 for v in vals):
            raise ConfigError("shore conversion: all parameters must be finite and > 0")
        if self.spring_full_n <= self.spring_zero_n:
            raise ConfigError("shore conversion: spring_full_n must exceed spring_zero_n")

    def _curve(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        shore = np.linspace(0.0, 99.9, 2000)
        modulus = durometer_modulus_kpa(shore, indenter_radius_mm=self.indenter_radius_mm,
                                        extension_mm=self.extension_mm,
                                        spring_zero_n=self.spring_zero_n,
                                        spring_full_n=self.spring_full_n)
        return modulus, shore

    def modulus_kpa(self, k_n_per_mm: ArrayLike) -> NDArray[np.float64]:
        """Apparent modulus of the tissue under the pad.

        Raises:
            InputDataError: NaN or negative stiffness.
        """
        return punch_modulus_kpa(k_n_per_mm, self.pad_radius_mm, self.layer_thickness_mm)

    def shore00_from_modulus(self, modulus_kpa: ArrayLike) -> NDArray[np.float64]:
        """Shore 00 reading for a modulus (0 below the scale, 100 above it).

        Raises:
            InputDataError: NaN or negative modulus.
        """
        e = np.asarray(modulus_kpa, dtype=float)
        if not np.isfinite(e).all() or np.any(e < 0):
            raise InputDataError("modulus must be finite and >= 0")
        mod_tab, shore_tab = self._curve()
        out = np.interp(np.log(np.maximum(e, 1e-9)), np.log(mod_tab), shore_tab,
                        left=0.0, right=100.0)
        return np.asarray(out, dtype=float)

    def shore00(self, k_n_per_mm: ArrayLike) -> NDArray[np.float64]:
        """Shore 00 for a probe stiffness."""
        return self.shore00_from_modulus(self.modulus_kpa(k_n_per_mm))

    def display_k(self, k_n_per_mm: ArrayLike) -> NDArray[np.float64]:
        """The display's normalised stiffness k in [0.5, 1] for a probe stiffness."""
        return self.table.shore00_to_k(self.shore00(k_n_per_mm))
