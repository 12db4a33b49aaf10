"""Line fits of force on indentation: OLS, Theil-Sen (scipy) and Huber (IRLS).

Each returns ``(slope, intercept)`` of ``y = intercept + slope * x``. Inputs are finite 1-D
arrays of equal length with at least two distinct ``x`` (checked by the caller).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.stats import theilslopes

from shared.errors import ConfigError

__all__ = ["FITS", "fit_huber", "fit_ols", "fit_theil_sen"]

Array = NDArray[np.float64]


def fit_ols(x: Array, y: Array) -> tuple[float, float]:
    """Ordinary least squares."""
    xm, ym = float(x.mean()), float(y.mean())
    dx = x - xm
    slope = float(np.dot(dx, y - ym) / np.dot(dx, dx))
    return slope, ym - slope * xm


def fit_theil_sen(x: Array, y: Array) -> tuple[float, float]:
    """Theil-Sen: median of pairwise slopes (29% breakdown point), O(n^2) pairs."""
    res = theilslopes(y, x)
    return float(res.slope), float(res.intercept)


def _weighted_ls(x: Array, y: Array, w: Array) -> tuple[float, float]:
    sw = float(w.sum())
    xm, ym = float(np.dot(w, x) / sw), float(np.dot(w, y) / sw)
    dx = x - xm
    slope = float(np.dot(w * dx, y - ym) / np.dot(w * dx, dx))
    return slope, ym - slope * xm


def fit_huber(x: Array, y: Array, *, c: float = 1.345, iterations: int = 30,
              tol: float = 1e-10) -> tuple[float, float]:
    """Huber M-estimate by iteratively reweighted least squares (MAD scale, c = 1.345)."""
    slope, intercept = fit_ols(x, y)
    for _ in range(iterations):
        r = y - (intercept + slope * x)
        scale = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        if scale <= 1e-15:
            break  # an exact fit: nothing to down-weight
        a = np.abs(r) / (c * scale)
        w = np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1.0))
        new_slope, new_intercept = _weighted_ls(x, y, w)
        done = abs(new_slope - slope) <= tol * max(1.0, abs(slope))
        slope, intercept = new_slope, new_intercept
        if done:
            break
    return slope, intercept


FITS: dict[str, Callable[[Array, Array], tuple[float, float]]] = {
    "ols": fit_ols,
    "theil_sen": fit_theil_sen,
    "huber": fit_huber,
}


def get_fit(method: str) -> Callable[[Array, Array], tuple[float, float]]:
    """The fit function for a method name.

    Raises:
        ConfigError: an unknown method.
    """
    try:
        return FITS[method]
    except KeyError as err:
        raise ConfigError(f"unknown regression {method!r}; known: {sorted(FITS)}") from err
