"""A scene backed by layers on a regular grid (layer files and the remote stream).

Values between grid samples are interpolated (order 0, 1 or 3, see
:mod:`local_site.render.interpolation`); since cubic weights can overshoot, every layer,
height included, is clipped to its own data range after interpolation
(``GridLayers.sample(..., clip=True)``), so cubic ringing never goes beyond the data (the
renderer then clamps heights to the display's stroke). Points outside the grid get the scene's
:class:`~local_site.scenes.base.OutsidePolicy` (flat by default); an empty scene (no
data yet) is "outside" everywhere.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from local_site.render.interpolation import DEFAULT_ORDER, INTERPOLATION_ORDERS, GridLayers
from local_site.scenes.base import OutsidePolicy, SceneSample, SceneSource
from shared.errors import ConfigError

__all__ = ["GRID_LAYER_ORDER", "GridScene"]

#: order of the layers inside a :class:`GridLayers` built by grid scenes
GRID_LAYER_ORDER: tuple[str, str, str] = ("height_mm", "stiffness_k", "friction")


class GridScene(SceneSource):
    """Base of grid-backed scenes.

    Args:
        order: interpolation order (0 nearest, 1 bilinear, 3 Keys cubic).
        outside: what to return outside the grid (default: flat, rigid, frictionless at
            height 0).

    Raises:
        ConfigError: an unsupported order.
    """

    kind: ClassVar[str] = "grid"

    def __init__(self, *, order: int = DEFAULT_ORDER, outside: OutsidePolicy | None = None) -> None:
        super().__init__()
        if order not in INTERPOLATION_ORDERS:
            raise ConfigError(f"interpolation order must be one of {INTERPOLATION_ORDERS}, "
                              f"got {order!r}")
        self.order = order
        self.outside = outside or OutsidePolicy()
        self._grid: GridLayers | None = None

    @property
    def grid(self) -> GridLayers | None:
        """The current layers, or None before any data."""
        return self._grid

    def extent_mm(self) -> tuple[float, float, float, float] | None:
        """Extent of the sample centres, or None while empty."""
        return None if self._grid is None else self._grid.extent_mm

    def _set_grid(self, grid: GridLayers | None) -> None:
        """Replace the content (one attribute store, so readers see old or new) and bump
        the version."""
        self._grid = grid
        self._version += 1

    def _sample(self, points_xy_mm: NDArray[np.float64]) -> SceneSample:
        grid = self._grid  # one read: a concurrent update cannot mix two grids
        n = points_xy_mm.shape[0]
        if grid is None:
            o = self.outside
            return SceneSample(np.full(n, o.height_mm), np.full(n, o.stiffness_k),
                               np.full(n, o.friction), np.zeros(n, dtype=bool))
        # clipped: cubic weights overshoot; even convex weights can round 1 ulp past a bound
        values, inside = grid.sample(points_xy_mm, self.order, clip=True)
        s = SceneSample(values[0], values[1], values[2], inside)
        if not inside.all():
            s = self.outside.apply(s)
        return s
