"""The reconstruction pipeline as it was before the full-resolution speed work (issue 12, item 4).

A frozen, straightforward numpy copy of each stage (colour change, evidence, model, Poisson,
zero level), kept as the *independent reference* the fast path is tested against
(tests/remote_site/test_reconstruction_fast_path.py) and as the "before" column of the A/B
benchmark (benchmarks/bench_reconstruction_fullres.py), which calls both alternately in one
run. Product code never imports this (lab is evaluation code); do not optimise it.

``reference_height_map(rec, frame)`` reproduces ``Reconstructor.height_map(frame)`` at full
resolution (no ``out_pitch_mm`` pooling) with the reconstructor's calibration, background and
settings, for the free-gel zero level (``relief="plane"``); the rim relief is a step after it,
with its own references (tests/remote_site/test_reconstruction_rim_relief.py).
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.fft as sfft
from numba import njit

from remote_site.reconstruction.frames import validate_frame
from remote_site.reconstruction.grid_predict import BakedPolyPredictor
from remote_site.reconstruction.reconstructor import HeightMap, Reconstructor
from shared.errors import InputDataError

__all__ = [
    "reference_abs_max",
    "reference_brightness_gain",
    "reference_height_map",
    "reference_integrate",
    "reference_relative_change",
    "reference_slopes",
    "reference_zero_level",
]

_GAIN_TOLERANCE = 0.05
_STAT_STEP = 4


def reference_brightness_gain(frame: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Per-channel gain (median ratio frame/background, refined on the unchanged pixels)."""
    step = max(1, min(_STAT_STEP, min(frame.shape[:2]) // 60))
    f = frame[::step, ::step].reshape(-1, 3)
    b = np.maximum(background[::step, ::step].reshape(-1, 3), 1.0)
    ratio = f / b
    gain = np.median(ratio, axis=0)
    unchanged = (np.abs(ratio - gain) < _GAIN_TOLERANCE * gain).all(axis=1)
    if unchanged.sum() >= 0.1 * len(ratio):
        gain = np.median(ratio[unchanged], axis=0)
    if not (np.isfinite(gain).all() and (gain > 0.2).all() and (gain < 5.0).all()):
        raise InputDataError(f"brightness gain {gain} between frame and background is "
                             "implausible: is the background from this sensor?")
    return gain.astype(np.float32)


def reference_relative_change(frame: np.ndarray, background: np.ndarray,
                              blur_sigma_px: float = 1.0,
                              inv_background_pct: np.ndarray | None = None) -> np.ndarray:
    """``100 * (I / (g * B) - 1)``, optionally Gaussian-blurred, (H, W, 3) float32."""
    import cv2

    gain = reference_brightness_gain(frame, background)
    if inv_background_pct is None:
        inv_background_pct = (100.0 / np.maximum(background, 1.0)).astype(np.float32)
    change = frame * (1.0 / gain).astype(np.float32)
    change *= inv_background_pct
    change -= np.float32(100.0)
    if blur_sigma_px > 0:
        change = cv2.GaussianBlur(change, (0, 0), blur_sigma_px)
    return change


def reference_abs_max(change: np.ndarray) -> np.ndarray:
    """max over channels of |change| (channel by channel, as the old reconstructor did)."""
    return np.maximum(np.maximum(np.abs(change[..., 0]), np.abs(change[..., 1])),
                      np.abs(change[..., 2]))


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


def reference_slopes(rec: Reconstructor, frame_rgb: np.ndarray,
                     background: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, bool]:
    """Full-resolution slopes and contact evidence, as ``Reconstructor.slopes`` computed them."""
    calib = rec.calibration
    frame = validate_frame(frame_rgb, rec.shape_hw)
    bg, inv_bg = rec._background_for(background)  # validated and cached as before
    change = reference_relative_change(frame, bg, calib.blur_sigma_px, inv_bg)
    noise = max(calib.noise_pct, 1e-3)
    magnitude = reference_abs_max(change)
    evidence = int(np.count_nonzero(magnitude > rec.settings.contact_evidence_sigmas * noise))
    min_px = rec.settings.min_contact_area_mm2 / calib.mm_per_px**2
    has_contact = evidence >= max(min_px, 1.0)
    gx = np.zeros(change.shape[:2], np.float32)
    gy = np.zeros(change.shape[:2], np.float32)
    if has_contact:
        active = magnitude > rec.settings.dead_zone_sigmas * noise
        predictor = rec._grid_predictor(1, change.shape[:2])
        if isinstance(predictor, BakedPolyPredictor):
            _predict_active(np.ascontiguousarray(change), active, predictor.inv_scale,
                            predictor.exponents, predictor.coeffs, predictor.max_slope, gx, gy)
        else:
            predictor.predict_into(change, active, gx, gy)
    return gx, gy, has_contact


def _edge_slopes(g: np.ndarray, axis: int, solver: str) -> np.ndarray:
    g = np.moveaxis(g, axis, -1)
    inner = 0.5 * (g[..., :-1] + g[..., 1:])
    if solver == "dct":
        first = np.zeros_like(g[..., :1])
        last = first
    elif solver == "dst":
        first, last = g[..., :1], g[..., -1:]
    else:
        wrap = 0.5 * (g[..., -1:] + g[..., :1])
        first, last = wrap, wrap
    edges = np.concatenate([first, inner, last], axis=-1)
    return np.moveaxis(edges, -1, axis)


def reference_divergence(px: np.ndarray, py: np.ndarray, solver: str) -> np.ndarray:
    """Divergence of the edge slopes (``px``, ``py`` already times the pitch)."""
    return (np.diff(_edge_slopes(px, 1, solver), axis=1)
            + np.diff(_edge_slopes(py, 0, solver), axis=0))


@functools.lru_cache(maxsize=8)
def _denominator(shape: tuple[int, int], solver: str) -> np.ndarray:
    rows, cols = shape
    if solver == "dct":
        ky = 2.0 * np.cos(np.pi * np.arange(rows) / rows) - 2.0
        kx = 2.0 * np.cos(np.pi * np.arange(cols) / cols) - 2.0
    elif solver == "dst":
        ky = 2.0 * np.cos(np.pi * np.arange(1, rows + 1) / rows) - 2.0
        kx = 2.0 * np.cos(np.pi * np.arange(1, cols + 1) / cols) - 2.0
    else:
        ky = 2.0 * np.cos(2.0 * np.pi * np.arange(rows) / rows) - 2.0
        kx = 2.0 * np.cos(2.0 * np.pi * np.arange(cols // 2 + 1) / cols) - 2.0
    denom = ky[:, None] + kx[None, :]
    if solver in ("dct", "fft"):
        denom[0, 0] = 1.0
    return denom.astype(np.float32)


def reference_integrate(gx: np.ndarray, gy: np.ndarray, pitch_mm: float,
                        solver: str = "dst") -> np.ndarray:
    """Least-squares height of the slopes (float32), as ``PoissonSolver.integrate`` was."""
    px = gx.astype(np.float32, copy=False) * np.float32(pitch_mm)
    py = gy.astype(np.float32, copy=False) * np.float32(pitch_mm)
    div = reference_divergence(px, py, solver)
    denom = _denominator(gx.shape, solver)
    if solver == "dct":
        spec = sfft.dctn(div, type=2, workers=1)
        spec /= denom
        spec[0, 0] = 0.0
        height = sfft.idctn(spec, type=2, workers=1)
    elif solver == "dst":
        spec = sfft.dstn(div, type=2, workers=1)
        spec /= denom
        height = sfft.idstn(spec, type=2, workers=1)
    else:
        spec = sfft.rfft2(div, workers=1)
        spec /= denom
        spec[0, 0] = 0.0
        height = sfft.irfft2(spec, s=gx.shape, workers=1)
    return np.asarray(height, dtype=np.float32)


def reference_zero_level(height: np.ndarray, pitch_mm: float, mode: str = "plane",
                         contact_threshold_mm: float = 0.03,
                         zero_exclusion_mm: float = 1.0) -> np.ndarray:
    """Height minus the zero level (plane/median through the undeformed gel), float32."""
    import cv2

    if mode == "none":
        return height
    step = max(1, min(height.shape) // 60)
    base = float(np.median(height[::step, ::step]))
    raised = ((height - base) > contact_threshold_mm).astype(np.uint8)
    radius_px = round(zero_exclusion_mm / pitch_mm)
    if radius_px > 0:
        kernel = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
        raised = np.asarray(cv2.dilate(raised, kernel), np.uint8)
    free = raised[::step, ::step] == 0
    sub = height[::step, ::step]
    if free.sum() < 10:
        return height - np.float32(base)
    if mode == "median":
        return height - np.float32(np.median(sub[free]))
    rows, cols = np.nonzero(free)
    design = np.stack([np.ones(len(rows)), cols * step, rows * step], axis=1)
    coef, *_ = np.linalg.lstsq(design, sub[free].astype(np.float64), rcond=None)
    r = np.arange(height.shape[0], dtype=np.float32)[:, None]
    c = np.arange(height.shape[1], dtype=np.float32)[None, :]
    plane = np.float32(coef[0]) + np.float32(coef[1]) * c + np.float32(coef[2]) * r
    return (height - plane).astype(np.float32, copy=False)


def reference_height_map(rec: Reconstructor, frame_rgb: np.ndarray,
                         background: np.ndarray | None = None) -> HeightMap:
    """``rec.height_map(frame_rgb, background)`` at full resolution, the pre-speed-up way."""
    pitch_mm = rec.calibration.mm_per_px
    gx, gy, has_contact = reference_slopes(rec, frame_rgb, background)
    if not has_contact:
        return HeightMap(np.zeros(gx.shape, np.float32), np.zeros(gx.shape, bool), pitch_mm,
                         skipped=True)
    s = rec.settings
    height = reference_integrate(gx, gy, pitch_mm, s.solver)
    height = reference_zero_level(height, pitch_mm, s.zero_level, s.contact_threshold_mm,
                                  s.zero_exclusion_mm)
    if not np.isfinite(height).all():
        raise InputDataError("reconstruction produced non-finite heights")
    return HeightMap(height, height > s.contact_threshold_mm, pitch_mm, skipped=False)
