"""Shore 00 hardness <-> ArrayTac normalized stiffness k, through a calibration table.

The paper (Materials and Methods, "Calibration to standard stiffness metrics", Fig. 8G)
aligns the display's parameter ``k`` in [0.5, 1] with Shore 00 hardness by matching the
deformation of reference objects and of the display under the same force, and finds a
near-linear relation. It does not print the fitted numbers, so the default table below
is a stated assumption (k = 0.5 at Shore 00 10, k = 1 at Shore 00 90, linear between):
a station with a measured calibration passes its own points (for example from its TOML
configuration). Values outside the table are clamped to its ends, never extrapolated,
so the display is never asked for a k outside [0.5, 1].

Probe stiffness (N/mm, what the remote station measures) reaches k through the same table:
:class:`StiffnessToK` = the probe's measured N/mm -> Shore 00 curve (calibration data, see
:mod:`shared.stiffness_calibration`) followed by :class:`HardnessTable`. It is the only
N/mm -> k mapping of the project; both stations use it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.errors import ConfigError, InputDataError

__all__ = ["DEFAULT_SHORE00_K_POINTS", "K_MAX", "K_MIN", "HardnessTable", "StiffnessShoreCurve",
           "StiffnessToK"]

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


@dataclass(frozen=True)
class StiffnessShoreCurve:
    """A monotone probe stiffness (N/mm) -> Shore 00 curve, from a stiffness calibration.

    Interpolated linearly in ``log(stiffness)`` between the points and clamped to the end
    points outside them (never extrapolated). A stiffness of 0 reads the softest point.

    Args:
        points: (stiffness_n_per_mm, shore00) pairs; both strictly increasing, stiffness
            finite and > 0, Shore 00 in [0, 100].

    Raises:
        ConfigError: fewer than two points, non-monotone or out-of-range values.
    """

    points: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2:
            raise ConfigError("a stiffness curve needs at least two (n_per_mm, shore00) points")
        if not np.isfinite(pts).all() or np.any(pts[:, 0] <= 0):
            raise ConfigError("stiffness curve: stiffnesses must be finite and > 0")
        if np.any(np.diff(pts[:, 0]) <= 0) or np.any(np.diff(pts[:, 1]) <= 0):
            raise ConfigError("stiffness curve: stiffness and Shore 00 must both strictly "
                              "increase")
        if pts[0, 1] < 0 or pts[-1, 1] > 100:
            raise ConfigError("stiffness curve: Shore 00 values must lie in [0, 100]")

    @classmethod
    def from_points(cls, points: Sequence[Sequence[float]]) -> StiffnessShoreCurve:
        """Build a curve from any sequence of (stiffness_n_per_mm, shore00) pairs."""
        return cls(tuple((float(k), float(s)) for k, s in points))

    def shore00(self, stiffness_n_per_mm: ArrayLike) -> NDArray[np.float64]:
        """Shore 00 for a probe stiffness (clamped to the curve's Shore range).

        Raises:
            InputDataError: a NaN, infinite or negative stiffness.
        """
        k = np.asarray(stiffness_n_per_mm, dtype=float)
        if not np.isfinite(k).all() or np.any(k < 0):
            raise InputDataError("stiffness must be finite and >= 0")
        pts = np.asarray(self.points, dtype=float)
        log_k = np.log(np.maximum(k, np.finfo(float).tiny))
        return np.asarray(np.interp(log_k, np.log(pts[:, 0]), pts[:, 1]), dtype=float)


@dataclass(frozen=True)
class StiffnessToK:
    """The one probe stiffness (N/mm) -> display k mapping of both stations.

    N/mm -> Shore 00 through the stiffness calibration's curve, then Shore 00 -> k through
    the display's :class:`HardnessTable`; the result always lies in [0.5, 1].

    Args:
        curve: N/mm -> Shore 00 (from the probe's stiffness calibration).
        table: Shore 00 -> k (the display's calibration).
    """

    curve: StiffnessShoreCurve
    table: HardnessTable = field(default_factory=HardnessTable)

    def shore00(self, stiffness_n_per_mm: ArrayLike) -> NDArray[np.float64]:
        """Shore 00 for a probe stiffness (see :meth:`StiffnessShoreCurve.shore00`)."""
        return self.curve.shore00(stiffness_n_per_mm)

    def k(self, stiffness_n_per_mm: ArrayLike) -> NDArray[np.float64]:
        """Display k in [0.5, 1] for a probe stiffness.

        Raises:
            InputDataError: a NaN, infinite or negative stiffness.
        """
        k_value = self.table.shore00_to_k(self.curve.shore00(stiffness_n_per_mm))
        return np.clip(k_value, K_MIN, K_MAX)
