"""Slope prediction on a fixed pixel grid: the position part of the polynomial baked per pixel.

The degree-``d`` polynomial of :class:`~remote_site.reconstruction.models.PolyGradientModel` in
(colour change r, g, b; position x, y) regroups exactly as a polynomial in the colour change
whose coefficients are polynomials in the position:

    slope(p) = sum_m  colour_m(change_p) * C_m(x_p, y_p),   C_m = sum_t coef_t * pos_t(x_p, y_p)

On a fixed grid (the sensor frame, or a pooled one) the positions never change, so ``C`` is
computed once per grid (56 colour monomials x 2 slopes per pixel for degree 5, instead of 252
terms) and a fused numba loop evaluates only the pixels above the dead zone, writing the slope
maps in place (no gather/scatter). When the colour terms are all monomials up to the degree
(the polynomial models), the generated straight-line kernel of that degree
(``poly_kernels``, a third of the loop's time: no variable-length loops, a nested Horner
scheme instead of monomials and one long addition chain; equal to it up to float32
rounding) runs instead of the loop. The result equals :meth:`PolyGradientModel.predict` up to
float32 rounding order (checked in the tests).
"""

from __future__ import annotations

import logging
from typing import Protocol

import numpy as np
from numba import njit

from remote_site.reconstruction.poly_kernels import KERNELS

__all__ = ["MAX_BAKED_BYTES", "BakedPolyPredictor", "GridPredictor", "PlainGridPredictor"]

log = logging.getLogger(__name__)

#: largest per-pixel coefficient table baked for one grid (the full 320 x 240 frame at degree
#: 5 needs 34 MB); a larger grid falls back to the plain model
MAX_BAKED_BYTES = 64 * 1024 * 1024


class GridPredictor(Protocol):
    """Slope prediction for the pixels of one fixed grid."""

    shape: tuple[int, ...]

    def predict_into(self, change: np.ndarray, active: np.ndarray, gx: np.ndarray,
                     gy: np.ndarray) -> None:
        """Write the slopes of the ``active`` pixels into ``gx``/``gy``."""


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _predict_active(change: np.ndarray, active: np.ndarray, inv_scale: np.ndarray,
                    exponents: np.ndarray, coeffs: np.ndarray, max_slope: float,
                    gx: np.ndarray, gy: np.ndarray) -> None:  # pragma: no cover - compiled
    rows, cols = active.shape
    n_terms = exponents.shape[0]
    max_deg = 0
    for m in range(n_terms):
        for v in range(3):
            max_deg = max(max_deg, exponents[m, v])
    powers = np.empty((3, max_deg + 1), np.float32)
    limit = np.float32(max_slope)
    for i in range(rows):
        for j in range(cols):
            if not active[i, j]:
                continue
            for v in range(3):
                powers[v, 0] = np.float32(1.0)
                value = change[i, j, v] * inv_scale[v]
                for d in range(1, max_deg + 1):
                    powers[v, d] = powers[v, d - 1] * value
            p = i * cols + j
            sx = np.float32(0.0)
            sy = np.float32(0.0)
            for m in range(n_terms):
                mono = (powers[0, exponents[m, 0]] * powers[1, exponents[m, 1]]
                        * powers[2, exponents[m, 2]])
                sx += mono * coeffs[p, m, 0]
                sy += mono * coeffs[p, m, 1]
            gx[i, j] = min(max(sx, -limit), limit)
            gy[i, j] = min(max(sy, -limit), limit)


def _complete_degree(exponents: np.ndarray) -> int | None:
    """The degree if ``exponents`` are all colour monomials up to it in lexicographic order."""
    degree = int(exponents.sum(axis=1).max()) if len(exponents) else 0
    complete = [(a, b, c) for a in range(degree + 1) for b in range(degree + 1 - a)
                for c in range(degree + 1 - a - b)]
    return degree if [tuple(int(v) for v in e) for e in exponents] == complete else None


