"""Poisson integration against analytic functions and over degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from remote_site.reconstruction.poisson import MAX_FREE_BORDER_FRACTION, SOLVERS, PoissonSolver
from shared.errors import InputDataError

PITCH_MM = 0.0634


def _bump(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A Gaussian bump well inside the frame with its exact gradient."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]] * PITCH_MM
    cy, cx = shape[0] * PITCH_MM / 2, shape[1] * PITCH_MM / 2.2
    h = 0.5 * np.exp(-((cols - cx) ** 2 + (rows - cy) ** 2) / 4.0)
    gx = h * (-2 * (cols - cx) / 4.0)
    gy = h * (-2 * (rows - cy) / 4.0)
    return h, gx, gy


@pytest.mark.parametrize("solver", SOLVERS)
def test_integrates_analytic_bump(solver: str) -> None:
    h, gx, gy = _bump((240, 320))
    out = PoissonSolver(solver).integrate(gx, gy, PITCH_MM)
    err = out - h
    err -= np.median(err)
    assert np.sqrt(np.mean(err**2)) < 2e-4
    assert np.abs(err).max() < 2e-3


def test_dst_pins_the_border_to_zero_without_offset() -> None:
    h, gx, gy = _bump((240, 320))
    out = PoissonSolver("dst").integrate(gx, gy, PITCH_MM)
    assert np.abs(out - h).max() < 2e-3  # no constant to remove


def test_linear_ramp_is_exact_for_dct() -> None:
    _, cols = np.mgrid[0:50, 0:70]
    h = 0.01 * cols * PITCH_MM
    out = PoissonSolver("dct").integrate(np.full(h.shape, 0.01), np.zeros(h.shape), PITCH_MM)
    np.testing.assert_allclose(out - out.mean(), h - h.mean(), atol=1e-5)


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(2, 60), cols=st.integers(2, 60), solver=st.sampled_from(SOLVERS))
def test_zero_gradients_give_zero_height(rows: int, cols: int, solver: str) -> None:
    out = PoissonSolver(solver).integrate(np.zeros((rows, cols)), np.zeros((rows, cols)), 0.1)
    assert out.shape == (rows, cols)
    assert np.abs(out).max() == 0.0


@settings(max_examples=40, deadline=None)
@given(g=arrays(np.float64, (2, 17, 23), elements=st.floats(-50, 50)),
       solver=st.sampled_from(SOLVERS), pitch=st.floats(1e-3, 10.0))
def test_extreme_gradients_stay_finite_and_bounded(g: np.ndarray, solver: str,
                                                   pitch: float) -> None:
    out = PoissonSolver(solver).integrate(g[0], g[1], pitch)
    assert np.isfinite(out).all()
    # A least-squares height never varies more than the steepest path across the frame.
    assert np.ptp(out) <= 2 * 50 * pitch * (17 + 23) + 1e-6


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_gradients_rejected(bad: float) -> None:
    gx = np.zeros((10, 10))
    gx[3, 4] = bad
    with pytest.raises(InputDataError):
        PoissonSolver().integrate(gx, np.zeros((10, 10)), PITCH_MM)


@pytest.mark.parametrize(("gx", "gy", "pitch"), [
    (np.zeros((10, 10)), np.zeros((10, 11)), 0.1),
    (np.zeros((1, 10)), np.zeros((1, 10)), 0.1),
    (np.zeros(10), np.zeros(10), 0.1),
    (np.zeros((5, 5)), np.zeros((5, 5)), 0.0),
    (np.zeros((5, 5)), np.zeros((5, 5)), float("nan")),
])
def test_bad_shapes_and_pitch_rejected(gx: np.ndarray, gy: np.ndarray, pitch: float) -> None:
    with pytest.raises(InputDataError):
        PoissonSolver().integrate(gx, gy, pitch)


def test_unknown_solver_rejected() -> None:
    with pytest.raises(InputDataError):
        PoissonSolver("multigrid")


# ---------------------------------------------------------------- free border pixels (dst)


def _least_squares_reference(gx: np.ndarray, gy: np.ndarray, pitch: float,
                             free: np.ndarray) -> np.ndarray:
    """The least-squares height written out edge by edge and solved densely (independent of
    the transforms and of the Woodbury update): interior edges carry the mean of their two
    pixels' slopes; each border pixel not ``free`` has one edge per frame side it touches to
    a ghost at h = 0 half a pixel outside (height step 2 h over the ghost's spacing, weight
    1/2: the DST-II condition), carrying the pixel's own slope."""
    rows, cols = gx.shape
    index = np.arange(rows * cols).reshape(rows, cols)
    px, py = gx * pitch, gy * pitch
    lines: list[tuple[list[tuple[int, float]], float, float]] = []
    for i in range(rows):
        for j in range(cols - 1):
            lines.append(([(index[i, j + 1], 1.0), (index[i, j], -1.0)],
                          0.5 * (px[i, j] + px[i, j + 1]), 1.0))
    for i in range(rows - 1):
        for j in range(cols):
            lines.append(([(index[i + 1, j], 1.0), (index[i, j], -1.0)],
                          0.5 * (py[i, j] + py[i + 1, j]), 1.0))
    ghost_weight = np.sqrt(0.5)
    for i in range(rows):
        if not free[i, 0]:
            lines.append(([(index[i, 0], 2.0)], px[i, 0], ghost_weight))
        if not free[i, -1]:
            lines.append(([(index[i, -1], -2.0)], px[i, -1], ghost_weight))
    for j in range(cols):
        if not free[0, j]:
            lines.append(([(index[0, j], 2.0)], py[0, j], ghost_weight))
        if not free[-1, j]:
            lines.append(([(index[-1, j], -2.0)], py[-1, j], ghost_weight))
    a = np.zeros((len(lines), rows * cols))
    b = np.zeros(len(lines))
    for r, (terms, target, weight) in enumerate(lines):
        for c, v in terms:
            a[r, c] = v * weight
        b[r] = target * weight
    return np.linalg.lstsq(a, b, rcond=None)[0].reshape(rows, cols)


