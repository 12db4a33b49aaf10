"""Poisson integration against analytic functions and over degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from remote_site.reconstruction.poisson import SOLVERS, PoissonSolver
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
