"""Fused per-pixel shading kernel of the photometric model (numba, one pass over the frame).

For a gel surface ``h`` (mm) the pixel colour of channel ``c`` is

    I_c = base_c + sum_k coef_kc * max(lz_k - lx_k h_x - ly_k h_y, 0) / sqrt(1 + h_x^2 + h_y^2)

plus camera noise, rounded and clipped to uint8, where the static per-pixel terms ``base``
and ``coef`` fold the background, markers, brightness, light colours and shading gain
(see :class:`~remote_site.sensor.photometric.PhotometricModel`). The slopes ``h_x``, ``h_y``
follow :func:`numpy.gradient` (central differences inside, one-sided at the border). One
fused loop replaces ~25 full-frame numpy passes (the frame stays in cache).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["finish_frame", "shade_frame", "shaded_values"]


@njit(cache=True, nogil=True, inline="always", error_model="numpy", fastmath=True)
def _pixel(gx: float, gy: float, i: int, j: int, base: np.ndarray, coef: np.ndarray,
           lights: np.ndarray, noise: np.ndarray, use_noise: bool, gain: np.ndarray,
           use_gain: bool, out: np.ndarray) -> None:  # pragma: no cover - compiled
    zero = np.float32(0.0)
    norm = np.float32(1.0) / np.sqrt(np.float32(1.0) + gx * gx + gy * gy)
    s0 = max(lights[0, 2] - lights[0, 0] * gx - lights[0, 1] * gy, zero) * norm
    s1 = max(lights[1, 2] - lights[1, 0] * gx - lights[1, 1] * gy, zero) * norm
    s2 = max(lights[2, 2] - lights[2, 0] * gx - lights[2, 1] * gy, zero) * norm
    for c in range(3):
        value = base[i, j, c] + coef[i, j, 0, c] * s0 + coef[i, j, 1, c] * s1 \
            + coef[i, j, 2, c] * s2
        if use_noise:
            value += noise[i, j, c]
        value = np.floor(value + np.float32(0.5))
        out[i, j, c] = _gained(min(max(value, zero), np.float32(255.0)), gain, c, use_gain)


@njit(cache=True, nogil=True, inline="always", error_model="numpy", fastmath=True)
def _gained(value: float, gain: np.ndarray, c: int,
            use_gain: bool) -> np.uint8:  # pragma: no cover - compiled
    # the LED brightness gain on the 8-bit value as cv2.multiply(frame, gain, dtype=CV_8U)
    # applies it: in double precision, rounded half to even, saturated
    if not use_gain:
        return np.uint8(value)
    scaled = np.rint(np.float64(value) * gain[c])
    return np.uint8(min(max(scaled, 0.0), 255.0))


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _flat_values(base: np.ndarray, coef: np.ndarray, lights: np.ndarray,
                 out: np.ndarray) -> None:  # pragma: no cover - compiled
    # _pixel with zero slopes (norm 1), before noise and rounding
    zero = np.float32(0.0)
    s0 = max(lights[0, 2], zero)
    s1 = max(lights[1, 2], zero)
    s2 = max(lights[2, 2], zero)
    rows, cols = base.shape[0], base.shape[1]
    for i in range(rows):
        for j in range(cols):
            for c in range(3):
                out[i, j, c] = base[i, j, c] + coef[i, j, 0, c] * s0 \
                    + coef[i, j, 1, c] * s1 + coef[i, j, 2, c] * s2


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _finish(values: np.ndarray, noise: np.ndarray, gain: np.ndarray, use_gain: bool,
            out: np.ndarray) -> None:  # pragma: no cover - compiled
    zero = np.float32(0.0)
    rows, cols = values.shape[0], values.shape[1]
    for i in range(rows):
        for j in range(cols):
            for c in range(3):
                value = np.floor(values[i, j, c] + noise[i, j, c] + np.float32(0.5))
                out[i, j, c] = _gained(min(max(value, zero), np.float32(255.0)), gain, c,
                                       use_gain)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _shade(surface: np.ndarray, inv_pitch: float, base: np.ndarray, coef: np.ndarray,
           lights: np.ndarray, noise: np.ndarray, use_noise: bool, gain: np.ndarray,
           use_gain: bool, out: np.ndarray) -> None:  # pragma: no cover - compiled
    rows, cols = surface.shape
    half = np.float32(0.5 * inv_pitch)
    full = np.float32(inv_pitch)
    for i in range(rows):
        # numpy.gradient: central differences inside, one-sided at the border
        up = min(i + 1, rows - 1)
        down = max(i - 1, 0)
        scale_y = half if (up - down) == 2 else full
        left_gx = (surface[i, 1] - surface[i, 0]) * full
        _pixel(left_gx, (surface[up, 0] - surface[down, 0]) * scale_y, i, 0, base, coef,
               lights, noise, use_noise, gain, use_gain, out)
        for j in range(1, cols - 1):
            gx = (surface[i, j + 1] - surface[i, j - 1]) * half
            gy = (surface[up, j] - surface[down, j]) * scale_y
            _pixel(gx, gy, i, j, base, coef, lights, noise, use_noise, gain, use_gain, out)
        last = cols - 1
        right_gx = (surface[i, last] - surface[i, last - 1]) * full
        _pixel(right_gx, (surface[up, last] - surface[down, last]) * scale_y, i, last, base,
               coef, lights, noise, use_noise, gain, use_gain, out)


def shade_frame(surface_mm: np.ndarray, pitch_mm: float, base: np.ndarray, coef: np.ndarray,
                lights: np.ndarray, noise: np.ndarray | None,
                gain: np.ndarray | None = None) -> np.ndarray:
    """Shade one frame (see the module docstring for the formula).

    Rounding is half-up (``floor(v + 0.5)``) where numpy's ``rint`` rounds half to even: the
    two differ only for values exactly on .5, which float32 sums practically never hit.

    Args:
        surface_mm: (H, W) float32 gel surface.
        pitch_mm: pixel pitch (mm), > 0.
        base: (H, W, 3) float32 static colour of flat gel minus the lit part.
        coef: (H, W, 3 lights, 3 channels) float32 static shading weights.
        lights: (3, 3) float32 unit light directions (x, y, z) per light.
        noise: (H, W, 3) float32 camera noise, or None.
        gain: per-channel brightness gain applied to the 8-bit frame (as
            ``cv2.multiply(frame, gain, dtype=cv2.CV_8U)``: double precision, rounded half to
            even, saturated), or None.

    Returns:
        (H, W, 3) uint8 frame.
    """
    rows, cols = surface_mm.shape
    out = np.empty((rows, cols, 3), np.uint8)
    surface = np.ascontiguousarray(surface_mm, dtype=np.float32)
    use_noise = noise is not None
    noise_arr = noise if noise is not None else np.zeros((1, 1, 3), np.float32)
    gain_arr = _gain_array(gain)
    _shade(surface, float(1.0 / pitch_mm), base, coef, lights, noise_arr, use_noise, gain_arr,
           gain is not None, out)
    return out


def _gain_array(gain: np.ndarray | None) -> np.ndarray:
    return np.ones(3) if gain is None else np.asarray(gain, np.float64).reshape(3)


def shaded_values(base: np.ndarray, coef: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """The colour of the flat gel (zero slopes) before noise and rounding, (H, W, 3) float32.

    :func:`finish_frame` of these values with a frame's noise gives the frame
    :func:`shade_frame` renders for a flat surface with that noise (the same float32
    arithmetic, so equal except where the two compilations round a sum differently in its
    last bit and the value then lies on the .5 between two digital numbers: practically never).
    """
    out = np.empty(base.shape, np.float32)
    _flat_values(base, coef, lights, out)
    return out


def finish_frame(values: np.ndarray, noise: np.ndarray | None,
                 gain: np.ndarray | None = None) -> np.ndarray:
    """``values`` (H, W, 3 float32) plus ``noise``, rounded half-up and clipped to uint8, then
    ``gain`` applied as in :func:`shade_frame`."""
    out = np.empty(values.shape, np.uint8)
    noise_arr = noise if noise is not None else np.zeros(values.shape, np.float32)
    _finish(values, noise_arr, _gain_array(gain), gain is not None, out)
    return out
