"""Ball-press geometry: sphere-cap height and slopes, and a sphere fit to a height map.

Coordinates: x along image columns, y along rows, in mm; height positive where the ball
presses into the gel. For a ball of radius ``R`` whose contact circle has radius ``a``, the
cap height at distance ``r`` from the centre is ``sqrt(R^2 - r^2) - sqrt(R^2 - a^2)``
(zero on the contact circle) and its slopes are ``-(x - cx) / sqrt(R^2 - r^2)``.
"""

from __future__ import annotations

import numpy as np

from shared.errors import CalibrationError

__all__ = ["cap_depth_mm", "cap_height_mm", "cap_slopes", "fit_sphere_radius_mm"]


def cap_depth_mm(ball_radius_mm: float, contact_radius_mm: float) -> float:
    """The cap's height at its centre, i.e. the ball's indentation for a contact circle of
    radius ``a``: ``R - sqrt(R^2 - a^2)``.

    Raises:
        CalibrationError: the contact circle is not smaller than the ball.
    """
    if not 0.0 <= contact_radius_mm < ball_radius_mm:
        raise CalibrationError(f"contact radius {contact_radius_mm:.4g} mm is not in "
                               f"[0, ball radius {ball_radius_mm:.4g} mm)")
    return float(ball_radius_mm - np.sqrt(ball_radius_mm**2 - contact_radius_mm**2))


def cap_height_mm(r_mm: np.ndarray, ball_radius_mm: float, contact_radius_mm: float) -> np.ndarray:
    """Sphere-cap height (mm) at distances ``r_mm``; 0 outside the contact circle."""
    r = np.asarray(r_mm, np.float64)
    inside = r < contact_radius_mm
    top = np.sqrt(np.clip(ball_radius_mm**2 - r**2, 0.0, None))
    rim = np.sqrt(max(ball_radius_mm**2 - contact_radius_mm**2, 0.0))
    return np.where(inside, top - rim, 0.0)


def cap_slopes(dx_mm: np.ndarray, dy_mm: np.ndarray,
               ball_radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Slopes (dh/dx, dh/dy) of the ball surface at offsets (dx, dy) from its axis.

    Raises:
        CalibrationError: an offset lies at or beyond the ball's radius.
    """
    z2 = ball_radius_mm**2 - dx_mm**2 - dy_mm**2
    if np.any(z2 <= 0):
        raise CalibrationError("contact circle is as large as the ball: check the diameter, "
                               "mm/px and the labelled radius")
    z = np.sqrt(z2)
    return -dx_mm / z, -dy_mm / z


def fit_sphere_radius_mm(x_mm: np.ndarray, y_mm: np.ndarray, h_mm: np.ndarray) -> float:
    """Radius of the least-squares (algebraic) sphere through points (x, y, h).

    Returns NaN-free results only: raises instead.

    Raises:
        CalibrationError: fewer than 4 points or a degenerate (planar) point set.
    """
    x, y, z = (np.asarray(a, np.float64).ravel() for a in (x_mm, y_mm, h_mm))
    if len(x) < 4:
        raise CalibrationError("need at least 4 points to fit a sphere")
    design = np.stack([x, y, z, np.ones_like(x)], axis=1)
    rhs = -(x**2 + y**2 + z**2)
    sol, *_ = np.linalg.lstsq(design, rhs, rcond=None)
    centre = -sol[:3] / 2.0
    r2 = float(centre @ centre - sol[3])
    if not np.isfinite(r2) or r2 <= 0:
        raise CalibrationError("points are degenerate for a sphere fit")
    return float(np.sqrt(r2))
