"""The compiled bilinear and Keys cubic paths of GridLayers.sample (the renderer's 1 kHz
path) give the same values and inside mask as the numpy implementation they bypass, and agree
with independent references (scipy.ndimage.map_coordinates at order 1, edge replication;
quadratic fields, which Keys reproduces exactly)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from local_site.render.interpolation import GridLayers, keys_cubic_weights


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), layers=st.integers(1, 4), ny=st.integers(2, 40),
       nx=st.integers(2, 40), n=st.integers(1, 64), dx=st.floats(0.05, 3.0),
       dy=st.floats(0.05, 3.0), spread=st.floats(0.5, 2.0))
def test_compiled_bilinear_matches_numpy_and_scipy(seed: int, layers: int, ny: int, nx: int,
                                                   n: int, dx: float, dy: float,
                                                   spread: float) -> None:
    rng = np.random.default_rng(seed)
    values = rng.normal(0, 1, (layers, ny, nx))
    x0, y0 = rng.uniform(-50, 50, 2)
    grid = GridLayers(values, x0_mm=float(x0), y0_mm=float(y0), dx_mm=dx, dy_mm=dy)
    # points inside, on the border and outside the grid
    pts = np.stack([x0 + rng.uniform(-0.5, 1.5, n) * (nx - 1) * dx * spread,
                    y0 + rng.uniform(-0.5, 1.5, n) * (ny - 1) * dy], axis=1)
    pts[0] = (x0, y0)
    got, inside = grid.sample(pts, order=1)
    ref, ref_inside = _reference_numpy(grid, pts)  # the numpy path it replaced
    np.testing.assert_array_equal(inside, ref_inside)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    fx = np.clip((pts[:, 0] - x0) / dx, 0, nx - 1)
    fy = np.clip((pts[:, 1] - y0) / dy, 0, ny - 1)
    for layer in range(layers):
        sp = ndimage.map_coordinates(values[layer], [fy, fx], order=1, mode="nearest")
        np.testing.assert_allclose(got[layer], sp, rtol=0, atol=1e-9)


def _reference_numpy(grid: GridLayers, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The numpy order-1 path of GridLayers.sample as it was before the compiled kernel."""
    v = grid.values
    ny, nx = grid.shape
    fx = (pts[:, 0] - grid.x0_mm) / grid.dx_mm
    fy = (pts[:, 1] - grid.y0_mm) / grid.dy_mm
    tol = 1e-9
    inside = (fx >= -tol) & (fx <= nx - 1 + tol) & (fy >= -tol) & (fy <= ny - 1 + tol)
    fx = np.clip(fx, 0.0, nx - 1.0)
    fy = np.clip(fy, 0.0, ny - 1.0)
    ix = np.minimum(fx.astype(np.intp), nx - 2)
    iy = np.minimum(fy.astype(np.intp), ny - 2)
    tx, ty = fx - ix, fy - iy
    top = v[:, iy, ix] * (1.0 - tx) + v[:, iy, ix + 1] * tx
    bottom = v[:, iy + 1, ix] * (1.0 - tx) + v[:, iy + 1, ix + 1] * tx
    return top * (1.0 - ty) + bottom * ty, inside


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), layers=st.integers(1, 4), ny=st.integers(2, 40),
       nx=st.integers(2, 40), n=st.integers(1, 64), dx=st.floats(0.05, 3.0),
       dy=st.floats(0.05, 3.0))
def test_compiled_keys_cubic_matches_numpy(seed: int, layers: int, ny: int, nx: int, n: int,
                                           dx: float, dy: float) -> None:
    """Order 3: the compiled path against the numpy path it bypasses."""
    rng = np.random.default_rng(seed)
    grid = GridLayers(rng.normal(0, 1, (layers, ny, nx)), x0_mm=1.5, y0_mm=-2.0, dx_mm=dx,
                      dy_mm=dy)
    pts = np.stack([1.5 + rng.uniform(-0.5, 1.5, n) * (nx - 1) * dx,
                    -2.0 + rng.uniform(-0.5, 1.5, n) * (ny - 1) * dy], axis=1)
    got, inside = grid.sample(pts, order=3)
    ref, ref_inside = _reference_keys_numpy(grid, pts)
    np.testing.assert_array_equal(inside, ref_inside)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * max(1.0, np.abs(ref).max()))


