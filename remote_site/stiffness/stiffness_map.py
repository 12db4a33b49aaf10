"""A stiffness map built up over a scan, on a grid in phantom coordinates.

Each press adds its tissue stiffness to the cell under the pad centre. Cells keep a count,
a running mean (Welford) and variance, so the map reports a value and a confidence per cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from shared.errors import ConfigError, InputDataError

__all__ = ["MAX_CELLS", "MapBounds", "StiffnessMap"]

#: the most cells a map may have (three float64/int64 arrays: 24 MB)
MAX_CELLS = 1_000_000


@dataclass(frozen=True)
class MapBounds:
    """Rectangle covered by the map (phantom mm) and its cell size."""

    x_min_mm: float = -30.0
    x_max_mm: float = 30.0
    y_min_mm: float = -30.0
    y_max_mm: float = 30.0
    cell_mm: float = 2.0

    def __post_init__(self) -> None:
        vals = (self.x_min_mm, self.x_max_mm, self.y_min_mm, self.y_max_mm, self.cell_mm)
        if not all(math.isfinite(v) for v in vals) or self.cell_mm <= 0:
            raise ConfigError("map bounds must be finite with cell_mm > 0")
        if self.x_min_mm >= self.x_max_mm or self.y_min_mm >= self.y_max_mm:
            raise ConfigError("map bounds: min must be below max")
        width_mm, height_mm = self.x_max_mm - self.x_min_mm, self.y_max_mm - self.y_min_mm
        sides = (width_mm / self.cell_mm, height_mm / self.cell_mm)  # (inf for tiny cells)
        cells = sides[0] * sides[1] if max(sides) > MAX_CELLS else math.prod(self.shape)
        if cells > MAX_CELLS:
            raise ConfigError(
                f"a stiffness map of {width_mm:g} x {height_mm:g} mm in cells of "
                f"{self.cell_mm:g} mm would hold "
                f"{f'{cells:,.0f}' if math.isfinite(cells) else 'countless'} cells, more than "
                f"{MAX_CELLS:,}: the cells must be larger (remote.agent.stiffness_cell_mm)")

    @property
    def shape(self) -> tuple[int, int]:
        """(rows along y, columns along x)."""
        return (math.ceil((self.y_max_mm - self.y_min_mm) / self.cell_mm),
                math.ceil((self.x_max_mm - self.x_min_mm) / self.cell_mm))


class StiffnessMap:
    """Per-cell running statistics of stiffness estimates.

    Args:
        bounds: the covered rectangle and cell size.
    """

    def __init__(self, bounds: MapBounds | None = None) -> None:
        self.bounds = bounds or MapBounds()
        shape = self.bounds.shape
        self.count = np.zeros(shape, dtype=np.int64)
        self._mean = np.zeros(shape)
        self._m2 = np.zeros(shape)

    def cell_of(self, x_mm: float, y_mm: float) -> tuple[int, int] | None:
        """(row, column) of the cell holding (x, y), or None outside the map."""
        b = self.bounds
        if not (b.x_min_mm <= x_mm < b.x_max_mm and b.y_min_mm <= y_mm < b.y_max_mm):
            return None
        row = min(int((y_mm - b.y_min_mm) / b.cell_mm), self.count.shape[0] - 1)
        col = min(int((x_mm - b.x_min_mm) / b.cell_mm), self.count.shape[1] - 1)
        return row, col

    def add(self, x_mm: float, y_mm: float, k_n_per_mm: float) -> bool:
        """Add one estimate; returns False when (x, y) is outside the map.

        Raises:
            InputDataError: a non-finite or negative value.
        """
        vals = (x_mm, y_mm, k_n_per_mm)
        if not all(math.isfinite(v) for v in vals) or k_n_per_mm < 0:
            raise InputDataError("stiffness map: position and stiffness must be finite, k >= 0")
        cell = self.cell_of(x_mm, y_mm)
        if cell is None:
            return False
        self.count[cell] += 1
        delta = k_n_per_mm - self._mean[cell]
        self._mean[cell] += delta / self.count[cell]
        self._m2[cell] += delta * (k_n_per_mm - self._mean[cell])
        return True

    def value(self, x_mm: float, y_mm: float) -> float | None:
        """Mean stiffness of the cell at (x, y), or None when it has no estimate."""
        cell = self.cell_of(x_mm, y_mm)
        if cell is None or self.count[cell] == 0:
            return None
        return float(self._mean[cell])

    def mean_n_per_mm(self) -> NDArray[np.float64]:
        """Mean per cell; 0 where there is no estimate (see :attr:`count`)."""
        return np.where(self.count > 0, self._mean, 0.0)

    def mean_at(self, rows: NDArray[np.int64], cols: NDArray[np.int64]
                ) -> NDArray[np.float64]:
        """:meth:`mean_n_per_mm` at the cells ``[rows, cols]`` (numpy indexing, broadcast),
        without the whole map: a frame's patch reads a few dozen cells of it."""
        return np.where(self.count[rows, cols] > 0, self._mean[rows, cols], 0.0)

    def std_n_per_mm(self) -> NDArray[np.float64]:
        """Sample standard deviation per cell; 0 with fewer than two estimates."""
        var = np.where(self.count > 1, self._m2 / np.maximum(self.count - 1, 1), 0.0)
        return np.sqrt(np.maximum(var, 0.0))

    def confidence(self) -> NDArray[np.float64]:
        """Confidence in [0, 1) per cell: ``1 - 1 / (1 + n)`` damped by the relative spread."""
        mean = self.mean_n_per_mm()
        rel = np.where(mean > 0, self.std_n_per_mm() / np.maximum(mean, 1e-12), 0.0)
        return (1.0 - 1.0 / (1.0 + self.count)) / (1.0 + rel)

    def cell_centers_mm(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(x per column, y per row) of the cell centres."""
        b = self.bounds
        rows, cols = self.count.shape
        xs = b.x_min_mm + (np.arange(cols, dtype=np.float64) + 0.5) * b.cell_mm
        ys = b.y_min_mm + (np.arange(rows, dtype=np.float64) + 0.5) * b.cell_mm
        return xs, ys
