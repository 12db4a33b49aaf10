"""The fused reconstruction kernels against the frozen numpy reference, over random inputs.

Reference: ``lab/reconstruction_reference.py`` (the pipeline before the speed work). Stages
that do the same float32 operations must agree bit for bit; the zero-level plane (normal
equations instead of an SVD least squares) to float rounding. The Poisson solve is also
checked against an analytic property: the discrete Laplacian of its output (with the
solver's boundary) is the divergence of the edge slopes.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lab.reconstruction_reference as ref
from remote_site.reconstruction.features import brightness_gain, relative_change
from remote_site.reconstruction.kernels import (
    DIV_DCT,
    DIV_DST,
    DIV_FFT,
    clipped_counts,
    divergence_kernel,
    evidence_kernel,
    free_subsample_kernel,
)
from remote_site.reconstruction.poisson import SOLVERS, PoissonSolver
from remote_site.reconstruction.reconstructor import ReconstructionSettings, Reconstructor
from remote_site.sensor.photometric import PhotometricModel
from remote_site.sensor.shapes import ball_depth_mm
from remote_site.sensor.sim_calibration import simulated_calibration
from shared.errors import InputDataError

CODES = {"dct": DIV_DCT, "dst": DIV_DST, "fft": DIV_FFT}
shapes = st.tuples(st.integers(2, 48), st.integers(2, 48))


def _frame(rng: np.random.Generator, shape: tuple[int, int], levels: int) -> np.ndarray:
    """A float32 frame in [0, 255] with ``levels`` distinct values (ties, like uint8)."""
    return (rng.integers(0, levels, (*shape, 3)) * (255.0 / max(levels - 1, 1))).astype(
        np.float32)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), shape=st.tuples(st.integers(8, 90), st.integers(8, 90)),
       levels=st.sampled_from([3, 20, 256]), gain=st.floats(0.3, 3.0),
       changed=st.floats(0.0, 0.95))
def test_brightness_gain_equals_reference(seed: int, shape: tuple[int, int], levels: int,
                                          gain: float, changed: float) -> None:
    rng = np.random.default_rng(seed)
    background = np.clip(_frame(rng, shape, levels), 0, 255)
    frame = np.clip(background * np.float32(gain), 0, 255).astype(np.float32)
    press = rng.random(shape) < changed
    frame[press] = _frame(rng, shape, levels)[press]
    try:
        expected = ref.reference_brightness_gain(frame, background)
    except InputDataError:
        with pytest.raises(InputDataError, match="brightness gain"):
            brightness_gain(frame, background)
        return
    np.testing.assert_array_equal(brightness_gain(frame, background), expected)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), shape=st.tuples(st.integers(8, 60), st.integers(8, 60)),
       blur=st.sampled_from([0.0, 1.0, 1.7]))
def test_relative_change_equals_reference(seed: int, shape: tuple[int, int],
                                          blur: float) -> None:
    rng = np.random.default_rng(seed)
    background = rng.uniform(20, 230, (*shape, 3)).astype(np.float32)
    frame = np.clip(background * rng.uniform(0.8, 1.2, (*shape, 3)), 0, 255).astype(np.float32)
    np.testing.assert_array_equal(relative_change(frame, background, blur),
                                  ref.reference_relative_change(frame, background, blur))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), shape=shapes, nan_fraction=st.sampled_from([0.0, 0.1]),
       thresholds=st.tuples(st.floats(0, 20), st.floats(0, 20)))
def test_evidence_equals_reference_with_nan(seed: int, shape: tuple[int, int],
                                            nan_fraction: float,
                                            thresholds: tuple[float, float]) -> None:
    rng = np.random.default_rng(seed)
    change = rng.normal(0, 8, (*shape, 3)).astype(np.float32)
    change[rng.random((*shape, 3)) < nan_fraction] = np.nan
    ev, dz = np.float32(thresholds[0]), np.float32(thresholds[1])
    magnitude = ref.reference_abs_max(change)
    count, active = evidence_kernel(change, ev, dz)
    assert count == int(np.count_nonzero(magnitude > ev))
    np.testing.assert_array_equal(active, magnitude > dz)


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31), shape=shapes, solver=st.sampled_from(SOLVERS),
       dtype=st.sampled_from([np.float32, np.float64]), pitch=st.floats(1e-3, 1.0))
def test_divergence_equals_reference(seed: int, shape: tuple[int, int], solver: str,
                                     dtype: type[np.floating], pitch: float) -> None:
    rng = np.random.default_rng(seed)
    gx, gy = rng.normal(0, 1, (2, *shape))
    out = np.empty(shape, dtype)
    divergence_kernel(gx, gy, dtype(pitch), CODES[solver], out)
    px = gx.astype(dtype) * dtype(pitch)
    py = gy.astype(dtype) * dtype(pitch)
    np.testing.assert_array_equal(out, ref.reference_divergence(px, py, solver))


def _laplacian(h: np.ndarray, solver: str) -> np.ndarray:
    """Discrete Laplacian with the solver's boundary: ghost pixels are -h (DST: h = 0 half a
    pixel outside), h (DCT: no flux) or the opposite border (FFT)."""
    h = h.astype(np.float64)
    padded = np.pad(h, 1, mode="wrap") if solver == "fft" else np.pad(h, 1, mode="edge")
    if solver == "dst":
        padded[0, 1:-1], padded[-1, 1:-1] = -h[0], -h[-1]
        padded[1:-1, 0], padded[1:-1, -1] = -h[:, 0], -h[:, -1]
    core = padded[1:-1, 1:-1]
    return (padded[:-2, 1:-1] + padded[2:, 1:-1] + padded[1:-1, :-2] + padded[1:-1, 2:]
            - 4.0 * core)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), shape=shapes, solver=st.sampled_from(SOLVERS),
       pitch=st.floats(0.01, 0.5))
def test_poisson_inverts_the_discrete_gradient(seed: int, shape: tuple[int, int], solver: str,
                                               pitch: float) -> None:
    rng = np.random.default_rng(seed)
    gx, gy = rng.normal(0, 0.5, (2, *shape))
    gx_in, gy_in = gx.copy(), gy.copy()
    h = PoissonSolver(solver, np.float64).integrate(gx, gy, pitch)
    np.testing.assert_array_equal(gx, gx_in)  # in-place transforms never touch the inputs
    np.testing.assert_array_equal(gy, gy_in)
    div = ref.reference_divergence(gx * pitch, gy * pitch, solver)
    scale = max(1.0, float(np.abs(div).max()))
    np.testing.assert_allclose(_laplacian(h, solver), div, rtol=0, atol=1e-9 * scale)
    # float32 (the default) matches the reference float32 solve to rounding
    h32 = PoissonSolver(solver).integrate(gx, gy, pitch)
    expected = ref.reference_integrate(gx, gy, pitch, solver)
    tol = 1e-5 * max(1.0, float(np.abs(expected).max()))
    np.testing.assert_allclose(h32, expected, rtol=0, atol=tol)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31), rows=st.integers(2, 260), cols=st.integers(2, 340),
       radius=st.floats(0.05, 0.6), noise=st.sampled_from([0.0, 1e-3, 0.1]))
def test_dst_column_solve_is_as_accurate_as_the_2d_transform(
        seed: int, rows: int, cols: int, radius: float, noise: float) -> None:
    """The DST solver's tridiagonal column solve (float32 transforms, float64 recurrence)
    against the float64 2-D DST solve of the frozen reference, on up to full-frame sizes
    with a smooth bump (the ill-conditioned low frequencies dominate): no further from it
    than the float32 2-D DST solve it replaced, up to rounding."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:rows, 0:cols]
    r2 = ((yy - rows * rng.uniform(0.3, 0.7)) ** 2 + (xx - cols * rng.uniform(0.3, 0.7)) ** 2
          ) / (radius * max(rows, cols)) ** 2
    h = np.exp(-r2)
    gx = np.gradient(h, axis=1) + rng.normal(0, noise, h.shape)
    gy = np.gradient(h, axis=0) + rng.normal(0, noise, h.shape)
    pitch = 0.0634
    gx, gy = (gx / pitch).astype(np.float32), (gy / pitch).astype(np.float32)
    exact = _float64_dst_solve(gx, gy, pitch)
    got = PoissonSolver("dst").integrate(gx, gy, pitch)
    old = ref.reference_integrate(gx, gy, pitch, "dst")
    scale = max(1.0, float(np.abs(exact).max()))
    assert got.dtype == np.float32 and got.shape == gx.shape
    assert np.abs(got - exact).max() <= 2.0 * np.abs(old - exact).max() + 1e-6 * scale


