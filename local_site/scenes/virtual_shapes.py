"""Virtual-shape scenes: one analytic shape with a chosen stiffness and friction.

The shape's footprint carries its stiffness and friction; the floor around it is rigid
(k = 1) and frictionless by default, like the paper's shape study (k = 1, friction off).
Stiffness is given either as Shore 00 hardness (converted once through a
:class:`~shared.hardness.HardnessTable`) or directly as k; never both.

For a demo::

    for name in SHAPE_NAMES:
        scene = make_shape_scene(name, shore00=40, friction=0.2)
        layers = scene.rasterize(scene.extent_mm(), 0.2)   # an image of the shape
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from local_site.scenes.base import SceneSample, SceneSource
from local_site.scenes.shapes import SHAPE_CLASSES, Shape
from shared.errors import ConfigError
from shared.hardness import K_MAX, K_MIN, HardnessTable

__all__ = [
    "SCENE_PARAMETERS",
    "SHAPE_NAMES",
    "VirtualShapeScene",
    "make_shape_scene",
    "shape_gallery",
    "shape_parameters",
]

#: the paper's six shapes, in its order
SHAPE_NAMES: tuple[str, ...] = tuple(SHAPE_CLASSES)
#: scene-level parameters accepted next to a shape's own ones
SCENE_PARAMETERS: tuple[str, ...] = ("shore00", "k", "friction", "floor_k", "floor_friction")


def _check_unit(value: float, name: str, lo: float, hi: float) -> float:
    v = float(value)
    if not (np.isfinite(v) and lo <= v <= hi):
        raise ConfigError(f"{name} must lie in [{lo}, {hi}], got {value!r}")
    return v


class VirtualShapeScene(SceneSource):
    """An analytic shape on a flat floor; content never changes (``version`` stays 0).

    Args:
        shape: the geometry (see :mod:`local_site.scenes.shapes`).
        stiffness_k: k of the shape in [0.5, 1]; exclusive with ``shore00``.
        shore00: Shore 00 hardness of the shape, mapped through ``hardness``.
        friction: friction of the shape in [0, 1].
        floor_k: k of the floor around the shape.
        floor_friction: friction of the floor.
        hardness: the Shore 00 <-> k table (default table when None).

    Raises:
        ConfigError: both or an out-of-range stiffness, or out-of-range friction.
    """

    kind: ClassVar[str] = "virtual"

    def __init__(self, shape: Shape, *, stiffness_k: float | None = None,
                 shore00: float | None = None, friction: float = 0.0,
                 floor_k: float = K_MAX, floor_friction: float = 0.0,
                 hardness: HardnessTable | None = None) -> None:
        super().__init__()
        if stiffness_k is not None and shore00 is not None:
            raise ConfigError("give the shape's stiffness as k or as shore00, not both")
        if shore00 is not None:
            s = _check_unit(shore00, "shore00", 0.0, 100.0)
            stiffness_k = float((hardness or HardnessTable()).shore00_to_k(s))
        self.shape = shape
        self.stiffness_k = _check_unit(K_MAX if stiffness_k is None else stiffness_k,
                                       "k", K_MIN, K_MAX)
        self.friction = _check_unit(friction, "friction", 0.0, 1.0)
        self.floor_k = _check_unit(floor_k, "floor_k", K_MIN, K_MAX)
        self.floor_friction = _check_unit(floor_friction, "floor_friction", 0.0, 1.0)

    @property
    def name(self) -> str:
        """The shape's name, e.g. ``"hemisphere"``."""
        return self.shape.NAME

    def extent_mm(self) -> tuple[float, float, float, float]:
        """A square about the shape's centre holding the footprint plus a 2 mm margin."""
        r = self.shape.bounding_radius_mm + 2.0
        return (self.shape.x_mm - r, self.shape.x_mm + r, self.shape.y_mm - r,
                self.shape.y_mm + r)

    def _sample(self, points_xy_mm: NDArray[np.float64]) -> SceneSample:
        u, v = self.shape.local(points_xy_mm)
        on = self.shape.footprint(u, v)
        h = self.shape.height_at(u, v)
        k = np.where(on, self.stiffness_k, self.floor_k)
        f = np.where(on, self.friction, self.floor_friction)
        return SceneSample(h, k, f, np.ones(h.shape, dtype=bool))

    def __repr__(self) -> str:
        return (f"VirtualShapeScene({self.shape!r}, k={self.stiffness_k:.3f}, "
                f"friction={self.friction:.3f})")


def shape_parameters(name: str) -> tuple[str, ...]:
    """Names of the geometric parameters of shape ``name`` (placement first).

    Raises:
        ConfigError: an unknown shape.
    """
    cls = _shape_class(name)
    return tuple(f.name for f in dataclasses.fields(cls))


def _shape_class(name: str) -> type[Shape]:
    key = name.strip().lower().replace("-", "_").replace(" ", "_")
    try:
        return SHAPE_CLASSES[key]
    except KeyError as err:
        raise ConfigError(f"unknown shape {name!r}; known: {', '.join(SHAPE_NAMES)}") from err


def make_shape_scene(name: str, *, hardness: HardnessTable | None = None,
                     **params: Any) -> VirtualShapeScene:
    """Build a virtual-shape scene from a shape name and keyword parameters.

    Args:
        name: one of :data:`SHAPE_NAMES` (``-`` and ``_`` are interchangeable).
        hardness: Shore 00 <-> k table for ``shore00``.
        **params: the shape's geometry (see :func:`shape_parameters`) and the scene
            parameters ``shore00`` or ``k``, ``friction``, ``floor_k``,
            ``floor_friction``.

    Returns:
        The scene.

    Raises:
        ConfigError: an unknown shape or parameter, or an invalid value.
    """
    cls = _shape_class(name)
    geometry = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(params) - geometry - set(SCENE_PARAMETERS))
    if unknown:
        raise ConfigError(f"{cls.NAME}: unknown parameter(s) {unknown}; valid: "
                          f"{sorted(geometry) + list(SCENE_PARAMETERS)}")
    shape = cls(**{k: v for k, v in params.items() if k in geometry})
    scene: Mapping[str, Any] = {k: v for k, v in params.items() if k in SCENE_PARAMETERS}
    return VirtualShapeScene(shape, stiffness_k=scene.get("k"), shore00=scene.get("shore00"),
                             friction=scene.get("friction", 0.0),
                             floor_k=scene.get("floor_k", K_MAX),
                             floor_friction=scene.get("floor_friction", 0.0),
                             hardness=hardness)


def shape_gallery(**scene_params: Any) -> dict[str, VirtualShapeScene]:
    """The six shapes with default geometry, each centred at the origin.

    Args:
        **scene_params: scene parameters applied to every shape (``shore00``, ``k``,
            ``friction``, ...).

    Returns:
        ``{name: scene}`` in the paper's order.
    """
    return {name: make_shape_scene(name, **scene_params) for name in SHAPE_NAMES}
