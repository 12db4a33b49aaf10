"""Named phantom scenes: the TOML files shipped in ``remote_site/phantom/data/scenes``.

Each scene is an ordinary phantom file (:mod:`remote_site.phantom.phantom_file`) read through
the same loader as ``--phantom FILE.toml``; the seed drives its random placement:

* ``localization``: two identical silicone tumors (radius 5 mm, 7 mm deep, 300 kPa).
* ``severity``: four tumors 8 mm deep ranked by size and hardness (two silicone, two PLA).
* ``breast``: one benign (round, distinct boundary, 250 kPa) and one malignant (lobulated,
  graded boundary, uneven top, 600 kPa) tumor, both radius 6 mm at 7.5 mm.
"""

from __future__ import annotations

from dataclasses import replace

from remote_site.phantom.phantom import Phantom, SensorPad, SiliconeLayer
from remote_site.phantom.phantom_file import load_phantom, scene_file, shipped_scene_names

__all__ = ["make_scene", "scene_names"]


def scene_names() -> list[str]:
    """Names accepted by :func:`make_scene`."""
    return shipped_scene_names()


def make_scene(name: str, seed: int = 0, *, layer: SiliconeLayer | None = None,
               pad: SensorPad | None = None) -> Phantom:
    """Build a named phantom with seeded random tumor placement.

    Args:
        name: one of :func:`scene_names`.
        seed: placement seed (same seed, same phantom).
        layer: replaces the file's silicone body (the inclusions must still fit in it).
        pad: the sensor pad (default :class:`SensorPad`).

    Returns:
        The phantom; ``phantom.ground_truth()`` describes it.

    Raises:
        ConfigError: an unknown scene name.
    """
    phantom = load_phantom(scene_file(name), seed, pad=pad)
    if layer is None:
        return phantom
    return replace(phantom, layer=layer)