def _float64_dst_solve(gx: np.ndarray, gy: np.ndarray, pitch: float) -> np.ndarray:
    """The 2-D DST-II solve of the reference, in float64."""
    import scipy.fft as sfft

    rows, cols = gx.shape
    div = ref.reference_divergence(gx.astype(np.float64) * pitch, gy.astype(np.float64) * pitch,
                                   "dst")
    ky = 2.0 * np.cos(np.pi * np.arange(1, rows + 1) / rows) - 2.0
    kx = 2.0 * np.cos(np.pi * np.arange(1, cols + 1) / cols) - 2.0
    spec = sfft.dstn(div, type=2) / (ky[:, None] + kx[None, :])
    return np.asarray(sfft.idstn(spec, type=2))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), shape=st.tuples(st.integers(1, 40), st.integers(1, 40)),
       step=st.integers(1, 5), clipped=st.floats(0.0, 1.0))
def test_clipped_counts_equal_numpy(seed: int, shape: tuple[int, int], step: int,
                                    clipped: float) -> None:
    from remote_site.reconstruction.frames import BLACK_LEVEL, SATURATION_LEVEL

    rng = np.random.default_rng(seed)
    image = rng.uniform(0, 255, (*shape, 3)).astype(np.float32)
    pick = rng.random((*shape, 3)) < clipped
    image[pick] = rng.choice(np.array([0.0, 3.0, 3.5, 254.0, 254.5, 255.0], np.float32),
                             int(pick.sum()))
    sub = image[::step, ::step]
    saturated = (sub >= SATURATION_LEVEL).any(axis=2)
    black = (sub <= BLACK_LEVEL).all(axis=2)
    got = clipped_counts(image, step, np.float32(SATURATION_LEVEL), np.float32(BLACK_LEVEL))
    assert got == (int(saturated.sum()), int(black.sum()), saturated.size)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_poisson_rejects_non_finite_slopes(bad: float) -> None:
    gx = np.zeros((6, 7))
    gx[3, 0] = bad
    for solver in SOLVERS:
        with pytest.raises(InputDataError, match="NaN or Inf"):
            PoissonSolver(solver).integrate(gx, np.zeros((6, 7)), 0.1)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), shape=st.tuples(st.integers(8, 120), st.integers(8, 120)),
       radius=st.integers(0, 20), step=st.integers(1, 5), density=st.floats(0.0, 0.05))
