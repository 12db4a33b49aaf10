"""The boundary features that type a finding: their expectation must not depend on the
number of samples (a loaded machine delivers fewer frames), and they are checked against
independent references (the analytic distance of a disc, the plain mean of the samples).
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import special

from local_site.palpation.edge import edge_distance_mm, fit_edge, rim_level

CELL = 0.5
N = 48  # cells per side: 24 mm


def _radius_mm() -> np.ndarray:
    c = (np.arange(N) - (N - 1) / 2.0) * CELL
    return np.hypot(c[None, :], c[:, None])


Samples = tuple[np.ndarray, np.ndarray]  # (cell index, value) of every sample


def _samples(rng: np.random.Generator, radius: float, width: float, amplitude: float,
             noise: float, per_cell: float) -> tuple[np.ndarray, Samples]:
    """Samples of a blurred disc (an erfc edge of ``width`` at ``radius``), Poisson many
    per cell."""
    r = _radius_mm()
    truth = amplitude * 0.5 * special.erfc((r - radius) / (math.sqrt(2.0) * width))
    cell = np.repeat(np.arange(truth.size), rng.poisson(per_cell, truth.size))
    return truth, (cell, truth.ravel()[cell] + rng.normal(0.0, noise, cell.size))


def _cells(samples: Samples) -> tuple[np.ndarray, np.ndarray]:
    cell, value = samples
    counts = np.bincount(cell, minlength=N * N).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.bincount(cell, value, minlength=N * N) / counts
    return means.reshape(N, N), counts.reshape(N, N)


def _keep(rng: np.random.Generator, samples: Samples, p: float) -> Samples:
    kept = rng.random(samples[0].size) < p
    return samples[0][kept], samples[1][kept]


profiles = dict(radius=st.floats(3.0, 7.0), width=st.floats(0.3, 2.0),
                amplitude=st.floats(0.3, 2.0), noise=st.floats(0.02, 0.3),
                per_cell=st.floats(4.0, 30.0), seed=st.integers(0, 2**31 - 1))


def test_signed_distance_matches_a_disc() -> None:
    r = _radius_mm()
    inside = r <= 5.0
    d = edge_distance_mm(inside, CELL)
    near = np.abs(r - 5.0) <= 3.0
    assert (d[inside] < 0).all() and (d[~inside] > 0).all()
    # cell-centre distances on a grid: within one cell of the analytic |r - R|
    assert np.abs(d[near] - (r[near] - 5.0)).max() <= CELL


@settings(max_examples=25, deadline=None)
@given(**profiles)
def test_edge_width_recovered(radius: float, width: float, amplitude: float, noise: float,
                              per_cell: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth, samples = _samples(rng, radius, width, amplitude, noise, per_cell)
    means, counts = _cells(samples)
    d = edge_distance_mm(truth >= amplitude / 2.0, CELL)
    fit = fit_edge(means, counts, d, np.ones_like(counts, bool))
    assert math.isfinite(fit.width_se_mm)
    # the grid quantises the distance (about cell / sqrt(12) of extra blur)
    assert abs(fit.width_mm - width) <= 0.1 + 0.1 * width + 4.0 * fit.width_se_mm


@settings(max_examples=25, deadline=None)
@given(**profiles, keep=st.floats(0.15, 0.6))
def test_edge_width_does_not_drift_when_samples_are_dropped(
        radius: float, width: float, amplitude: float, noise: float, per_cell: float,
        seed: int, keep: float) -> None:
    """Fewer samples (each kept with probability ``keep``, as frames lost under load) make
    the width noisier, not biased: both estimates agree within their standard errors."""
    rng = np.random.default_rng(seed)
    truth, samples = _samples(rng, radius, width, amplitude, noise, per_cell)
    d = edge_distance_mm(truth >= amplitude / 2.0, CELL)
    use = np.ones((N, N), bool)
    full = fit_edge(*_cells(samples), d, use)
    sparse = fit_edge(*_cells(_keep(rng, samples, keep)), d, use)
    assert math.isfinite(full.width_se_mm) and math.isfinite(sparse.width_se_mm)
    tolerance = 4.0 * math.hypot(full.width_se_mm, sparse.width_se_mm) + 0.02 * width
    assert abs(sparse.width_mm - full.width_mm) <= tolerance


@settings(max_examples=25, deadline=None)
@given(**profiles, keep=st.floats(0.15, 1.0))
def test_rim_level_is_the_mean_of_the_samples(radius: float, width: float, amplitude: float,
                                              noise: float, per_cell: float, seed: int,
                                              keep: float) -> None:
    rng = np.random.default_rng(seed)
    truth, samples = _samples(rng, radius, width, amplitude, noise, per_cell)
    samples = _keep(rng, samples, keep)
    means, counts = _cells(samples)
    d = edge_distance_mm(truth >= amplitude / 2.0, CELL)
    level, se = rim_level(means, counts, d, np.ones((N, N), bool), (-2.5, -0.5))
    band = ((d >= -2.5) & (d <= -0.5)).ravel()
    pooled = samples[1][band[samples[0]]]
    assert math.isclose(level, float(pooled.mean()), rel_tol=1e-9, abs_tol=1e-12)
    assert 0 < se < math.inf


def test_too_few_cells_is_no_estimate() -> None:
    d = edge_distance_mm(_radius_mm() <= 5.0, CELL)
    counts = np.zeros((N, N))
    counts[0, :3] = 5
    values = np.where(counts > 0, 1.0, np.nan)
    fit = fit_edge(values, counts, d, np.ones((N, N), bool))
    assert fit.width_se_mm == math.inf and fit.relative_se == math.inf
    level, se = rim_level(values, counts, d, np.ones((N, N), bool))
    assert math.isnan(level) and se == math.inf
