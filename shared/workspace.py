"""Platform workspace <-> phantom coordinates (shared by both stations).

The local platform moves in a box of 60 x 60 x 185 mm (platform frame: origin at the
corner of its travel, +z up). The remote arm works in phantom coordinates (origin at the
centre of the phantom's top surface, +z up, surface at ``z = 0``; see
:mod:`remote_site.phantom.phantom`). The map is affine; in the plane a rotation by
``rotation_deg`` (counter-clockwise seen from above, about the platform's plane centre)
follows the scaling::

    [x_ph, y_ph] = R(rotation_deg) * scale_xy * [x_pl - center_x, y_pl - center_y]
                   + [offset_x, offset_y]
    z_ph = scale_z * (z_pl - z_surface)

The rotation and offset are where a registration (the arm <-> phantom calibration,
:mod:`remote_site.registration`) goes: the designed map with rotation 0 takes the platform to
the phantom; the registered map takes it to where the arm must go to reach that phantom point.

``z_surface`` is the platform height at which the pad touches the surface; lowering the
platform below it presses the phantom by ``scale_z`` mm per platform mm. Platform positions
are clamped to the platform box and phantom z to ``[-max_press_depth_mm, max_lift_mm]``
before mapping; :meth:`WorkspaceMap.inverse` maps phantom positions back (the local
station uses it to analyse what it received in phantom coordinates).

Settings resolve through :func:`shared.config.resolve_config`, section ``workspace``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.config import resolve_config
from shared.errors import ConfigError, InputDataError

__all__ = ["WorkspaceConfig", "WorkspaceMap", "load_workspace"]


@dataclass(frozen=True)
class WorkspaceConfig:
    """Platform box and its mapping onto the phantom (all mm).

    Attributes:
        platform_size_mm: travel of the platform (x, y, z).
        scale_xy: phantom mm per platform mm in the plane.
        offset_mm: phantom (x, y) the platform's plane centre maps to.
        rotation_deg: rotation of the plane mapping (counter-clockwise from above).
        scale_z: phantom mm per platform mm vertically (> 0).
        z_surface_mm: platform z at which the pad touches the phantom surface.
        max_press_depth_mm: deepest press allowed (phantom z >= -max_press_depth_mm).
        max_lift_mm: highest pad position above the surface.
    """

    platform_size_mm: tuple[float, float, float] = (60.0, 60.0, 185.0)
    scale_xy: float = 1.0
    offset_mm: tuple[float, float] = (0.0, 0.0)
    rotation_deg: float = 0.0
    scale_z: float = 0.1
    z_surface_mm: float = 40.0
    max_press_depth_mm: float = 6.0
    max_lift_mm: float = 20.0

    def __post_init__(self) -> None:
        nums = (*self.platform_size_mm, self.scale_xy, *self.offset_mm, self.rotation_deg,
                self.scale_z,
                self.z_surface_mm, self.max_press_depth_mm, self.max_lift_mm)
        if not all(math.isfinite(v) for v in nums):
            raise ConfigError("workspace: all values must be finite")
        if min(self.platform_size_mm) <= 0 or self.scale_xy <= 0 or self.scale_z <= 0:
            raise ConfigError("workspace: sizes and scales must be > 0")
        if abs(self.rotation_deg) > 180.0:
            raise ConfigError("workspace: rotation_deg must lie in [-180, 180]")
        if self.max_press_depth_mm < 0 or self.max_lift_mm < 0:
            raise ConfigError("workspace: max_press_depth_mm and max_lift_mm must be >= 0")


class WorkspaceMap:
    """The affine platform <-> phantom map with clamping.

    Args:
        config: the settings (defaults when None).
    """

    def __init__(self, config: WorkspaceConfig | None = None) -> None:
        self.config = config or WorkspaceConfig()
        c = self.config
        self._size = np.asarray(c.platform_size_mm, dtype=float)
        self._center = np.array([self._size[0] / 2, self._size[1] / 2, c.z_surface_mm])
        self._scale = np.array([c.scale_xy, c.scale_xy, c.scale_z])
        self._offset = np.array([c.offset_mm[0], c.offset_mm[1], 0.0])
        th = math.radians(c.rotation_deg)
        self._rot = np.array([[math.cos(th), -math.sin(th), 0.0],
                              [math.sin(th), math.cos(th), 0.0], [0.0, 0.0, 1.0]])
        corners = np.array([[x, y, z] for x in (0.0, self._size[0])
                            for y in (0.0, self._size[1]) for z in (0.0, self._size[2])])
        mapped = self.forward_unclamped(corners)
        lo, hi = mapped.min(axis=0), mapped.max(axis=0)
        lo[2] = max(lo[2], -c.max_press_depth_mm)
        hi[2] = min(hi[2], c.max_lift_mm)
        if lo[2] > hi[2]:
            raise ConfigError("workspace: the platform's z travel misses the allowed press range")
        self._phantom_lo, self._phantom_hi = lo, hi

    def registered(self, dx_mm: float, dy_mm: float, yaw_deg: float) -> WorkspaceMap:
        """This map followed by a rigid motion of the plane: ``q -> R(yaw) q + (dx, dy)``.

        A registration estimated as "the phantom point q lies at arm position
        R(yaw) q + d" gives the map from the platform to the arm's frame.
        """
        c = self.config
        th = math.radians(yaw_deg)
        rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        offset = rot @ np.asarray(c.offset_mm, float) + np.array([dx_mm, dy_mm])
        angle = (c.rotation_deg + yaw_deg + 180.0) % 360.0 - 180.0
        return WorkspaceMap(replace(c, offset_mm=(float(offset[0]), float(offset[1])),
                                    rotation_deg=float(angle)))

    @property
    def phantom_bounds_mm(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(lower, upper) corners of the reachable phantom box."""
        return tuple(self._phantom_lo.tolist()), tuple(self._phantom_hi.tolist())

    @staticmethod
    def _points(p: ArrayLike) -> NDArray[np.float64]:
        arr = np.asarray(p, dtype=float)
        if arr.shape[-1:] != (3,):
            raise InputDataError(f"positions must have 3 coordinates, got shape {arr.shape}")
        if not np.isfinite(arr).all():
            raise InputDataError("positions must be finite")
        return arr

    def clamp_platform(self, platform_mm: ArrayLike) -> NDArray[np.float64]:
        """Clamp platform position(s) to the platform box."""
        return np.clip(self._points(platform_mm), 0.0, self._size)

    def clamp_phantom(self, phantom_mm: ArrayLike) -> NDArray[np.float64]:
        """Clamp phantom position(s) to the reachable, press-limited box."""
        return np.clip(self._points(phantom_mm), self._phantom_lo, self._phantom_hi)

    def forward_unclamped(self, platform_mm: ArrayLike) -> NDArray[np.float64]:
        """The affine map alone (no clamping)."""
        p = self._points(platform_mm)
        return (self._scale * (p - self._center)) @ self._rot.T + self._offset

    def forward(self, platform_mm: ArrayLike) -> NDArray[np.float64]:
        """Platform position(s) -> phantom position(s), clamped on both sides.

        Raises:
            InputDataError: wrong shape or non-finite values.
        """
        return self.clamp_phantom(self.forward_unclamped(self.clamp_platform(platform_mm)))

    def inverse(self, phantom_mm: ArrayLike) -> NDArray[np.float64]:
        """Phantom position(s) -> platform position(s) (clamped to the reachable box first).

        With a rotation the reachable box is the bounding box of the rotated platform box.

        Raises:
            InputDataError: wrong shape or non-finite values.
        """
        p = self.clamp_phantom(phantom_mm)
        return ((p - self._offset) @ self._rot) / self._scale + self._center

    def phantom_xy_to_platform(self, xy_mm: Sequence[float]) -> tuple[float, float]:
        """Convenience: a phantom (x, y) to the platform (x, y) (no z involved)."""
        x, y = (float(v) for v in xy_mm)
        out = self.inverse([x, y, 0.0])
        return float(out[0]), float(out[1])


def load_workspace(explicit: Mapping[str, Any] | None = None,
                   toml_path: str | os.PathLike[str] | None = None) -> WorkspaceMap:
    """Resolve :class:`WorkspaceConfig` (section ``workspace``) and build the map.

    Raises:
        ConfigError: invalid settings.
    """
    return WorkspaceMap(resolve_config(WorkspaceConfig, "workspace", explicit=explicit,
                                       toml_path=toml_path))
