"""Shore 00 hardness <-> ArrayTac normalized stiffness k, through a calibration table.

The paper (Materials and Methods, "Calibration to standard stiffness metrics", Fig. 8G)
aligns the display's parameter ``k`` in [0.5, 1] with Shore 00 hardness by matching the
deformation of reference objects and of the display under the same force, and finds a
near-linear relation. It does not print the fitted numbers, so the default table below
is a stated assumption (k = 0.5 at Shore 00 10, k = 1 at Shore 00 90, linear between):
a station with a measured calibration passes its own points (for example from its TOML
configuration). Values outside the table are clamped to its ends, never extrapolated,
so the display is never asked for a k outside [0.5, 1].
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.errors import ConfigError, InputDataError

__all__ = ["DEFAULT_SHORE00_K_POINTS", "K_MAX", "K_MIN", "HardnessTable"]

K_MIN = 0.5
K_MAX = 1.0
#: (Shore 00, k) calibration points; assumption, see the module docstring
DEFAULT_SHORE00_K_POINTS: tuple[tuple[float, float], ...] = ((10.0, 0.5), (90.0, 1.0))


@dataclass(frozen=True)
class HardnessTable:
    """A monotone piecewise-linear Shore 00 <-> k calibration.

    Args:
        points: (shore00, k) pairs; Shore 00 strictly increasing in [0, 100], k strictly
            increasing in [0.5, 1].

    Raises:
        ConfigError: fewer than two points, non-monotone or out-of-range values.
    """

    points: tuple[tuple[float, float], ...] = DEFAULT_SHORE00_K_POINTS

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2:
            raise ConfigError("a hardness table needs at least two (shore00, k) points")
        if not np.isfinite(pts).all():
            raise ConfigError("hardness table points must be finite")
        shore, k = pts[:, 0], pts[:, 1]
        if np.any(np.diff(shore) <= 0) or np.any(np.diff(k) <= 0):
            raise ConfigError("hardness table: Shore 00 and k must both strictly increase")
        if shore[0] < 0 or shore[-1] > 100:
            raise ConfigError("hardness table: Shore 00 values must lie in [0, 100]")
        if k[0] < K_MIN or k[-1] > K_MAX:
            raise ConfigError(f"hardness table: k values must lie in [{K_MIN}, {K_MAX}]")

    @classmethod
    def from_points(cls, points: Sequence[Sequence[float]]) -> HardnessTable:
        """Build a table from any sequence of (shore00, k) pairs."""
        return cls(tuple((float(s), float(k)) for s, k in points))

    def _arrays(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        pts = np.asarray(self.points, dtype=float)
        return pts[:, 0], pts[:, 1]

    def shore00_to_k(self, shore00: ArrayLike) -> NDArray[np.float64]:
        """Map Shore 00 hardness to k (clamped to the table's k range).

        Raises:
            InputDataError: a NaN or infinite hardness.
        """
        s = np.asarray(shore00, dtype=float)
        if not np.isfinite(s).all():
            raise InputDataError("Shore 00 hardness must be finite")
        shore, k = self._arrays()
        return np.interp(s, shore, k)

    def k_to_shore00(self, k_value: ArrayLike) -> NDArray[np.float64]:
        """Map k back to Shore 00 hardness (clamped to the table's Shore range).

        Raises:
            InputDataError: a NaN or infinite k.
        """
        kv = np.asarray(k_value, dtype=float)
        if not np.isfinite(kv).all():
            raise InputDataError("k must be finite")
        shore, k = self._arrays()
        return np.interp(kv, k, shore)