def test_free_subsample_equals_dilation(seed: int, shape: tuple[int, int], radius: int,
                                        step: int, density: float) -> None:
    rng = np.random.default_rng(seed)
    height = np.where(rng.random(shape) < density, 1.0, 0.0).astype(np.float32)
    raised = (height > 0.5).astype(np.uint8)
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    expected = cv2.dilate(raised, kernel)[::step, ::step] == 0
    integral = np.full((shape[0] + 1, shape[1] + 1), 99, np.int32)  # garbage: must be reset
    got = free_subsample_kernel(height, np.float32(0.0), np.float32(0.5), radius, step, integral)
    np.testing.assert_array_equal(got, expected)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), shape=st.tuples(st.integers(10, 130), st.integers(10, 130)),
       mode=st.sampled_from(["plane", "median", "none"]), tilt=st.floats(-1e-3, 1e-3),
       bump=st.floats(0.0, 0.6), pitch=st.sampled_from([0.0634, 0.2, 1.0]))
def test_zero_level_matches_reference(seed: int, shape: tuple[int, int], mode: str,
                                      tilt: float, bump: float, pitch: float) -> None:
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:shape[0], 0:shape[1]]
    cy, cx = rng.uniform(0, shape[0]), rng.uniform(0, shape[1])
    height = (0.02 + tilt * c - 0.5 * tilt * r + rng.normal(0, 0.002, shape)
              + bump * np.exp(-((r - cy) ** 2 + (c - cx) ** 2) / (0.1 * shape[0] ** 2)))
    height = height.astype(np.float32)
    rec = Reconstructor(simulated_calibration(), ReconstructionSettings(zero_level=mode))
    out, mask, finite = rec._zero_level_and_mask(height, pitch)
    expected = ref.reference_zero_level(height, pitch, mode)
    assert finite and out.dtype == np.float32
    np.testing.assert_allclose(out, expected, rtol=0, atol=2e-6)
    near = np.abs(expected - 0.03) < 2e-6  # the threshold may fall either way only here
    np.testing.assert_array_equal(mask[~near], (expected > 0.03)[~near])


