"""Analytic contact depth maps (mm, >= 0) on a sensor grid: ball, cone, flat punch.

Used to calibrate the simulated sensor (ball presses) and to test the reconstruction
against shapes with known heights.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ball_depth_mm", "cone_depth_mm", "flat_punch_depth_mm"]


def _radius_mm(shape_hw: tuple[int, int], mm_per_px: float, center_x_px: float,
               center_y_px: float) -> np.ndarray:
    rows, cols = np.mgrid[0:shape_hw[0], 0:shape_hw[1]].astype(np.float64)
    return np.hypot(cols - center_x_px, rows - center_y_px) * mm_per_px


def ball_depth_mm(shape_hw: tuple[int, int], mm_per_px: float, center_x_px: float,
                  center_y_px: float, ball_radius_mm: float, depth_mm: float) -> np.ndarray:
    """Depth map of a rigid ball pressed ``depth_mm`` into the gel (a sphere cap)."""
    r = _radius_mm(shape_hw, mm_per_px, center_x_px, center_y_px)
    cap = np.sqrt(np.clip(ball_radius_mm**2 - r**2, 0.0, None)) - (ball_radius_mm - depth_mm)
    return np.clip(cap, 0.0, None).astype(np.float32)


def cone_depth_mm(shape_hw: tuple[int, int], mm_per_px: float, center_x_px: float,
                  center_y_px: float, half_angle_deg: float, depth_mm: float) -> np.ndarray:
    """Depth map of a blunt-free cone of the given half angle pressed ``depth_mm`` deep."""
    r = _radius_mm(shape_hw, mm_per_px, center_x_px, center_y_px)
    cone = depth_mm - r / np.tan(np.deg2rad(half_angle_deg))
    return np.clip(cone, 0.0, None).astype(np.float32)


def flat_punch_depth_mm(shape_hw: tuple[int, int], mm_per_px: float, center_x_px: float,
                        center_y_px: float, radius_mm: float, depth_mm: float) -> np.ndarray:
    """Depth map of a flat cylindrical punch (sharp edge, softened by the gel drape)."""
    r = _radius_mm(shape_hw, mm_per_px, center_x_px, center_y_px)
    return np.where(r < radius_mm, depth_mm, 0.0).astype(np.float32)
