"""GridLayers interpolation: exactness on polynomial fields, bounds, inside mask."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from local_site.render.interpolation import MAX_LAYER_ABS, GridLayers, keys_cubic_weights
from shared.errors import ConfigError, InputDataError


def _grid(fn, nx: int = 9, ny: int = 7, x0: float = -2.0, y0: float = 1.0,
          dx: float = 0.5, dy: float = 0.3) -> GridLayers:
    xs = x0 + dx * np.arange(nx)
    ys = y0 + dy * np.arange(ny)
    gx, gy = np.meshgrid(xs, ys)
    return GridLayers(fn(gx, gy)[None], x0_mm=x0, y0_mm=y0, dx_mm=dx, dy_mm=dy)


def _inner_points(n: int = 200, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-2.0, 2.0, n), rng.uniform(1.0, 2.8, n)])


def linear(x, y):
    return 0.7 * x - 1.3 * y + 0.25


def bilinear(x, y):
    return 0.2 * x * y + linear(x, y)


def quadratic(x, y):
    return 0.3 * x * x - 0.2 * x * y + 0.5 * y * y + linear(x, y)


@pytest.mark.parametrize("order", [1, 3])
@pytest.mark.parametrize("field", [linear, bilinear])
def test_linear_and_bilinear_fields_are_reproduced_exactly(order: int, field) -> None:
    grid = _grid(field)
    pts = _inner_points()
    values, inside = grid.sample(pts, order)
    assert inside.all()
    np.testing.assert_allclose(values[0], field(pts[:, 0], pts[:, 1]), atol=1e-12)


def test_cubic_is_exact_on_quadratics_up_to_the_border() -> None:
    grid = _grid(quadratic)
    pts = _inner_points(400, seed=1)
    values, _ = grid.sample(pts, 3)
    np.testing.assert_allclose(values[0], quadratic(pts[:, 0], pts[:, 1]), atol=1e-11)


def test_bilinear_is_not_exact_on_quadratics() -> None:
    """Control for the test above: the check can fail."""
    grid = _grid(quadratic)
    pts = _inner_points(400, seed=1)
    values, _ = grid.sample(pts, 1)
    assert np.max(np.abs(values[0] - quadratic(pts[:, 0], pts[:, 1]))) > 1e-3


def test_nearest_returns_the_closest_sample() -> None:
    grid = _grid(linear)
    values, _ = grid.sample(np.array([[-2.0 + 0.5 * 3 + 0.2, 1.0 + 0.3 * 2 - 0.1]]), 0)
    assert values[0, 0] == pytest.approx(linear(-2.0 + 1.5, 1.0 + 0.6))


@pytest.mark.parametrize("order", [0, 1, 3])
def test_grid_nodes_are_reproduced(order: int) -> None:
    grid = _grid(quadratic)
    ny, nx = grid.shape
    gx, gy = np.meshgrid(-2.0 + 0.5 * np.arange(nx), 1.0 + 0.3 * np.arange(ny))
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    values, inside = grid.sample(pts, order)
    assert inside.all()
    np.testing.assert_allclose(values[0], quadratic(gx, gy).ravel(), atol=1e-12)


def test_outside_points_are_flagged_and_take_the_nearest_edge() -> None:
    grid = _grid(linear)
    x0, x1, y0, y1 = grid.extent_mm
    pts = np.array([[x0 - 1.0, 0.5 * (y0 + y1)], [x1, y1], [x1 + 0.01, y1]])
    values, inside = grid.sample(pts, 1)
    assert inside.tolist() == [False, True, False]
    assert values[0, 0] == pytest.approx(linear(x0, 0.5 * (y0 + y1)))
    assert values[0, 2] == pytest.approx(linear(x1, y1))


def test_keys_weights_sum_to_one_and_interpolate() -> None:
    t = np.linspace(0.0, 1.0, 11)
    w = keys_cubic_weights(t)
    np.testing.assert_allclose(w.sum(axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(w[0], [0.0, 1.0, 0.0, 0.0])
    np.testing.assert_allclose(w[-1], [0.0, 0.0, 1.0, 0.0])


def test_bad_grids_and_orders_are_rejected() -> None:
    with pytest.raises(InputDataError):
        GridLayers(np.zeros((1, 1, 5)), x0_mm=0, y0_mm=0, dx_mm=1, dy_mm=1)
    with pytest.raises(InputDataError):
        GridLayers(np.full((1, 3, 3), np.nan), x0_mm=0, y0_mm=0, dx_mm=1, dy_mm=1)
    with pytest.raises(InputDataError):
        GridLayers(np.zeros((1, 3, 3)), x0_mm=0, y0_mm=0, dx_mm=0.0, dy_mm=1)
    grid = _grid(linear)
    with pytest.raises(ConfigError):
        grid.sample(np.zeros((1, 2)), 2)


def test_grid_is_a_private_read_only_copy() -> None:
    data = np.zeros((1, 3, 3))
    grid = GridLayers(data, x0_mm=0, y0_mm=0, dx_mm=1, dy_mm=1)
    data[0, 1, 1] = 5.0
    assert grid.values[0, 1, 1] == 0.0
    with pytest.raises(ValueError):
        grid.values[0, 0, 0] = 1.0


@settings(max_examples=60, deadline=None)
@given(values=arrays(np.float64, st.tuples(st.integers(2, 6), st.integers(2, 6)),
                     elements=st.floats(-10.0, 10.0)),
       pts=arrays(np.float64, (8, 2), elements=st.floats(-50.0, 50.0)),
       order=st.sampled_from([0, 1, 3]))
def test_interpolation_is_finite_and_bilinear_stays_within_the_data(values, pts, order) -> None:
    grid = GridLayers(values[None], x0_mm=-3.0, y0_mm=-2.0, dx_mm=0.7, dy_mm=1.1)
    out, inside = grid.sample(pts, order)
    assert np.isfinite(out).all()
    assert out.shape == (1, 8) and inside.shape == (8,)
    if order in (0, 1):
        assert out.min() >= values.min() - 1e-9 and out.max() <= values.max() + 1e-9


def _ghost_reference(values: np.ndarray, axis: int) -> np.ndarray:
    """The ghost padding as first written, one axis at a time (the independent reference)."""
    v = np.moveaxis(values, axis, -1)
    if v.shape[-1] >= 3:
        lo = 3.0 * v[..., 0] - 3.0 * v[..., 1] + v[..., 2]
        hi = 3.0 * v[..., -1] - 3.0 * v[..., -2] + v[..., -3]
    else:
        lo = 2.0 * v[..., 0] - v[..., 1]
        hi = 2.0 * v[..., -1] - v[..., -2]
    out = np.concatenate([lo[..., None], v, hi[..., None]], axis=-1)
    return np.moveaxis(out, -1, axis)


@given(st.integers(1, 4), st.integers(2, 12), st.integers(2, 12), st.integers(0, 2**32 - 1),
       st.floats(1e-3, 1e6))
def test_the_ghost_padding_equals_the_axis_by_axis_reference_bit_for_bit(
        layers: int, ny: int, nx: int, seed: int, scale: float) -> None:
    # the padding the Keys kernel reads, built in one array: the same arithmetic in the
    # same order as padding the rows, then the columns of the padded rows
    from local_site.render.interpolation import _with_ghosts

    values = np.random.default_rng(seed).normal(0.0, scale, (layers, ny, nx))
    got = _with_ghosts(values)
    want = _ghost_reference(_ghost_reference(values, 1), 2)
    assert got.shape == (layers, ny + 2, nx + 2) and got.flags.c_contiguous
    assert got.tobytes() == np.ascontiguousarray(want).tobytes()  # -0.0 and 0.0 differ here
    np.testing.assert_array_equal(got[:, 1:-1, 1:-1], values)


#: the whole finite range, and the accepted range (so both outcomes are drawn often)
_ANY_FINITE = (st.floats(allow_nan=False, allow_infinity=False)
               | st.floats(-MAX_LAYER_ABS, MAX_LAYER_ABS))


@settings(max_examples=80, deadline=None)
@given(values=arrays(np.float64, st.tuples(st.just(1), st.integers(2, 5), st.integers(2, 5)),
                     elements=_ANY_FINITE),
       order=st.sampled_from([0, 1, 3]), data=st.data())
def test_any_finite_grid_is_refused_or_interpolates_finitely_within_its_data(
        values: np.ndarray, order: int, data: st.DataObject) -> None:
    # over the WHOLE finite range: a grid is either refused up front or every sample is
    # finite, the clipped one within the data, and a grid node returns the node's value
    # (cubic border extrapolation of values near the float limit overflowed to inf -> NaN)
    if np.abs(values).max() > MAX_LAYER_ABS:
        with pytest.raises(InputDataError, match="within"):
            GridLayers(values, x0_mm=0.0, y0_mm=0.0, dx_mm=1.0, dy_mm=1.0)
        return
    grid = GridLayers(values, x0_mm=0.0, y0_mm=0.0, dx_mm=1.0, dy_mm=1.0)
    ny, nx = values.shape[1:]
    r = data.draw(st.integers(0, ny - 1))
    c = data.draw(st.integers(0, nx - 1))
    px = data.draw(st.floats(-2.0, nx + 1.0))
    py = data.draw(st.floats(-2.0, ny + 1.0))
    pts = np.array([[float(c), float(r)], [px, py]])
    raw, _ = grid.sample(pts, order)
    out, _ = grid.sample(pts, order, clip=True)
    assert np.isfinite(raw).all() and np.isfinite(out).all()
    assert values.min() <= out.min() and out.max() <= values.max()
    assert out[0, 0] == values[0, r, c]


@pytest.mark.parametrize("big", [MAX_LAYER_ABS * 1.0001, 1e308, -1.7e308])
def test_values_near_the_float_limit_are_refused(big: float) -> None:
    values = np.zeros((1, 4, 4))
    values[0, 0, 0] = big
    with pytest.raises(InputDataError, match="within"):
        GridLayers(values, x0_mm=0.0, y0_mm=0.0, dx_mm=1.0, dy_mm=1.0)
    values[0, 0, 0] = np.copysign(MAX_LAYER_ABS, big)  # the bound itself is accepted
    grid = GridLayers(values, x0_mm=0.0, y0_mm=0.0, dx_mm=1.0, dy_mm=1.0)
    assert np.isfinite(grid.sample(np.array([[0.0, 0.0], [0.4, 0.6]]), 3)[0]).all()
