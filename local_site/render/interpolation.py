"""Interpolation of tactile layers stored on a regular metric grid.

A :class:`GridLayers` holds several layers (height, stiffness, friction, ...) sampled on
one regular grid: element ``[row, col]`` sits at ``x = x0_mm + col * dx_mm`` and
``y = y0_mm + row * dy_mm`` (row index along +y, column index along +x, sample centres).
:meth:`GridLayers.sample` evaluates every layer at arbitrary points at once, so the
renderer's 16 pins cost one gather, not 16 x layers.

Orders:

* ``0`` nearest sample (the naive "one pixel per pin" renderer);
* ``1`` bilinear: exact for fields that are linear (indeed bilinear) in x and y;
* ``3`` Keys cubic convolution (a = -1/2): exact for quadratic fields, third-order
  accurate. The border uses Keys' quadratic extrapolation of one ghost sample
  (``f[-1] = 3 f[0] - 3 f[1] + f[2]``) so accuracy holds up to the edge. Cubic weights
  can overshoot between samples; bounded layers are clipped by the caller.

Points outside the grid are evaluated at the nearest point of the grid (edge
replication) and reported in the ``inside`` mask so a scene can apply its own policy.
:meth:`GridLayers.clip_to_data` bounds interpolated values by the data's own range.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit
from numpy.typing import NDArray

from shared.errors import ConfigError, InputDataError

__all__ = ["DEFAULT_ORDER", "INTERPOLATION_ORDERS", "MAX_GRID_DIM", "MAX_LAYER_ABS",
           "GridLayers", "keys_cubic_weights"]

#: supported interpolation orders (0 nearest, 1 bilinear, 3 Keys cubic)
INTERPOLATION_ORDERS = (0, 1, 3)
#: the scenes' default: Keys cubic (smaller rendered-height error than bilinear on every
#: analytic surface of benchmarks/bench_renderer.py, for the same render time)
DEFAULT_ORDER = 3
#: largest grid side accepted (same bound as the wire protocol's arrays)
MAX_GRID_DIM = 4096
#: largest magnitude of a layer value accepted: far beyond any physical layer (mm, k,
#: friction, N/mm), far below where arithmetic overflows (the cubic border's ghost samples
#: reach 7 x 7 = 49 times the data at a corner and |Keys weights| add up to <= 1.25 per
#: axis, so every intermediate stays below ~1e14; a value near the float limit overflowed
#: to inf and then NaN, even at the grid nodes)
MAX_LAYER_ABS = 1.0e12
#: tolerance (in grid cells) for deciding that a point lies inside the grid
_INSIDE_TOL_CELLS = 1e-9


def keys_cubic_weights(t: NDArray[np.float64]) -> NDArray[np.float64]:
    """Keys (a = -1/2) cubic convolution weights for the 4 samples around ``t``.

    Args:
        t: fractional positions in [0, 1] between sample 0 and sample 1, any shape.

    Returns:
        Array of shape ``t.shape + (4,)``: weights of samples -1, 0, 1, 2 (they sum to 1).
    """
    t2 = t * t
    t3 = t2 * t
    return np.stack([
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ], axis=-1)


def _fill_ghosts(a: NDArray[np.float64], axis: int) -> None:
    """Write the ghost samples of ``a`` in place: its first and last samples along ``axis``
    (1 or 2) from the data between them, by Keys' quadratic extrapolation (linear where
    there are only two data samples: the best the data allow)."""
    def at(i: int) -> tuple[slice | int, ...]:
        return (slice(None), i) if axis == 1 else (slice(None), slice(None), i)

    if a.shape[axis] - 2 >= 3:
        a[at(0)] = 3.0 * a[at(1)] - 3.0 * a[at(2)] + a[at(3)]
        a[at(-1)] = 3.0 * a[at(-2)] - 3.0 * a[at(-3)] + a[at(-4)]
    else:
        a[at(0)] = 2.0 * a[at(1)] - a[at(2)]
        a[at(-1)] = 2.0 * a[at(-2)] - a[at(-3)]


def _with_ghosts(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """``values`` ``(n_layers, ny, nx)`` with one ghost sample at both ends of each grid axis:
    ``(n_layers, ny + 2, nx + 2)``. The ghost rows first, then the ghost columns over every
    row (the corners extrapolate the ghost rows), written into one array: a few numpy calls
    per frame instead of two rounds of axis moves and concatenations (this runs in the
    display loop's tick for every frame, in the display process)."""
    n, ny, nx = values.shape
    out = np.empty((n, ny + 2, nx + 2))
    out[:, 1:-1, 1:-1] = values
    _fill_ghosts(out[:, :, 1:-1], 1)
    _fill_ghosts(out, 2)
    return out


@dataclass(frozen=True, eq=False)
class GridLayers:
    """Layers on one regular grid, ready for interpolation.

    Args:
        values: array ``(n_layers, ny, nx)`` of finite floats, ``|v| <= MAX_LAYER_ABS``,
            ``ny, nx >= 2``.
        x0_mm: x of column 0; y0_mm: y of row 0 (sample centres).
        dx_mm: column spacing; dy_mm: row spacing (both > 0).

    Raises:
        InputDataError: wrong shape, non-finite or too large values, or non-finite
            spacing.
    """

    values: NDArray[np.float64]
    x0_mm: float
    y0_mm: float
    dx_mm: float
    dy_mm: float
    _padded: NDArray[np.float64] = field(init=False, repr=False)
    #: per-layer ``(min, max)`` of the data, shape ``(n_layers, 2)``
    value_range: NDArray[np.float64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        v = np.array(self.values, dtype=np.float64)  # private copy
        if v.ndim != 3 or v.shape[0] < 1:
            raise InputDataError(f"grid layers must be (n_layers, ny, nx), got shape {v.shape}")
        ny, nx = v.shape[1:]
        if not (2 <= ny <= MAX_GRID_DIM and 2 <= nx <= MAX_GRID_DIM):
            raise InputDataError(f"a layer grid needs 2..{MAX_GRID_DIM} samples per side, "
                                 f"got {ny} x {nx}")
        # the data range serves the bound check too (a NaN makes min or max NaN and an Inf
        # leaves the bound, so both fail it): no extra pass over every frame's layers
        value_range = np.stack([v.min(axis=(1, 2)), v.max(axis=(1, 2))], axis=1)
        least, most = float(value_range[:, 0].min()), float(value_range[:, 1].max())
        if not (least >= -MAX_LAYER_ABS and most <= MAX_LAYER_ABS):
            if not np.isfinite(v).all():
                raise InputDataError("grid layers contain NaN or Inf")
            raise InputDataError(f"grid layer values must lie within +-{MAX_LAYER_ABS:g}, got "
                                 f"[{least:.6g}, {most:.6g}]")
        geom = np.array([self.x0_mm, self.y0_mm, self.dx_mm, self.dy_mm], dtype=float)
        if not np.isfinite(geom).all() or self.dx_mm <= 0 or self.dy_mm <= 0:
            raise InputDataError("grid origin must be finite and spacing positive, got "
                                 f"x0={self.x0_mm}, y0={self.y0_mm}, dx={self.dx_mm}, "
                                 f"dy={self.dy_mm}")
        v.setflags(write=False)
        padded = _with_ghosts(v)
        padded.setflags(write=False)
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "_padded", padded)
        value_range.setflags(write=False)
        object.__setattr__(self, "value_range", value_range)

    def clip_to_data(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """Clip interpolated ``values`` ``(n_layers, n)`` to each layer's data range.

        Removes cubic overshoot (and 1-ulp rounding of convex weights), so a layer whose
        data respect a bound never yields a value beyond it.
        """
        return np.clip(values, self.value_range[:, :1], self.value_range[:, 1:])

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape ``(ny, nx)``."""
        return int(self.values.shape[1]), int(self.values.shape[2])

    @property
    def extent_mm(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` of the sample centres."""
        ny, nx = self.shape
        return (self.x0_mm, self.x0_mm + (nx - 1) * self.dx_mm,
                self.y0_mm, self.y0_mm + (ny - 1) * self.dy_mm)

    def sample(self, points_xy_mm: NDArray[np.float64], order: int = 1, *,
               clip: bool = False) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Interpolate every layer at ``points_xy_mm``.

        Args:
            points_xy_mm: array ``(n_points, 2)`` of finite (x, y) in mm.
            order: 0 (nearest), 1 (bilinear) or 3 (Keys cubic).
            clip: bound the values by each layer's data range (:meth:`clip_to_data`).

        Returns:
            ``(values, inside)``: ``values`` is ``(n_layers, n_points)``; ``inside`` is
            ``(n_points,)``, False where the point lies outside the grid (its value is then
            the one at the nearest grid point).

        Raises:
            ConfigError: an unsupported order.
        """
        if order in (1, 3) and points_xy_mm.dtype == np.float64 and points_xy_mm.ndim == 2 \
                and points_xy_mm.shape[1] == 2:
            # the renderer's path at 1 kHz: one compiled call instead of ~30 numpy calls on
            # 16 points (same arithmetic, same results: tests/local_site/test_bilinear_kernel),
            # the clip included
            out = np.empty((self.values.shape[0], points_xy_mm.shape[0]))
            inside_out = np.empty(points_xy_mm.shape[0], dtype=np.bool_)
            if order == 1:
                _bilinear_kernel(self.values, points_xy_mm, self.x0_mm, self.y0_mm, self.dx_mm,
                                 self.dy_mm, _INSIDE_TOL_CELLS, clip, self.value_range, out,
                                 inside_out)
            else:  # the numpy path's sum-to-float rounding (tests as above)
                _keys_kernel(self._padded, points_xy_mm, self.x0_mm, self.y0_mm, self.dx_mm,
                             self.dy_mm, _INSIDE_TOL_CELLS, clip, self.value_range, out,
                             inside_out)
            return out, inside_out
        values, inside = self._sample_numpy(points_xy_mm, order)
        return (self.clip_to_data(values) if clip else values), inside

    def _sample_numpy(self, points_xy_mm: NDArray[np.float64],
                      order: int) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        ny, nx = self.shape
        fx = (points_xy_mm[:, 0] - self.x0_mm) / self.dx_mm
        fy = (points_xy_mm[:, 1] - self.y0_mm) / self.dy_mm
        tol = _INSIDE_TOL_CELLS
        inside = (fx >= -tol) & (fx <= nx - 1 + tol) & (fy >= -tol) & (fy <= ny - 1 + tol)
        fx = np.clip(fx, 0.0, nx - 1.0)
        fy = np.clip(fy, 0.0, ny - 1.0)
        if order == 0:
            ix = np.rint(fx).astype(np.intp)
            iy = np.rint(fy).astype(np.intp)
            return self.values[:, iy, ix], inside
        ix = np.minimum(fx.astype(np.intp), nx - 2)
        iy = np.minimum(fy.astype(np.intp), ny - 2)
        tx = fx - ix
        ty = fy - iy
        if order == 1:
            v = self.values
            top = v[:, iy, ix] * (1.0 - tx) + v[:, iy, ix + 1] * tx
            bottom = v[:, iy + 1, ix] * (1.0 - tx) + v[:, iy + 1, ix + 1] * tx
            return top * (1.0 - ty) + bottom * ty, inside
        if order == 3:
            wx = keys_cubic_weights(tx)  # (P, 4)
            wy = keys_cubic_weights(ty)
            offs = np.arange(4)
            # padded index of sample (i - 1) is i, so the 4 taps start at ix in padded space
            rows = (iy[:, None] + offs[None, :])[:, :, None]  # (P, 4, 1)
            cols = (ix[:, None] + offs[None, :])[:, None, :]  # (P, 1, 4)
            taps = self._padded[:, rows, cols]  # (L, P, 4, 4)
            return np.einsum("lpij,pi,pj->lp", taps, wy, wx), inside
        raise ConfigError(f"interpolation order must be one of {INTERPOLATION_ORDERS}, "
                          f"got {order!r}")


@njit(cache=True, nogil=True)
def _cell(x: float, y: float, x0: float, y0: float, dx: float, dy: float, tol: float, nx: int,
          ny: int) -> tuple[int, int, float, float, bool]:  # pragma: no cover - compiled
    """The sample cell of one point: (column, row, fraction along x, along y, inside), the
    point clipped to the grid first (edge replication), as the numpy path does."""
    fx = (x - x0) / dx
    fy = (y - y0) / dy
    inside = (fx >= -tol) and (fx <= nx - 1 + tol) and (fy >= -tol) and (fy <= ny - 1 + tol)
    fx = min(max(fx, 0.0), nx - 1.0)
    fy = min(max(fy, 0.0), ny - 1.0)
    ix = min(int(fx), nx - 2)
    iy = min(int(fy), ny - 2)
    return ix, iy, fx - ix, fy - iy, inside


@njit(cache=True, nogil=True)
def _bilinear_kernel(v: NDArray[np.float64], pts: NDArray[np.float64], x0: float, y0: float,
                     dx: float, dy: float, tol: float, clip: bool,
                     value_range: NDArray[np.float64], out: NDArray[np.float64],
                     inside: NDArray[np.bool_]) -> None:  # pragma: no cover - compiled
    """:meth:`GridLayers.sample` at order 1, fused: the numpy path's operations in order
    (then :meth:`GridLayers.clip_to_data`'s when ``clip``)."""
    n_layers, ny, nx = v.shape
    for p in range(pts.shape[0]):
        ix, iy, tx, ty, inside[p] = _cell(pts[p, 0], pts[p, 1], x0, y0, dx, dy, tol, nx, ny)
        for layer in range(n_layers):
            top = v[layer, iy, ix] * (1.0 - tx) + v[layer, iy, ix + 1] * tx
            bottom = v[layer, iy + 1, ix] * (1.0 - tx) + v[layer, iy + 1, ix + 1] * tx
            value = top * (1.0 - ty) + bottom * ty
            if clip:
                value = min(max(value, value_range[layer, 0]), value_range[layer, 1])
            out[layer, p] = value


@njit(cache=True, nogil=True)
def _keys_kernel(padded: NDArray[np.float64], pts: NDArray[np.float64], x0: float, y0: float,
                 dx: float, dy: float, tol: float, clip: bool,
                 value_range: NDArray[np.float64], out: NDArray[np.float64],
                 inside: NDArray[np.bool_]) -> None:  # pragma: no cover - compiled
    """:meth:`GridLayers.sample` at order 3, fused: Keys (a = -1/2) weights on the
    ghost-padded samples, positions as in :func:`_bilinear_kernel` (and its clip)."""
    n_layers, ny2, nx2 = padded.shape
    nx, ny = nx2 - 2, ny2 - 2
    wx = np.empty(4)
    wy = np.empty(4)
    for p in range(pts.shape[0]):
        ix, iy, tx, ty, inside[p] = _cell(pts[p, 0], pts[p, 1], x0, y0, dx, dy, tol, nx, ny)
        for w, t in ((wx, tx), (wy, ty)):
            t2 = t * t
            t3 = t2 * t
            w[0] = 0.5 * (-t3 + 2.0 * t2 - t)
            w[1] = 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0)
            w[2] = 0.5 * (-3.0 * t3 + 4.0 * t2 + t)
            w[3] = 0.5 * (t3 - t2)
        for layer in range(n_layers):
            acc = 0.0
            for i in range(4):
                row = 0.0
                for j in range(4):
                    row += padded[layer, iy + i, ix + j] * wx[j]
                acc += row * wy[i]
            if clip:
                acc = min(max(acc, value_range[layer, 0]), value_range[layer, 1])
            out[layer, p] = acc


def warm_up() -> None:
    """Compile (or load from numba's cache) the interpolation kernels now, not in the first
    display-loop iteration that renders."""
    grid = GridLayers(np.zeros((1, 2, 2)), x0_mm=0.0, y0_mm=0.0, dx_mm=1.0, dy_mm=1.0)
    for order in (1, 3):
        grid.sample(np.zeros((1, 2)), order=order, clip=True)
