"""Photometric features: brightness-normalised relative colour change from the background.

The sensor's lights and camera drift between the background frame and a press (auto
exposure, LED warm-up). A per-channel gain ``g_c`` is estimated robustly on the pixels that
did not change (median ratio frame/background, refined once after dropping changed pixels)
and the feature is the relative change ``100 * (I_c / (g_c * B_c) - 1)`` in percent,
optionally smoothed. Dividing by the background also removes most of the per-pixel
illumination falloff (vignetting), so a model fitted on one unit transfers better; the
residual position dependence is left to the model (it gets the normalised pixel position).
"""

from __future__ import annotations

import numpy as np

from remote_site.reconstruction.kernels import change_kernel, ratio_kernel, unchanged_kernel
from shared.errors import InputDataError

__all__ = ["brightness_gain", "pixel_position", "relative_change", "row_medians"]

#: pixels whose ratio differs from the first gain estimate by more than this are "changed"
_GAIN_TOLERANCE = 0.05
#: largest subsampling step of the robust statistics (speed: 1/16 of a 320x240 frame's pixels;
#: smaller frames, e.g. pooled ones, use every pixel)
_STAT_STEP = 4


def brightness_gain(frame: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Per-channel gain that best maps the background onto the unchanged part of a frame.

    The median ratio frame/background on a subsample, refined once on the pixels within
    ``_GAIN_TOLERANCE`` of it (compiled ratio and selection passes, medians by sort;
    ``lab/reconstruction_reference.py`` has the numpy form, with the same result).

    Args:
        frame: float32 (H, W, 3), validated.
        background: float32 (H, W, 3), validated, same shape.

    Returns:
        float32 array of 3 gains.

    Raises:
        InputDataError: the gain is not finite or implausible (< 0.2 or > 5): the frame and
            background are not from the same sensor/lighting.
    """
    step = max(1, min(_STAT_STEP, min(frame.shape[:2]) // 60))
    ratio = ratio_kernel(np.asarray(frame, np.float32), np.asarray(background, np.float32), step)
    gain = row_medians(ratio)
    unchanged = unchanged_kernel(ratio, gain, _GAIN_TOLERANCE)
    if unchanged.shape[1] >= 0.1 * ratio.shape[1]:
        gain = row_medians(unchanged)
    if not (np.isfinite(gain).all() and (gain > 0.2).all() and (gain < 5.0).all()):
        raise InputDataError(f"brightness gain {gain} between frame and background is "
                             "implausible: is the background from this sensor?")
    return gain.astype(np.float32)


def row_medians(values: np.ndarray) -> np.ndarray:
    """Median of each row of a 2-D array with n >= 1 columns, equal to
    ``np.median(values, axis=1)``, through numpy's vectorised sort (several times faster than
    its selection on these sizes, which are full of ties)."""
    ordered = np.sort(values, axis=1)
    n = ordered.shape[1]
    if n % 2:
        return ordered[:, n // 2].copy()
    return (ordered[:, n // 2 - 1] + ordered[:, n // 2]) / np.float32(2.0)


def inverse_background_pct(background: np.ndarray) -> np.ndarray:
    """``100 / max(background, 1)`` as float32: cache it per background (saves a division)."""
    return (100.0 / np.maximum(background, 1.0)).astype(np.float32)


def relative_change(frame: np.ndarray, background: np.ndarray,
                    blur_sigma_px: float = 1.0,
                    inv_background_pct: np.ndarray | None = None,
                    out: np.ndarray | None = None, work: np.ndarray | None = None
                    ) -> np.ndarray:
    """Brightness-normalised relative colour change in percent, (H, W, 3) float32.

    Args:
        frame: float32 (H, W, 3), validated.
        background: float32 (H, W, 3), validated, same shape.
        blur_sigma_px: Gaussian smoothing of the change (0 = none).
        inv_background_pct: :func:`inverse_background_pct` of ``background`` if cached.
        out, work: float32 (H, W, 3) scratch arrays to reuse for the result and (when
            blurring) the unblurred change; new arrays if None (or, for the unblurred
            change, not C-contiguous float32 of that shape).
    """
    import cv2

    gain = brightness_gain(frame, background)
    if inv_background_pct is None:
        inv_background_pct = inverse_background_pct(background)
    # 100 * (I / (g * B) - 1) in one fused pass (same float32 operations as
    # frame * (1 / g) * inv_background_pct - 100)
    shape = (*frame.shape[:2], 3)
    change = work if blur_sigma_px > 0 else out
    if change is None or change.shape != shape or change.dtype != np.float32 \
            or not change.flags.c_contiguous:  # the kernel loops over flat arrays
        change = np.empty(shape, np.float32)
    change_kernel(np.ascontiguousarray(frame, np.float32), (1.0 / gain).astype(np.float32),
                  np.ascontiguousarray(inv_background_pct, np.float32), change)
    if blur_sigma_px > 0:
        if out is None:
            return np.asarray(cv2.GaussianBlur(change, (0, 0), blur_sigma_px))
        cv2.GaussianBlur(change, (0, 0), blur_sigma_px, dst=out)
        return out
    return change


def pixel_position(shape_hw: tuple[int, int], rows: np.ndarray | None = None,
                   cols: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pixel position in [-0.5, 0.5] (x along columns, y along rows).

    Normalising by the frame size lets the same model serve any resolution of the sensor.
    With ``rows``/``cols`` given, returns positions of those pixels only (fractional
    indices allowed, e.g. centres of pooled blocks).
    """
    h, w = shape_hw
    if rows is None or cols is None:
        rows, cols = np.mgrid[0:h, 0:w]
    x = (np.asarray(cols, np.float32) + 0.5) / w - 0.5
    y = (np.asarray(rows, np.float32) + 0.5) / h - 0.5
    return x, y
