"""Fused per-pixel shading kernel of the photometric model (numba, one pass over the frame).

For a gel surface ``h`` (mm) the pixel colour of channel ``c`` is

    I_c = A_c * (w0_c + sum_k W_kc * max(lz_k - lx_k h_x - ly_k h_y, 0) / sqrt(1 + h_x^2 + h_y^2))

plus camera noise, rounded and clipped to uint8, where the per-pixel albedo ``A`` folds the
background, markers and brightness, and the nine weights ``W`` and three ``w0`` the light
colours and shading gain (see :class:`~remote_site.sensor.photometric.PhotometricModel`).
The slopes ``h_x``, ``h_y`` follow :func:`numpy.gradient` (central differences inside,
one-sided at the border).

The frame is done a row at a time in short loops over contiguous memory, which the
compiler turns into vector instructions: the row's slopes, the three lights' terms per
pixel, the colour of each pixel's three channels, then noise, rounding and the brightness
gain. The one static image read per frame is the albedo (H x W x 3 float32). The earlier
kernel went pixel by pixel with the channels innermost, read a static colour and nine
weights per pixel, and applied the gain with its branch inside; the shading alone took
about 5x as long warm (786 against 159 us for a pressed 320 x 240 frame with the LED gain),
the whole render step 2.9x (``benchmarks/bench_sim_sensor.py``). Flat and pressed frames
are finished by the same row function, and the flat gel's cached values
(:func:`shaded_values`) by the same row arithmetic as the full shading of a flat surface,
whose slopes are exactly zero: the bytes are equal (checked on noisy frames with a gain;
both are compiled from the same source, so equal instruction choices are expected, not
guaranteed by the compiler).

The kernels do not check bounds: the public functions check the shapes first.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["finish_frame", "shade_frame", "shaded_values"]


@njit(cache=True, nogil=True, inline="always", error_model="numpy", fastmath=True)
def _row_values(surface: np.ndarray, i: int, half: np.float32, full: np.float32,
                albedo: np.ndarray, weights: np.ndarray, lights: np.ndarray,
                scratch: np.ndarray, values: np.ndarray) -> None:  # pragma: no cover - compiled
    """Row ``i``'s colour values before noise: ``values`` (cols * 3,) float32. ``albedo``
    (rows, cols * 3); ``weights`` (4, 3): ``w0`` then each light's ``W``; ``scratch``
    (4, cols) float32."""
    rows, cols = surface.shape
    zero = np.float32(0.0)
    one = np.float32(1.0)
    up = min(i + 1, rows - 1)
    down = max(i - 1, 0)
    scale_y = half if (up - down) == 2 else full
    row = surface[i]
    row_up = surface[up]
    row_down = surface[down]
    # numpy.gradient along the row: central differences inside, one-sided at the ends
    gx = scratch[3]
    gx[0] = (row[1] - row[0]) * full
    gx[cols - 1] = (row[cols - 1] - row[cols - 2]) * full
    for j in range(1, cols - 1):
        gx[j] = (row[j + 1] - row[j - 1]) * half
    # each light's term per pixel
    l00, l01, l02 = lights[0, 0], lights[0, 1], lights[0, 2]
    l10, l11, l12 = lights[1, 0], lights[1, 1], lights[1, 2]
    l20, l21, l22 = lights[2, 0], lights[2, 1], lights[2, 2]
    s0 = scratch[0]
    s1 = scratch[1]
    s2 = scratch[2]
    for j in range(cols):
        x = gx[j]
        y = (row_up[j] - row_down[j]) * scale_y
        norm = one / np.sqrt(one + x * x + y * y)
        s0[j] = max(l02 - l00 * x - l01 * y, zero) * norm
        s1[j] = max(l12 - l10 * x - l11 * y, zero) * norm
        s2[j] = max(l22 - l20 * x - l21 * y, zero) * norm
    # the three channels of every pixel (spelled out: the compiler vectorizes this form)
    b0, b1, b2 = weights[0, 0], weights[0, 1], weights[0, 2]
    m00, m01, m02 = weights[1, 0], weights[1, 1], weights[1, 2]
    m10, m11, m12 = weights[2, 0], weights[2, 1], weights[2, 2]
    m20, m21, m22 = weights[3, 0], weights[3, 1], weights[3, 2]
    a = albedo[i]
    for j in range(cols):
        a0 = s0[j]
        a1 = s1[j]
        a2 = s2[j]
        k = 3 * j
        values[k] = a[k] * (b0 + m00 * a0 + m10 * a1 + m20 * a2)
        values[k + 1] = a[k + 1] * (b1 + m01 * a0 + m11 * a1 + m21 * a2)
        values[k + 2] = a[k + 2] * (b2 + m02 * a0 + m12 * a1 + m22 * a2)


@njit(cache=True, nogil=True, inline="always", error_model="numpy", fastmath=True)
def _row_finish(values: np.ndarray, noise: np.ndarray, use_noise: bool, gain: np.ndarray,
                out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``values`` plus ``noise``, rounded half-up and clipped to 0-255, then ``gain`` (per
    value, float64) applied as ``cv2.multiply(frame, gain, dtype=cv2.CV_8U)`` does: in double
    precision, rounded half to even, saturated. A gain of 1 leaves the rounded value as it
    is (an integer times 1.0 is exact)."""
    zero = np.float32(0.0)
    top = np.float32(255.0)
    half = np.float32(0.5)
    if use_noise:
        for k in range(values.shape[0]):
            v = min(max(np.floor(values[k] + noise[k] + half), zero), top)
            out[k] = np.uint8(min(max(np.rint(np.float64(v) * gain[k]), 0.0), 255.0))
    else:
        for k in range(values.shape[0]):
            v = min(max(np.floor(values[k] + half), zero), top)
            out[k] = np.uint8(min(max(np.rint(np.float64(v) * gain[k]), 0.0), 255.0))


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _shade(surface: np.ndarray, inv_pitch: float, albedo: np.ndarray, weights: np.ndarray,
           lights: np.ndarray, noise: np.ndarray, use_noise: bool, gain: np.ndarray,
           out: np.ndarray) -> None:  # pragma: no cover - compiled
    rows, cols = surface.shape
    half = np.float32(0.5 * inv_pitch)
    full = np.float32(inv_pitch)
    scratch = np.empty((4, cols), np.float32)
    values = np.empty(3 * cols, np.float32)
    for i in range(rows):
        _row_values(surface, i, half, full, albedo, weights, lights, scratch, values)
        _row_finish(values, noise[i], use_noise, gain, out[i])


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _values(surface: np.ndarray, inv_pitch: float, albedo: np.ndarray, weights: np.ndarray,
            lights: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    rows, cols = surface.shape
    half = np.float32(0.5 * inv_pitch)
    full = np.float32(inv_pitch)
    scratch = np.empty((4, cols), np.float32)
    for i in range(rows):
        _row_values(surface, i, half, full, albedo, weights, lights, scratch, out[i])


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _finish(values: np.ndarray, noise: np.ndarray, use_noise: bool, gain: np.ndarray,
            out: np.ndarray) -> None:  # pragma: no cover - compiled
    for i in range(values.shape[0]):
        _row_finish(values[i], noise[i], use_noise, gain, out[i])


def shade_frame(surface_mm: np.ndarray, pitch_mm: float, albedo: np.ndarray,
                weights: np.ndarray, lights: np.ndarray, noise: np.ndarray | None,
                gain: np.ndarray | None = None) -> np.ndarray:
    """Shade one frame (see the module docstring for the formula).

    Rounding is half-up (``floor(v + 0.5)``) where numpy's ``rint`` rounds half to even: the
    two differ only for values exactly on .5, which float32 sums practically never hit.

    Args:
        surface_mm: (H, W) float32 gel surface.
        pitch_mm: pixel pitch (mm), > 0.
        albedo: (H, W, 3) float32 C-contiguous static colour of the lit flat gel.
        weights: (4, 3) float32: the channels' constant term ``w0``, then each light's
            weights ``W`` (light, channel).
        lights: (3, 3) float32 unit light directions (x, y, z) per light.
        noise: (H, W, 3) float32 camera noise, or None.
        gain: per-channel brightness gain applied to the 8-bit frame (as
            ``cv2.multiply(frame, gain, dtype=cv2.CV_8U)``: double precision, rounded half to
            even, saturated), or None.

    Returns:
        (H, W, 3) uint8 frame.
    """
    rows, cols = surface_mm.shape
    _check_shapes((rows, cols), albedo, weights, lights, noise)
    out = np.empty((rows, cols, 3), np.uint8)
    surface = np.ascontiguousarray(surface_mm, dtype=np.float32)
    _shade(surface, float(1.0 / pitch_mm), _rows(albedo), weights, lights,
           _rows(_noise_or_zeros(noise, albedo.shape)), noise is not None,
           _gain_row(gain, cols), _rows(out))
    return out


def shaded_values(albedo: np.ndarray, weights: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """The colour of the flat gel (zero slopes) before noise and rounding, (H, W, 3) float32.

    :func:`finish_frame` of these values with a frame's noise gives the frame
    :func:`shade_frame` renders for a flat surface with that noise (see the module
    docstring).
    """
    rows, cols = albedo.shape[0], albedo.shape[1]
    _check_shapes((rows, cols), albedo, weights, lights, None)
    out = np.empty(albedo.shape, np.float32)
    _values(np.zeros((rows, cols), np.float32), 1.0, _rows(albedo), weights, lights, _rows(out))
    return out


def finish_frame(values: np.ndarray, noise: np.ndarray | None,
                 gain: np.ndarray | None = None) -> np.ndarray:
    """``values`` (H, W, 3 float32) plus ``noise``, rounded half-up and clipped to uint8, then
    ``gain`` applied as in :func:`shade_frame`."""
    _check_shapes(values.shape[:2], values, None, None, noise)
    out = np.empty(values.shape, np.uint8)
    _finish(_rows(values), _rows(_noise_or_zeros(noise, values.shape)), noise is not None,
            _gain_row(gain, values.shape[1]), _rows(out))
    return out


def _check_shapes(hw: tuple[int, ...], image: np.ndarray, weights: np.ndarray | None,
                  lights: np.ndarray | None, noise: np.ndarray | None) -> None:
    """The shapes the kernels index without bounds checks (ValueError otherwise)."""
    rows, cols = hw
    if rows < 1 or cols < 2:
        raise ValueError(f"a frame of {rows} x {cols} pixels cannot be shaded")
    for name, array, shape in (("image", image, (rows, cols, 3)), ("weights", weights, (4, 3)),
                               ("lights", lights, (3, 3)), ("noise", noise, (rows, cols, 3))):
        if array is not None and array.shape != shape:
            raise ValueError(f"{name} of shape {array.shape}, expected {shape}")


def _rows(image: np.ndarray) -> np.ndarray:
    """An (H, W, 3) array as (H, W * 3) rows (a view of a C-contiguous array)."""
    return image.reshape(image.shape[0], -1)


def _noise_or_zeros(noise: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    # without noise the kernels do not read it; a small stand-in keeps one compiled signature
    return noise if noise is not None else np.zeros((shape[0], 1, 3), np.float32)


def _gain_row(gain: np.ndarray | None, cols: int) -> np.ndarray:
    """The per-channel gain repeated for every pixel of a row (float64, cols * 3)."""
    g = np.ones(3) if gain is None else np.asarray(gain, np.float64).reshape(3)
    return np.tile(g, cols)
