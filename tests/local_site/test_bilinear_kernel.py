"""The compiled bilinear path of GridLayers.sample (the renderer's 1 kHz path) gives the same
values and inside mask as the numpy implementation it replaces, and agrees with an
independent reference (scipy.ndimage.map_coordinates, order 1, edge replication)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from local_site.render.interpolation import GridLayers


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