@pytest.fixture(scope="module")
def sim() -> tuple[PhotometricModel, Reconstructor]:
    return PhotometricModel(seed=11), Reconstructor(simulated_calibration())


@settings(max_examples=12, deadline=None)
@given(cx=st.floats(0.15, 0.85), cy=st.floats(0.15, 0.85), depth=st.floats(0.0, 0.6),
       solver=st.sampled_from(SOLVERS))
def test_height_map_equals_reference_on_rendered_presses(
        sim: tuple[PhotometricModel, Reconstructor], cx: float, cy: float, depth: float,
        solver: str) -> None:
    model, base = sim
    rec = Reconstructor(base.calibration, ReconstructionSettings(solver=solver))
    rows, cols = model.settings.shape_hw
    frame = model.render(ball_depth_mm((rows, cols), model.settings.mm_per_px, cx * cols,
                                       cy * rows, 3.0, depth))
    got = rec.height_map(frame)
    expected = ref.reference_height_map(rec, frame)
    assert got.skipped == expected.skipped
    np.testing.assert_allclose(got.height_mm, expected.height_mm, rtol=0, atol=1e-5)
    near = np.abs(expected.height_mm - rec.settings.contact_threshold_mm) < 1e-5
    np.testing.assert_array_equal(got.mask[~near], expected.mask[~near])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), degree=st.sampled_from([1, 2, 3, 4, 5]),
       shape=st.tuples(st.integers(2, 40), st.integers(2, 40)), spread=st.floats(0.1, 30.0),
       density=st.floats(0.0, 1.0))
def test_baked_predictor_equals_the_reference_kernel(seed: int, degree: int,
                                                     shape: tuple[int, int], spread: float,
                                                     density: float) -> None:
    from remote_site.reconstruction.features import pixel_position
    from remote_site.reconstruction.grid_predict import BakedPolyPredictor
    from remote_site.reconstruction.models import PolyGradientModel, _exponents

    rng = np.random.default_rng(seed)
    coef = rng.normal(0.0, 0.3, (len(_exponents(5, degree)), 2))
    scale = np.concatenate([rng.uniform(5.0, 20.0, 3), [0.5, 0.5]])
    x, y = pixel_position(shape)
    predictor = PolyGradientModel(coef, scale, degree, True).grid_predictor(x, y)
    assert isinstance(predictor, BakedPolyPredictor)
    change = rng.normal(0.0, spread, (*shape, 3)).astype(np.float32)
    active = rng.random(shape) < density
    got = np.full((2, *shape), 7.0, np.float32)
    expected = got.copy()
    predictor.predict_into(change, active, got[0], got[1])
    ref._predict_active(change, active, predictor.inv_scale, predictor.exponents,
                        predictor.coeffs, predictor.max_slope, expected[0], expected[1])
    np.testing.assert_array_equal(got[:, ~active], 7.0)  # inactive pixels untouched
    # the generated kernels evaluate the polynomial by nested Horner (another order than the
    # loop kernel's sum of monomials): both equal the exact (float64) polynomial up to
    # float32 rounding, bounded by ~n_terms x eps x sum |terms| (the clip is 1-Lipschitz)
    values = change.astype(np.float64) * predictor.inv_scale.astype(np.float64)
    monomials = np.prod(values[..., None, :] ** predictor.exponents[None, None], axis=-1)
    table = predictor.coeffs.reshape(*shape, -1, 2).astype(np.float64)
    magnitude = np.einsum("ijm,ijmk->kij", np.abs(monomials), np.abs(table))
    exact = np.clip(np.einsum("ijm,ijmk->kij", monomials, table), -predictor.max_slope,
                    predictor.max_slope)
    n_terms = len(predictor.exponents)
    bound = 2 * (n_terms + 8) * float(np.finfo(np.float32).eps) * magnitude
    assert np.all(np.abs(got - expected)[:, active] <= bound[:, active])
    assert np.all(np.abs(got - exact)[:, active] <= bound[:, active])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), rows=st.integers(1, 4), n=st.integers(1, 300),
       levels=st.sampled_from([2, 7, 10_000]))