class BakedPolyPredictor:
    """A position-aware polynomial with its position part evaluated once per grid pixel.

    Args:
        coef: (n_terms, 2) polynomial coefficients over (r, g, b, x, y) monomials.
        scale: (5,) divisors of the variables.
        exponents: (n_terms, 5) exponents of each monomial.
        x, y: (rows, cols) normalised pixel positions of the grid.
        max_slope: clip of the predicted slopes.
    """

    def __init__(self, coef: np.ndarray, scale: np.ndarray, exponents: np.ndarray,
                 x: np.ndarray, y: np.ndarray, max_slope: float) -> None:
        self.shape = x.shape
        colour_exps = sorted({tuple(int(v) for v in e[:3]) for e in exponents})
        index = {e: k for k, e in enumerate(colour_exps)}
        self.exponents = np.array(colour_exps, np.int64)
        px = (np.asarray(x, np.float64) / float(scale[3])).ravel()
        py = (np.asarray(y, np.float64) / float(scale[4])).ravel()
        coeffs = np.zeros((px.size, len(colour_exps), 2), np.float64)
        for t, e in enumerate(exponents):
            pos = px ** int(e[3]) * py ** int(e[4])
            coeffs[:, index[tuple(int(v) for v in e[:3])], :] += (
                pos[:, None] * np.asarray(coef[t], np.float64)[None, :])
        self.coeffs = np.ascontiguousarray(coeffs, dtype=np.float32)
        self.inv_scale = (1.0 / np.asarray(scale[:3], np.float64)).astype(np.float32)
        self.max_slope = float(max_slope)
        self._complete_degree = _complete_degree(self.exponents)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("baked polynomial for a %s grid: %d colour terms, %.1f MB", self.shape,
                      len(colour_exps), self.coeffs.nbytes / 1e6)

    @staticmethod
    def table_bytes(n_pixels: int, exponents: np.ndarray) -> int:
        """Size of the per-pixel table this predictor would build for ``n_pixels``."""
        n_colour = len({tuple(int(v) for v in e[:3]) for e in exponents})
        return n_pixels * n_colour * 2 * 4

    def predict_into(self, change: np.ndarray, active: np.ndarray, gx: np.ndarray,
                     gy: np.ndarray) -> None:
        """Write the slopes of the ``active`` pixels into ``gx``/``gy`` (others untouched).

        Args:
            change: (rows, cols, 3) float32 relative colour change of this grid.
            active: (rows, cols) bool.
            gx, gy: (rows, cols) float32 outputs.
        """
        change = np.ascontiguousarray(change, dtype=np.float32)
        active = np.ascontiguousarray(active)
        kernel = KERNELS.get(self._complete_degree or -1)
        if kernel is not None:
            kernel(change, active, self.inv_scale, self.coeffs.reshape(len(self.coeffs), -1),
                   self.max_slope, gx, gy)
        else:
            _predict_active(change, active, self.inv_scale, self.exponents, self.coeffs,
                            self.max_slope, gx, gy)


class PlainGridPredictor:
    """Any gradient model on a fixed grid: gathers the active pixels and calls ``predict``.

    Args:
        model: a model with ``predict(change (N, 3), x (N,), y (N,)) -> (N, 2)``.
        x, y: (rows, cols) normalised pixel positions of the grid.
    """

    def __init__(self, model: object, x: np.ndarray, y: np.ndarray) -> None:
        self.model = model
        self.shape = x.shape
        self.x = x
        self.y = y

    def predict_into(self, change: np.ndarray, active: np.ndarray, gx: np.ndarray,
                     gy: np.ndarray) -> None:
        """Write the slopes of the ``active`` pixels into ``gx``/``gy`` (others untouched)."""
        predict = self.model.predict  # type: ignore[attr-defined]
        pred = predict(change[active], self.x[active], self.y[active])
        gx[active] = pred[:, 0]
        gy[active] = pred[:, 1]
