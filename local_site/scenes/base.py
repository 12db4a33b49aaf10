"""The one interface every scene source implements.

A scene is a surface the operator explores: at any point (x, y) of the platform frame
(mm) it has a height (mm), a display stiffness k in [0.5, 1] and a friction f in
[0, 1]. Scenes always answer in k: a source that stores Shore 00 hardness converts it
through :class:`shared.hardness.HardnessTable` when it is built, once.

``version`` is an integer that changes whenever the content changes (a new tactile
frame, a cleared stream); a renderer that sees the same scene object with the same
version at the same position may reuse its previous output.

Backends implement ``_sample``; the public :meth:`SceneSource.sample` validates the
points and the shapes of what the backend returns.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.errors import ConfigError, InputDataError
from shared.hardness import K_MAX, K_MIN

__all__ = ["MAX_SCENE_HEIGHT_MM", "OutsidePolicy", "SceneSample", "SceneSource"]

log = logging.getLogger(__name__)

#: largest |height| a scene may hold; the renderer scales heights to the 5 mm stroke
MAX_SCENE_HEIGHT_MM = 1000.0
_MAX_RASTER_DIM = 4096


class SceneSample(NamedTuple):
    """What a scene holds at some points (all arrays have the points' shape).

    Attributes:
        height_mm: surface height in mm (scene units, before display scaling).
        stiffness_k: display stiffness k in [0.5, 1].
        friction: normalized friction in [0, 1].
        inside: False where the point lies outside the scene's data and the value is a
            degraded stand-in (see :class:`OutsidePolicy`).
    """

    height_mm: NDArray[np.float64]
    stiffness_k: NDArray[np.float64]
    friction: NDArray[np.float64]
    inside: NDArray[np.bool_]


#: the dtypes of a :class:`SceneSample`'s arrays, in field order
_SAMPLE_DTYPES = (np.dtype(np.float64),) * 3 + (np.dtype(np.bool_),)


@dataclass(frozen=True)
class OutsidePolicy:
    """What a bounded scene returns at points outside its data.

    Args:
        mode: ``"flat"`` gives the constant surface below; ``"edge"`` continues the
            nearest edge value of the data (holds the border).
        height_mm: height of the flat surface (scene units).
        stiffness_k: stiffness of the flat surface (1 = rigid, the safe choice).
        friction: friction of the flat surface (0: no vibration).

    Raises:
        ConfigError: unknown mode or out-of-range values.
    """

    mode: str = "flat"
    height_mm: float = 0.0
    stiffness_k: float = K_MAX
    friction: float = 0.0

    MODES: ClassVar[tuple[str, ...]] = ("flat", "edge")

    def __post_init__(self) -> None:
        if self.mode not in self.MODES:
            raise ConfigError(f"outside policy must be one of {self.MODES}, got {self.mode!r}")
        for name in ("height_mm", "stiffness_k", "friction"):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.number)) \
                    or isinstance(v, np.complexfloating):
                raise ConfigError(f"outside {name} must be a number, got {v!r}")
        if not (np.isfinite(self.height_mm) and abs(self.height_mm) <= MAX_SCENE_HEIGHT_MM):
            raise ConfigError(f"outside height must be finite, |h| <= {MAX_SCENE_HEIGHT_MM}")
        if not K_MIN <= self.stiffness_k <= K_MAX:
            raise ConfigError(f"outside stiffness k must lie in [{K_MIN}, {K_MAX}]")
        if not 0.0 <= self.friction <= 1.0:
            raise ConfigError("outside friction must lie in [0, 1]")

    def apply(self, sample: SceneSample) -> SceneSample:
        """Replace the values of ``sample`` outside the data according to the mode."""
        if self.mode == "edge" or bool(sample.inside.all()):
            return sample
        out = ~sample.inside
        h = np.where(out, self.height_mm, sample.height_mm)
        k = np.where(out, self.stiffness_k, sample.stiffness_k)
        f = np.where(out, self.friction, sample.friction)
        return SceneSample(h, k, f, sample.inside)


class SceneSource(ABC):
    """A tactile scene sampled at arbitrary (x, y) points of the platform frame.

    Subclasses implement :meth:`_sample`; they bump ``self._version`` when their content
    changes.
    """

    #: short name of the scene kind ("virtual", "layer_file", "remote")
    kind: ClassVar[str] = "scene"

    def __init__(self) -> None:
        self._version = 0

    @property
    def version(self) -> int:
        """Changes (increases) whenever the content changes."""
        return self._version

    def extent_mm(self) -> tuple[float, float, float, float] | None:
        """``(x_min, x_max, y_min, y_max)`` of the data, or None when unbounded/empty."""
        return None

    def sample(self, points_xy_mm: ArrayLike) -> SceneSample:
        """Evaluate the scene at points.

        Args:
            points_xy_mm: array ``(..., 2)`` of (x, y) in mm.

        Returns:
            A :class:`SceneSample` whose arrays have shape ``points.shape[:-1]``.

        Raises:
            InputDataError: points of the wrong shape or not finite.
        """
        pts = np.asarray(points_xy_mm, dtype=np.float64)
        if pts.ndim < 1 or pts.shape[-1] != 2:
            raise InputDataError(f"scene points must have shape (..., 2), got {pts.shape}")
        if not np.isfinite(pts).all():
            raise InputDataError("scene points contain NaN or Inf")
        flat = pts.reshape(-1, 2)
        return self._conformed(self._sample(flat), flat.shape[0], pts.shape[:-1])

    def sample_flat(self, points_xy_mm: NDArray[np.float64]) -> SceneSample:
        """:meth:`sample` at points the caller has checked: a float64 array ``(n, 2)`` of
        finite values (the renderer's 1 kHz path: its pins' positions). The arrays have
        shape ``(n,)`` and are contiguous (the types the renderer's compiled pass takes).

        Raises:
            InputDataError: the scene returned arrays of the wrong shape.
        """
        s = self._sample(points_xy_mm)
        n = points_xy_mm.shape[0]
        for arr, dtype in zip(s, _SAMPLE_DTYPES, strict=True):
            if type(arr) is not np.ndarray or arr.shape != (n,) or arr.dtype != dtype \
                    or not arr.flags.c_contiguous:
                return self._conformed(s, n, (n,))
        return s

    def _conformed(self, s: SceneSample, n: int, lead: tuple[int, ...]) -> SceneSample:
        """``s`` (what :meth:`_sample` returned for ``n`` points) checked, as contiguous
        float64 and bool arrays of shape ``lead``."""
        for name, arr in zip(SceneSample._fields, s, strict=True):
            if np.shape(arr) != (n,):
                raise InputDataError(f"{type(self).__name__} returned {name} of shape "
                                     f"{np.shape(arr)} for {n} points")
        return SceneSample(np.ascontiguousarray(s.height_mm, dtype=np.float64).reshape(lead),
                           np.ascontiguousarray(s.stiffness_k, dtype=np.float64).reshape(lead),
                           np.ascontiguousarray(s.friction, dtype=np.float64).reshape(lead),
                           np.ascontiguousarray(s.inside, dtype=bool).reshape(lead))

    @abstractmethod
    def _sample(self, points_xy_mm: NDArray[np.float64]) -> SceneSample:
        """Evaluate finite points ``(n, 2)``; return four ``(n,)`` arrays."""

    def rasterize(self, extent_mm: tuple[float, float, float, float],
                  pitch_mm: float) -> dict[str, NDArray[np.float64]]:
        """Sample the scene on a regular grid (row along +y, column along +x).

        Args:
            extent_mm: ``(x_min, x_max, y_min, y_max)`` of the first and last samples.
            pitch_mm: wanted grid spacing (> 0); the number of samples per side is rounded
                so the first and last samples sit exactly on the extent (the actual
                spacing is ``(x_max - x_min) / (nx - 1)``).

        Returns:
            ``{"height_mm", "stiffness_k", "friction"}`` arrays ``(ny, nx)``.

        Raises:
            InputDataError: a degenerate extent or pitch.
        """
        x0, x1, y0, y1 = (float(v) for v in extent_mm)
        if not (np.isfinite([x0, x1, y0, y1, pitch_mm]).all() and pitch_mm > 0
                and x1 > x0 and y1 > y0):
            raise InputDataError(f"bad raster extent {extent_mm} or pitch {pitch_mm}")
        # steps per side as floats first: an extent wider than the float range (or a tiny
        # pitch) makes them inf, which round() cannot turn into an int
        steps_x, steps_y = (x1 - x0) / pitch_mm, (y1 - y0) / pitch_mm
        if not (steps_x < _MAX_RASTER_DIM and steps_y < _MAX_RASTER_DIM):
            raise InputDataError(f"raster of {steps_y + 1:.6g} x {steps_x + 1:.6g} samples "
                                 f"(extent {extent_mm}, pitch {pitch_mm} mm) is too large "
                                 f"(max {_MAX_RASTER_DIM} per side)")
        nx = round(steps_x) + 1
        ny = round(steps_y) + 1
        if nx > _MAX_RASTER_DIM or ny > _MAX_RASTER_DIM:
            raise InputDataError(f"raster of {ny} x {nx} samples is too large "
                                 f"(max {_MAX_RASTER_DIM} per side)")
        gx, gy = np.meshgrid(np.linspace(x0, x1, nx), np.linspace(y0, y1, ny))
        s = self.sample(np.stack([gx, gy], axis=-1))
        return {"height_mm": s.height_mm, "stiffness_k": s.stiffness_k, "friction": s.friction}