def _border(shape: tuple[int, int]) -> np.ndarray:
    border = np.zeros(shape, bool)
    border[0] = border[-1] = border[:, 0] = border[:, -1] = True
    return border


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(2, 9), cols=st.integers(2, 9), seed=st.integers(0, 2**32 - 1),
       share=st.floats(0.0, 1.0), pitch=st.floats(0.01, 2.0))
def test_free_border_is_the_least_squares_height_without_those_edges(
        rows: int, cols: int, seed: int, share: float, pitch: float) -> None:
    rng = np.random.default_rng(seed)
    gx, gy = rng.normal(0, 0.5, (2, rows, cols))
    border = _border((rows, cols))
    free = border & (rng.random((rows, cols)) < share)
    free |= rng.random((rows, cols)) < 0.2  # interior marks are ignored
    out = PoissonSolver("dst", np.float64).integrate(gx, gy, pitch, free_border=free)
    # border edges dropped (a corner pixel has two); over half of the 2 (rows + cols) edges:
    # too few anchors left, the Dirichlet condition everywhere
    n_free = int(free[:, 0].sum() + free[:, -1].sum() + free[0].sum() + free[-1].sum())
    expected_free = free & border if n_free <= MAX_FREE_BORDER_FRACTION * 2 * (rows + cols) \
        else \
        np.zeros_like(free)
    ref = _least_squares_reference(gx, gy, pitch, expected_free)
    np.testing.assert_allclose(out, ref, atol=1e-9 * max(1.0, np.abs(ref).max()))


def test_no_free_pixel_is_exactly_the_dirichlet_solution() -> None:
    _, gx, gy = _bump((40, 50))
    solver = PoissonSolver("dst")
    np.testing.assert_array_equal(
        solver.integrate(gx, gy, PITCH_MM, free_border=np.zeros(gx.shape, bool)),
        solver.integrate(gx, gy, PITCH_MM))


def test_a_bump_cut_by_the_frame_edge_keeps_its_height_with_a_free_border() -> None:
    """A sphere cap whose contact runs off the left edge: h = 0 there pulls the cap down;
    freeing the steep border pixels gives it back (a plane of free gel elsewhere)."""
    rows, cols = 80, 100
    y, x = np.mgrid[0:rows, 0:cols] * PITCH_MM
    cx, cy, radius, contact = 0.5, rows * PITCH_MM / 2, 4.735, 1.9  # centre near the edge
    r2 = (x - cx) ** 2 + (y - cy) ** 2
    depth = radius - np.sqrt(radius**2 - contact**2)
    inside = r2 < contact**2
    z = np.where(inside, np.sqrt(np.clip(radius**2 - r2, 0, None)) - (radius - depth), 0.0)
    gx = np.where(inside, -(x - cx) / np.sqrt(np.clip(radius**2 - r2, 1e-9, None)), 0.0)
    gy = np.where(inside, -(y - cy) / np.sqrt(np.clip(radius**2 - r2, 1e-9, None)), 0.0)
    solver = PoissonSolver("dst", np.float64)
    fixed = solver.integrate(gx, gy, PITCH_MM)
    free = _border((rows, cols)) & (np.hypot(gx, gy) > 0.1)
    freed = solver.integrate(gx, gy, PITCH_MM, free_border=free)
    assert free.sum() > 0
    assert fixed.max() < z.max() - 0.1  # the Dirichlet edge costs the cap a lot
    assert abs(freed.max() - z.max()) < 0.02
    assert np.abs(freed - z)[~inside].max() < 0.03  # the free gel stays flat


def test_free_border_needs_dst_and_the_slopes_shape() -> None:
    g = np.zeros((6, 7))
    with pytest.raises(InputDataError, match="dst"):
        PoissonSolver("dct").integrate(g, g, 0.1, free_border=np.ones((6, 7), bool))
    with pytest.raises(InputDataError, match="shape"):
        PoissonSolver("dst").integrate(g, g, 0.1, free_border=np.ones((6, 8), bool))
