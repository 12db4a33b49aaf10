"""The six virtual shapes of the paper's shape-perception study, as analytic heights.

The paper (Results, "Intuitive Shape Rendering", Fig. 3A) renders a hemisphere, a
cone, a cube, a bow-shaped platform, a semi-ellipsoid and a triangular prism, sampled
at the finger position. It shows them only as pictures, so sizes here are our choice:
each fits the display's 5 mm stroke at gain 1 and spans a few 5.1 mm windows so it can
be explored by moving. Every shape stands on a flat floor at height 0.

Each shape has a centre ``(x_mm, y_mm)`` in the platform frame and a rotation
``angle_deg`` (counter-clockwise, about the centre); its own geometry is written in
local coordinates ``(u, v)``. ``height_at`` and ``footprint`` take arrays of local
coordinates; :meth:`Shape.local` converts platform points to them. Every shape except the
hemisphere (whose height is its radius) takes its peak height as ``height_mm``.

Interpretation of the "bow-shaped platform": a flat-topped plateau whose outline is a
bow, i.e. an annular sector (curved band) of constant height, so it has both the
curvature and the sharp edges participants reported. Its local origin is the middle of
the band (the ring centre lies at ``(0, -mid_radius)``, the bow bulges towards +v).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from shared.errors import ConfigError

__all__ = [
    "SHAPE_CLASSES",
    "BowPlatform",
    "Cone",
    "Cube",
    "Hemisphere",
    "SemiEllipsoid",
    "Shape",
    "TriangularPrism",
]

_SIZE_LIMIT_MM = 500.0


@dataclass(frozen=True, kw_only=True)
class Shape(ABC):
    """Base of the analytic shapes: placement and validation.

    Args:
        x_mm: centre x in the platform frame.
        y_mm: centre y in the platform frame.
        angle_deg: rotation about the centre, counter-clockwise.

    Raises:
        ConfigError: a non-finite placement or a size that is not positive and finite.
    """

    NAME: ClassVar[str] = ""
    #: fields that are sizes (must be positive)
    SIZE_FIELDS: ClassVar[tuple[str, ...]] = ()

    x_mm: float = 0.0
    y_mm: float = 0.0
    angle_deg: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ConfigError(f"{self.NAME}.{f.name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ConfigError(f"{self.NAME}.{f.name} must be finite, got {value!r}")
            if abs(value) > _SIZE_LIMIT_MM * (10 if f.name == "angle_deg" else 1):
                raise ConfigError(f"{self.NAME}.{f.name}={value} is implausibly large")
        for name in self.SIZE_FIELDS:
            if getattr(self, name) <= 0:
                raise ConfigError(f"{self.NAME}.{name} must be > 0, got {getattr(self, name)}")

    def local(self, points_xy_mm: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                               NDArray[np.float64]]:
        """Platform points ``(n, 2)`` -> local coordinates ``(u, v)`` of this shape."""
        dx = points_xy_mm[:, 0] - self.x_mm
        dy = points_xy_mm[:, 1] - self.y_mm
        if self.angle_deg == 0.0:
            return dx, dy
        c = math.cos(math.radians(self.angle_deg))
        s = math.sin(math.radians(self.angle_deg))
        return c * dx + s * dy, -s * dx + c * dy

    @property
    @abstractmethod
    def peak_height_mm(self) -> float:
        """Highest point of the shape."""

    @property
    @abstractmethod
    def bounding_radius_mm(self) -> float:
        """Radius of a circle about the centre that contains the whole footprint."""

    @abstractmethod
    def height_at(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        """Surface height at local coordinates (0 on the floor)."""

    @abstractmethod
    def footprint(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.bool_]:
        """True where the point lies on the shape (not on the floor)."""


@dataclass(frozen=True, kw_only=True)
class Hemisphere(Shape):
    """Half a ball: ``h = sqrt(R^2 - r^2)`` for ``r <= R``."""

    NAME: ClassVar[str] = "hemisphere"
    SIZE_FIELDS: ClassVar[tuple[str, ...]] = ("radius_mm",)
    radius_mm: float = 4.5

    @property
    def peak_height_mm(self) -> float:
        return self.radius_mm

    @property
    def bounding_radius_mm(self) -> float:
        return self.radius_mm

    def height_at(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.sqrt(np.maximum(self.radius_mm ** 2 - u * u - v * v, 0.0))

    def footprint(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.bool_]:
        return u * u + v * v <= self.radius_mm ** 2


@dataclass(frozen=True, kw_only=True)
class Cone(Shape):
    """A right circular cone: ``h = H (1 - r / R)`` for ``r <= R`` (R = ``radius_mm``)."""

    NAME: ClassVar[str] = "cone"
    SIZE_FIELDS: ClassVar[tuple[str, ...]] = ("radius_mm", "height_mm")
    radius_mm: float = 7.0
    height_mm: float = 4.5

    @property
    def peak_height_mm(self) -> float:
        return self.height_mm

    @property
    def bounding_radius_mm(self) -> float:
        return self.radius_mm

    def height_at(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        r = np.hypot(u, v)
        return self.height_mm * np.maximum(1.0 - r / self.radius_mm, 0.0)

    def footprint(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.bool_]:
        return np.hypot(u, v) <= self.radius_mm


@dataclass(frozen=True, kw_only=True)
class Cube(Shape):
    """A square block of side ``side_mm`` and height ``height_mm``.

    The height defaults to a stroke-safe 4.5 mm; set it equal to ``side_mm`` for a true
    cube and lower the renderer's height gain.
    """

    NAME: ClassVar[str] = "cube"
    SIZE_FIELDS: ClassVar[tuple[str, ...]] = ("side_mm", "height_mm")
    side_mm: float = 8.0
    height_mm: float = 4.5

    @property
    def peak_height_mm(self) -> float:
        return self.height_mm

    @property
    def bounding_radius_mm(self) -> float:
        return self.side_mm / math.sqrt(2.0)

    def height_at(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.where(self.footprint(u, v), self.height_mm, 0.0)

    def footprint(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.bool_]:
        half = self.side_mm / 2.0
        return (np.abs(u) <= half) & (np.abs(v) <= half)


@dataclass(frozen=True, kw_only=True)
class BowPlatform(Shape):
    """A flat-topped plateau shaped like a bow: an annular sector of constant height.

    The ring centre is at local ``(0, -(inner + outer) / 2)``; the band spans
    ``span_deg`` symmetrically about +v, between ``inner_radius_mm`` and
    ``outer_radius_mm``.
    """

    NAME: ClassVar[str] = "bow_platform"
    SIZE_FIELDS: ClassVar[tuple[str, ...]] = ("inner_radius_mm", "outer_radius_mm", "span_deg",
                                              "height_mm")
    inner_radius_mm: float = 7.0
    outer_radius_mm: float = 12.0
    span_deg: float = 120.0
    height_mm: float = 3.5

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.outer_radius_mm <= self.inner_radius_mm:
            raise ConfigError("bow_platform: outer_radius_mm must exceed inner_radius_mm")
        if self.span_deg > 360.0:
            raise ConfigError("bow_platform: span_deg must be at most 360")

    @property
    def mid_radius_mm(self) -> float:
        """Radius of the band's middle line (the local origin lies on it)."""
        return 0.5 * (self.inner_radius_mm + self.outer_radius_mm)

    @property
    def peak_height_mm(self) -> float:
        return self.height_mm

    @property
    def bounding_radius_mm(self) -> float:
        return self.mid_radius_mm + self.outer_radius_mm

    def height_at(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.where(self.footprint(u, v), self.height_mm, 0.0)

    def footprint(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.bool_]:
        ry = v + self.mid_radius_mm  # coordinates about the ring centre
        r = np.hypot(u, ry)
        # angle from +v (the bow's axis), in [0, pi]
        off_axis_deg = np.degrees(np.abs(np.arctan2(u, ry)))
        return ((r >= self.inner_radius_mm) & (r <= self.outer_radius_mm)
                & (off_axis_deg <= self.span_deg / 2.0))


@dataclass(frozen=True, kw_only=True)
class SemiEllipsoid(Shape):
    """Half an ellipsoid: ``h = c sqrt(1 - (u/a)^2 - (v/b)^2)`` inside the ellipse."""

    NAME: ClassVar[str] = "semi_ellipsoid"
    SIZE_FIELDS: ClassVar[tuple[str, ...]] = ("semi_axis_x_mm", "semi_axis_y_mm",
                                              "height_mm")
    semi_axis_x_mm: float = 10.0
    semi_axis_y_mm: float = 6.0
    height_mm: float = 4.5

    @property
    def peak_height_mm(self) -> float:
        return self.height_mm

    @property
    def bounding_radius_mm(self) -> float:
        return max(self.semi_axis_x_mm, self.semi_axis_y_mm)

    def _q(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        return (u / self.semi_axis_x_mm) ** 2 + (v / self.semi_axis_y_mm) ** 2

    def height_at(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.height_mm * np.sqrt(np.maximum(1.0 - self._q(u, v), 0.0))

    def footprint(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.bool_]:
        return self._q(u, v) <= 1.0


@dataclass(frozen=True, kw_only=True)
class TriangularPrism(Shape):
    """A prism lying on a rectangular face: ridge along v, ``h = H (1 - 2|u| / w)``."""

    NAME: ClassVar[str] = "triangular_prism"
    SIZE_FIELDS: ClassVar[tuple[str, ...]] = ("width_mm", "length_mm", "height_mm")
    width_mm: float = 10.0
    length_mm: float = 14.0
    height_mm: float = 4.5

    @property
    def peak_height_mm(self) -> float:
        return self.height_mm

    @property
    def bounding_radius_mm(self) -> float:
        return 0.5 * math.hypot(self.width_mm, self.length_mm)

    def height_at(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        ridge = self.height_mm * np.maximum(1.0 - 2.0 * np.abs(u) / self.width_mm, 0.0)
        return np.where(np.abs(v) <= self.length_mm / 2.0, ridge, 0.0)

    def footprint(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.bool_]:
        return (np.abs(u) <= self.width_mm / 2.0) & (np.abs(v) <= self.length_mm / 2.0)


#: shape name -> class, in the paper's order
SHAPE_CLASSES: dict[str, type[Shape]] = {
    cls.NAME: cls
    for cls in (Hemisphere, Cone, Cube, BowPlatform, SemiEllipsoid, TriangularPrism)
}
