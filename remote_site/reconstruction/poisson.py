"""Least-squares integration of a gradient field with fast transform solvers.

Given per-pixel slopes ``gx = dh/dx`` (along columns) and ``gy = dh/dy`` (along rows), the
height ``h`` minimising ``sum (h[i+1]-h[i] - p[i+1/2])**2`` over all neighbour pairs, where
``p`` is the slope on the edge between two pixels (mean of the two pixel slopes times the
pitch), solves a discrete Poisson equation ``L h = div p``. The three solvers differ only in
what they assume beyond the frame:

* ``"dct"`` (Neumann): nothing is known outside; the edge terms across the border are
  dropped. DCT-II diagonalises this Laplacian exactly. The height is defined up to a
  constant; the solution returned has zero mean. This is the default and the most robust.
* ``"dst"`` (Dirichlet): the gel is flat (h = 0) half a pixel outside the frame. DST-II
  diagonalises this Laplacian (DST-I would need FFTs of length 2(N+1), which is prime-ish
  and 8x slower for 240 rows). Best when the contact is well inside the frame. Only the
  rows are transformed: after a DST-II along x each column frequency ``k`` leaves a
  tridiagonal system along y, ``(T_y + kx_k) H_k = D_k`` (``T_y`` the 1-D Dirichlet second
  difference, the matrix DST-II diagonalises), solved directly in float64 by the Thomas
  algorithm with cached pivots; then one inverse DST along x. That is the same
  least-squares solution (equal to float rounding) with two of the four 1-D transform passes
  replaced by a cheap vectorised recurrence.
* ``"fft"`` (periodic, Frankot-Chellappa): the frame wraps around. Fast but it leaks the
  slope of one border into the opposite one; kept as a reference variant.

**Free border pixels (``dst`` only).** Where a contact runs off the frame, h = 0 at the
border is false: the object goes on beyond the image, and the Dirichlet condition pulls its
heights down towards the edge (a GelSight Mini ball press crossing the left edge lost 0.06 mm
of its peak). ``integrate(..., free_border=mask)`` drops the edge terms across the border at
the border pixels ``mask`` marks (no condition there, as ``dct`` has everywhere) and keeps
h = 0 elsewhere. Dropping a border edge changes the Dirichlet system by a rank-one term per
edge (``L_N = L_D + U C U^T``: the end diagonal goes from -3 to -1, ``C`` = 2 per edge; the
edge's slope leaves the divergence), so the Woodbury identity solves it with the fast
Dirichlet solver: one solve of the changed divergence, the k x k capacitance matrix
``C^-1 + U^T L_D^-1 U`` (float64; its Green's function entries from the column frequencies'
tridiagonal inverses, one Thomas pass per distinct row of the free pixels, no transform: see
``_green``), and one solve for the correction. A frame
whose free edges are more than half of its 2 (H + W) border edges (little left to anchor the
height) keeps the Dirichlet condition everywhere.

Eigenvalue denominators and tridiagonal pivots are cached per (shape, solver); scipy's
pocketfft caches its plans.
The divergence is one compiled pass (``kernels.divergence_kernel``) into a buffer the caller
may supply, and the transforms run in place on it. All work is in float32 by default
(heights of a few mm with ~1e-7 relative rounding are far below the sensor noise).
"""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import numpy as np
import scipy.fft as sfft

from remote_site.reconstruction.kernels import (
    DIV_DCT,
    DIV_DST,
    DIV_FFT,
    divergence_kernel,
    tridiagonal_columns_kernel,
)
from shared.errors import InputDataError

__all__ = ["MAX_FREE_BORDER_FRACTION", "SOLVERS", "PoissonSolver", "integrate_gradients"]

Solver = Literal["dct", "dst", "fft"]
SOLVERS: tuple[str, ...] = ("dct", "dst", "fft")
#: free border edges beyond this share of the border's: the Dirichlet condition is kept
MAX_FREE_BORDER_FRACTION = 0.5


