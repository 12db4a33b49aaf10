"""Named phantom scenes from the paper, with seeded random tumor placement.

* ``localization`` (paper Fig. 5B left): two identical round silicone tumors.
* ``severity`` (Fig. 5B right): four tumors growing in size and hardening (soft silicone vs
  hard PLA): small silicone (rank 1) < medium silicone (2) < medium PLA (3) < large PLA (4).
  Size and hardness never decrease along the rank, so the order is unambiguous, and the
  probe stiffness over each tumor follows it (checked in the tests).
* ``breast`` (Fig. 6C): one benign (round, smooth, distinct boundary) and one malignant
  tumor (irregular outline, uneven surface, graded boundary, stiffer).

Tumors are placed uniformly at random (``numpy.random.default_rng(seed)``) inside the
region the default platform workspace maps onto (``PLACEMENT_HALF_MM`` around the
centre), at least ``min_separation_mm`` apart.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from remote_site.phantom.phantom import Phantom, SensorPad, SiliconeLayer
from remote_site.phantom.tumor import Tumor
from shared.errors import ConfigError

__all__ = ["PLACEMENT_HALF_MM", "SCENES", "make_scene", "scene_names"]

#: tumors are placed with centres in [-PLACEMENT_HALF_MM, +PLACEMENT_HALF_MM]^2
PLACEMENT_HALF_MM = 22.0
SILICONE_TUMOR_KPA = 300.0
PLA_KPA = 3.5e6  # PLA ~3.5 GPa: rigid compared with the tissue


def _place(rng: np.random.Generator, count: int, min_separation_mm: float,
           half_mm: float = PLACEMENT_HALF_MM, tries: int = 10_000) -> list[tuple[float, float]]:
    points: list[tuple[float, float]] = []
    for _ in range(tries):
        p = rng.uniform(-half_mm, half_mm, size=2)
        if all(math.dist(p, q) >= min_separation_mm for q in points):
            points.append((float(p[0]), float(p[1])))
            if len(points) == count:
                return points
    raise ConfigError(f"could not place {count} tumors {min_separation_mm} mm apart")


def _localization(rng: np.random.Generator) -> tuple[Tumor, ...]:
    centres = _place(rng, 2, 22.0)
    return tuple(Tumor(f"T{i + 1}", "benign", c, depth_mm=7.0, radius_mm=5.0,
                       modulus_kpa=SILICONE_TUMOR_KPA) for i, c in enumerate(centres))


def _severity(rng: np.random.Generator) -> tuple[Tumor, ...]:
    specs = [  # (radius mm, modulus kPa, material, severity rank)
        (3.5, SILICONE_TUMOR_KPA, "silicone", 1),
        (5.0, SILICONE_TUMOR_KPA, "silicone", 2),
        (5.0, PLA_KPA, "pla", 3),
        (6.5, PLA_KPA, "pla", 4),
    ]
    centres = _place(rng, 4, 22.0, half_mm=24.0)
    order = rng.permutation(4)  # which spec sits at which random centre
    return tuple(
        Tumor(f"T{i + 1}", "benign", centres[i], depth_mm=8.0, radius_mm=r, modulus_kpa=e,
              material=m, severity_rank=rank)
        for i, (r, e, m, rank) in enumerate(specs[k] for k in order))


def _breast(rng: np.random.Generator) -> tuple[Tumor, ...]:
    c_benign, c_malignant = _place(rng, 2, 25.0)
    benign = Tumor("benign", "benign", c_benign, depth_mm=7.5, radius_mm=6.0,
                   modulus_kpa=250.0, boundary_width_mm=0.05, severity_rank=1)
    orders = (3, 5, 7)
    amps = rng.uniform(0.05, 0.1, size=3)
    phases = rng.uniform(0.0, 2 * math.pi, size=4)
    malignant = Tumor(
        "malignant", "malignant", c_malignant, depth_mm=7.5, radius_mm=6.0, modulus_kpa=600.0,
        boundary_width_mm=1.5,
        harmonics=tuple((o, float(a), float(p)) for o, a, p in zip(orders, amps, phases,
                                                                     strict=False)),
        surface_roughness=0.2, surface_phase_rad=float(phases[3]), severity_rank=2)
    return benign, malignant


SCENES: dict[str, Callable[[np.random.Generator], tuple[Tumor, ...]]] = {
    "localization": _localization,
    "severity": _severity,
    "breast": _breast,
}


def scene_names() -> list[str]:
    """Names accepted by :func:`make_scene`."""
    return sorted(SCENES)


def make_scene(name: str, seed: int = 0, *, layer: SiliconeLayer | None = None,
               pad: SensorPad | None = None) -> Phantom:
    """Build a named phantom with seeded random tumor placement.

    Args:
        name: one of :func:`scene_names`.
        seed: placement seed (same seed, same phantom).
        layer: the silicone body (default 100 x 100 x 20 mm, 50 kPa).
        pad: the sensor pad (default :class:`SensorPad`).

    Returns:
        The phantom; ``phantom.ground_truth()`` describes it.

    Raises:
        ConfigError: an unknown scene name.
    """
    try:
        build = SCENES[name]
    except KeyError as err:
        raise ConfigError(f"unknown phantom scene {name!r}; known: {scene_names()}") from err
    tumors = build(np.random.default_rng(seed))
    return Phantom(layer=layer or SiliconeLayer(), tumors=tumors, pad=pad or SensorPad(),
                   name=name, seed=seed)