def _reference_keys_numpy(grid: GridLayers, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The numpy order-3 path of GridLayers.sample (Keys weights on the padded samples)."""
    _, inside = _reference_numpy(grid, pts)
    ny, nx = grid.shape
    fx = np.clip((pts[:, 0] - grid.x0_mm) / grid.dx_mm, 0.0, nx - 1.0)
    fy = np.clip((pts[:, 1] - grid.y0_mm) / grid.dy_mm, 0.0, ny - 1.0)
    ix = np.minimum(fx.astype(np.intp), nx - 2)
    iy = np.minimum(fy.astype(np.intp), ny - 2)
    wx, wy = keys_cubic_weights(fx - ix), keys_cubic_weights(fy - iy)
    offs = np.arange(4)
    taps = grid._padded[:, (iy[:, None] + offs)[:, :, None], (ix[:, None] + offs)[:, None, :]]
    return np.einsum("lpij,pi,pj->lp", taps, wy, wx), inside


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), ny=st.integers(3, 30), nx=st.integers(3, 30))
def test_compiled_keys_cubic_is_exact_for_quadratic_fields(seed: int, ny: int, nx: int) -> None:
    """Keys (a = -1/2) with its quadratic ghost extrapolation reproduces any quadratic
    field exactly, up to the grid's edge (an analytic reference)."""
    rng = np.random.default_rng(seed)
    c = rng.normal(0, 1, 6)

    def quad(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.asarray(c[0] + c[1] * x + c[2] * y + c[3] * x * x + c[4] * x * y
                          + c[5] * y * y)

    dx, dy = 0.5, 0.7
    yy, xx = np.mgrid[0:ny, 0:nx]
    grid = GridLayers(quad(xx * dx, yy * dy)[None], x0_mm=0.0, y0_mm=0.0, dx_mm=dx, dy_mm=dy)
    pts = np.stack([rng.uniform(0, (nx - 1) * dx, 50), rng.uniform(0, (ny - 1) * dy, 50)],
                   axis=1)
    got, inside = grid.sample(pts, order=3)
    assert inside.all()
    np.testing.assert_allclose(got[0], quad(pts[:, 0], pts[:, 1]), rtol=0, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), order=st.sampled_from([0, 1, 3]),
       layers=st.integers(1, 3), ny=st.integers(2, 20), nx=st.integers(2, 20),
       n=st.integers(1, 32))
def test_sampling_with_clip_is_sampling_then_clip_to_data(seed: int, order: int, layers: int,
                                                          ny: int, nx: int, n: int) -> None:
    """``clip=True`` (done inside the compiled kernels at orders 1 and 3) gives exactly the
    unclipped values passed through :meth:`GridLayers.clip_to_data`, and never leaves a
    layer's data range (Keys overshoots it on a step)."""
    rng = np.random.default_rng(seed)
    values = rng.normal(0, 1, (layers, ny, nx))
    values[:, :, nx // 2:] += 3.0  # a step: cubic weights overshoot next to it
    grid = GridLayers(values, x0_mm=0.0, y0_mm=0.0, dx_mm=0.5, dy_mm=0.5)
    pts = np.stack([rng.uniform(-1.0, nx * 0.5 + 1.0, n), rng.uniform(-1.0, ny * 0.5 + 1.0, n)],
                   axis=1)
    raw, inside = grid.sample(pts, order=order)
    clipped, clipped_inside = grid.sample(pts, order=order, clip=True)
    np.testing.assert_array_equal(clipped_inside, inside)
    np.testing.assert_array_equal(clipped, grid.clip_to_data(raw))
    assert (clipped >= values.min(axis=(1, 2))[:, None]).all()
    assert (clipped <= values.max(axis=(1, 2))[:, None]).all()