def test_row_medians_equal_numpy(seed: int, rows: int, n: int, levels: int) -> None:
    from remote_site.reconstruction.features import row_medians

    rng = np.random.default_rng(seed)
    values = (rng.integers(0, levels, (rows, n)) / rng.uniform(1, 300)).astype(np.float32)
    got = row_medians(values)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, np.median(values, axis=1))


def test_generated_poly_kernels_are_up_to_date() -> None:
    from lab.gen_poly_kernels import TARGET, generate

    assert TARGET.read_text() == generate(), "run: python -m lab.gen_poly_kernels"


def test_results_are_never_workspace_memory(sim: tuple[PhotometricModel, Reconstructor]) -> None:
    """Scratch arrays are reused between frames: what a caller holds must not change."""
    model, rec = sim
    rows, cols = model.settings.shape_hw
    p = model.settings.mm_per_px
    frames = [model.render(ball_depth_mm((rows, cols), p, cols * x, rows * 0.5, 3.0, 0.4))
              for x in (0.3, 0.7)]
    first = rec.height_map(frames[0])
    kept = first.height_mm.copy(), first.mask.copy()
    gx, _gy, _ = rec.slopes(frames[0])
    gx_kept = gx.copy()
    second = rec.height_map(frames[1])
    rec.slopes(frames[1])
    np.testing.assert_array_equal(first.height_mm, kept[0])
    np.testing.assert_array_equal(first.mask, kept[1])
    np.testing.assert_array_equal(gx, gx_kept)
    assert not np.shares_memory(first.height_mm, second.height_mm)
    again = rec.height_map(frames[0])
    np.testing.assert_array_equal(again.height_mm, first.height_mm)


def test_reconstructor_threads_do_not_share_scratch(
        sim: tuple[PhotometricModel, Reconstructor]) -> None:
    import threading

    model, rec = sim
    rows, cols = model.settings.shape_hw
    p = model.settings.mm_per_px
    frames = [model.render(ball_depth_mm((rows, cols), p, cols * x, rows * 0.5, 3.0, 0.4))
              for x in (0.3, 0.7)]
    expected = [rec.height_map(f).height_mm for f in frames]
    failures: list[str] = []

    def worker(k: int) -> None:
        for _ in range(15):
            if not np.array_equal(rec.height_map(frames[k]).height_mm, expected[k]):
                failures.append(f"thread {k}")

    threads = [threading.Thread(target=worker, args=(k,)) for k in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not failures


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31), dtype=st.sampled_from([np.uint8, np.float32, np.float64]),
       blur=st.sampled_from([0.0, 1.0]))
def test_scratch_outputs_equal_fresh_ones(seed: int, dtype: type, blur: float) -> None:
    from remote_site.reconstruction.frames import validate_frame

    rng = np.random.default_rng(seed)
    raw: np.ndarray = rng.integers(20, 230, (24, 31, 3)).astype(dtype)
    garbage = np.full((24, 31, 3), np.nan, np.float32)
    frame = validate_frame(raw, out=garbage)
    assert frame is garbage
    np.testing.assert_array_equal(frame, validate_frame(raw))
    background = rng.uniform(20, 230, (24, 31, 3)).astype(np.float32)
    out, work = np.full_like(garbage, 7.0), np.full_like(garbage, 7.0)
    np.testing.assert_array_equal(relative_change(frame, background, blur, out=out, work=work),
                                  relative_change(frame, background, blur))