@functools.lru_cache(maxsize=32)
def _denominator(shape: tuple[int, int], solver: str, dtype_name: str) -> np.ndarray:
    """Eigenvalues of the discrete Laplacian for ``solver`` (dct, fft) on ``shape`` (cached;
    dst solves its columns directly, see :func:`_column_factors`).

    For Neumann the (0, 0) entry is 0 and is replaced by 1 (the mean is fixed separately).
    """
    rows, cols = shape
    if solver == "dct":
        ky = 2.0 * np.cos(np.pi * np.arange(rows) / rows) - 2.0
        kx = 2.0 * np.cos(np.pi * np.arange(cols) / cols) - 2.0
    elif solver == "fft":
        ky = 2.0 * np.cos(2.0 * np.pi * np.arange(rows) / rows) - 2.0
        kx = 2.0 * np.cos(2.0 * np.pi * np.arange(cols // 2 + 1) / cols) - 2.0
    else:  # pragma: no cover - guarded by PoissonSolver
        raise ValueError(solver)
    denom = ky[:, None] + kx[None, :]
    denom[0, 0] = 1.0
    out = denom.astype(dtype_name)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=32)
def _column_factors(shape: tuple[int, int]) -> np.ndarray:
    """Inverse Thomas pivots of ``T_y + kx_j`` for every column frequency ``j`` (cached).

    ``T_y`` (rows x rows) is the second difference with h = 0 half a pixel beyond both ends
    (diagonal -3 at the ends, -2 inside, off-diagonals 1: the matrix DST-II diagonalises,
    eigenvalues ``2 cos(pi k / rows) - 2``, k = 1..rows); ``kx_j = 2 cos(pi j / cols) - 2``,
    j = 1..cols. Every ``T_y + kx_j`` is diagonally dominant (|b| >= 2 + |kx_j| > 2), so the
    pivots never vanish. float64, (rows, cols), read-only.
    """
    rows, cols = shape
    kx = 2.0 * np.cos(np.pi * np.arange(1, cols + 1) / cols) - 2.0
    diag = np.full(rows, -2.0)
    diag[0] = diag[-1] = -3.0
    inv_pivot = np.empty((rows, cols), np.float64)
    previous = np.zeros(cols)
    for i in range(rows):
        previous = inv_pivot[i] = 1.0 / (diag[i] + kx - previous)
    inv_pivot.setflags(write=False)
    return inv_pivot


_DIVERGENCE_CODE = {"dct": DIV_DCT, "dst": DIV_DST, "fft": DIV_FFT}


class PoissonSolver:
    """Integrate slope maps into a height map.

    Args:
        solver: ``"dct"`` (Neumann, default), ``"dst"`` (Dirichlet h=0 outside) or ``"fft"``.
        dtype: float dtype of the computation (float32 default).

    Raises:
        InputDataError: unknown solver name.
    """

    def __init__(self, solver: str = "dct", dtype: type[np.floating] = np.float32) -> None:
        if solver not in SOLVERS:
            raise InputDataError(f"unknown Poisson solver {solver!r}; choose one of {SOLVERS}")
        self.solver = solver
        self.dtype = np.dtype(dtype)

    def integrate(self, gx: np.ndarray, gy: np.ndarray, pitch_mm: float,
                  work: np.ndarray | None = None,
                  free_border: np.ndarray | None = None) -> np.ndarray:
        """Return the least-squares height (mm) whose slopes are ``gx``, ``gy``.

        Args:
            gx: dh/dx along columns, dimensionless (mm per mm), shape (H, W).
            gy: dh/dy along rows, same shape.
            pitch_mm: pixel pitch in mm.
            work: scratch array of shape (H, W) and this solver's dtype for the divergence
                and the (in-place) transforms: the height returned may then *be* ``work``
                (reuse it only once the height is consumed). A new array if None.
            free_border: ``dst`` only: (H, W) bool; the border pixels it marks get no
                condition across the border (see the module doc); None: none.

        Returns:
            Height in mm, shape (H, W). For ``dct``/``fft`` it has zero mean.

        Raises:
            InputDataError: shapes differ, are smaller than 2 x 2, contain NaN/Inf, the
                pitch is not a positive finite number, or ``free_border`` is given to another
                solver than ``dst`` or has another shape.
        """
        gx = np.asarray(gx)
        gy = np.asarray(gy)
        if gx.shape != gy.shape or gx.ndim != 2:
            raise InputDataError(f"gradient maps must be 2-D and equal in shape, got "
                                 f"{gx.shape} and {gy.shape}")
        if gx.shape[0] < 2 or gx.shape[1] < 2:
            raise InputDataError(f"gradient maps must be at least 2 x 2, got {gx.shape}")
        if not (np.isfinite(pitch_mm) and pitch_mm > 0):
            raise InputDataError(f"pitch_mm must be positive and finite, got {pitch_mm}")
        edges = None
        if free_border is not None:
            if self.solver != "dst":
                raise InputDataError(f"free_border needs the dst solver, not {self.solver!r}")
            if np.shape(free_border) != gx.shape:
                raise InputDataError(f"free_border has shape {np.shape(free_border)}, the "
                                     f"slopes {gx.shape}")
            edges = _free_edges(np.asarray(free_border, bool))
        if work is None or work.shape != gx.shape or work.dtype != self.dtype:
            work = np.empty(gx.shape, self.dtype)
        div = work
        # one pass: slopes x pitch -> edge slopes -> divergence (a NaN/Inf slope spreads to it)
        divergence_kernel(gx, gy, self.dtype.type(pitch_mm), _DIVERGENCE_CODE[self.solver], div)
        if not np.isfinite(div).all():
            if np.isfinite(gx).all() and np.isfinite(gy).all():
                raise InputDataError(f"slopes x pitch overflow {self.dtype.name}")
            raise InputDataError("gradient maps contain NaN or Inf")
        # the transforms work in place on buffers this call owns (no copies)
        if self.solver == "dct":
            denom = _denominator(gx.shape, self.solver, self.dtype.name)
            spec = sfft.dctn(div, type=2, workers=1, overwrite_x=True)
            spec /= denom
            spec[0, 0] = 0.0
            height = sfft.idctn(spec, type=2, workers=1, overwrite_x=True)
        elif self.solver == "dst":
            if edges is not None:
                return _integrate_free(div, gx, gy, pitch_mm, edges)
            height = _solve_dirichlet(div)
        else:
            denom = _denominator(gx.shape, self.solver, self.dtype.name)
            spec = sfft.rfft2(div, workers=1)
            spec /= denom
            spec[0, 0] = 0.0
            height = sfft.irfft2(spec, s=gx.shape, workers=1)
        return np.asarray(height, dtype=self.dtype)


def _solve_dirichlet(rhs: np.ndarray) -> np.ndarray:
    """``L_D^-1 rhs`` in place: DST-II along x, a tridiagonal solve along y per column
    frequency, inverse DST (equal to dstn -> / denom -> idstn up to float rounding)."""
    spec = sfft.dst(rhs, type=2, axis=1, workers=1, overwrite_x=True)
    tridiagonal_columns_kernel(spec, _column_factors(rhs.shape))
    return np.asarray(sfft.idst(spec, type=2, axis=1, workers=1, overwrite_x=True))


class _FreeEdges(NamedTuple):
    """The border edges dropped: rows of the free left / right pixels, columns of the free
    top / bottom pixels; the free pixels (flat indices) and their count of dropped edges."""

    left: np.ndarray
    right: np.ndarray
    top: np.ndarray
    bottom: np.ndarray
    pixels: np.ndarray
    counts: np.ndarray


def _free_edges(free: np.ndarray) -> _FreeEdges | None:
    """The border edges to drop for ``free``; None when none (or too many) are free."""
    rows, cols = free.shape
    left, right = np.flatnonzero(free[:, 0]), np.flatnonzero(free[:, -1])
    top, bottom = np.flatnonzero(free[0, :]), np.flatnonzero(free[-1, :])
    n_free = len(left) + len(right) + len(top) + len(bottom)
    if n_free == 0 or n_free > MAX_FREE_BORDER_FRACTION * 2 * (rows + cols):
        return None
    flat = np.concatenate([left * cols, right * cols + cols - 1, top, (rows - 1) * cols + bottom])
    pixels, counts = np.unique(flat, return_counts=True)
    return _FreeEdges(left, right, top, bottom, pixels, counts)


def _integrate_free(div: np.ndarray, gx: np.ndarray, gy: np.ndarray, pitch_mm: float,
                    edges: _FreeEdges) -> np.ndarray:
    """The Dirichlet solution with the ``edges`` dropped (Woodbury, see the module doc), in
    ``div``'s dtype (which it overwrites); the capacitance system in float64."""
    # the dropped edges' slopes leave the divergence (their sign as in divergence_kernel)
    div[edges.left, 0] += gx[edges.left, 0] * pitch_mm
    div[edges.right, -1] -= gx[edges.right, -1] * pitch_mm
    div[0, edges.top] += gy[0, edges.top] * pitch_mm
    div[-1, edges.bottom] -= gy[-1, edges.bottom] * pitch_mm
    h0 = _solve_dirichlet(div)
    capacitance = np.diag(1.0 / (2.0 * edges.counts)) + _green(div.shape, edges.pixels)
    w = np.linalg.solve(capacitance, h0.flat[edges.pixels].astype(np.float64))
    correction = np.zeros(div.shape, div.dtype)
    correction.flat[edges.pixels] = w
    return np.asarray(h0 - _solve_dirichlet(correction), dtype=div.dtype)


def _green(shape: tuple[int, ...], pixels: np.ndarray) -> np.ndarray:
    """``U^T L_D^-1 U``: the Dirichlet solution at pixel p for a unit source at pixel q.

    Without a transform per source: in the DST-II basis along x (scipy's unnormalised pair:
    forward ``2 sum_n x_n s(k, n)``, inverse ``sum_k w_k y_k s(k, n) / 2W`` with
    ``s(k, n) = sin(pi (k + 1)(2 n + 1) / 2W)``, ``w_k`` = 2, and 1 for the last k), each
    column frequency k is the tridiagonal system along y that the Thomas kernel solves, so
    ``G[p, q] = sum_k w_k / 2W * s(k, c_p) * 2 s(k, c_q) * M_k[r_p, r_q]`` with ``M_k`` the
    inverse of that system: one kernel call per distinct source row gives ``M_k[:, r]`` for
    every k (a border pixel's row: few distinct rows but on the left and right sides).
    """
    rows, cols = shape
    r, c = np.divmod(pixels, cols)
    k = np.arange(cols)
    s = np.sin(np.pi * (k[None, :] + 1) * (2 * c[:, None] + 1) / (2 * cols))  # (P, W)
    out_side = s * (np.where(k < cols - 1, 2.0, 1.0) / (2.0 * cols))
    in_side = 2.0 * s
    factors = _column_factors((rows, cols))
    green = np.empty((len(pixels), len(pixels)))
    unit = np.empty((rows, cols), np.float64)
    for row in np.unique(r):
        unit.fill(0.0)
        unit[row] = 1.0
        tridiagonal_columns_kernel(unit, factors)  # unit[:, k] = M_k[:, row]
        sources = np.flatnonzero(r == row)
        green[:, sources] = (out_side * unit[r]) @ in_side[sources].T
    return green


def integrate_gradients(gx: np.ndarray, gy: np.ndarray, pitch_mm: float,
                        solver: str = "dct") -> np.ndarray:
    """Functional shortcut for :meth:`PoissonSolver.integrate`."""
    return PoissonSolver(solver).integrate(gx, gy, pitch_mm)
