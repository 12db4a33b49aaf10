"""Frame loading and validation: the gate every sensor image passes before any arithmetic.

A frame is an RGB image, ``(H, W, 3)``, ``uint8`` (or a float array with values in
[0, 255]). Images on disk are read with OpenCV and converted from BGR to RGB once, here.
Rejected (:class:`~shared.errors.InputDataError`): wrong rank/shape/dtype, NaN/Inf,
values outside [0, 255], frames that are mostly saturated or mostly black (no
photometric information is left in them).

:func:`check_image_content` is the reconstructor's second gate, for a frame about to be
integrated: a frame that passes the checks above but holds no image of the gel (a uniform
frame, as a USB camera sends while it resyncs; pure noise, a corrupted transfer) is refused
instead of being read as slopes everywhere.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from remote_site.reconstruction.kernels import clipped_counts
from shared.errors import InputDataError

__all__ = [
    "BLACK_LEVEL",
    "MAX_CLIPPED_FRACTION",
    "MAX_NOISE_FRACTION",
    "MIN_SHADING_RATIO",
    "NOISE_STEP_DN",
    "SATURATION_LEVEL",
    "check_image_content",
    "load_rgb",
    "shading",
    "validate_frame",
]

log = logging.getLogger(__name__)

#: a channel value at or above this counts as saturated
SATURATION_LEVEL = 254.5
#: a pixel whose channels are all at or below this counts as black
BLACK_LEVEL = 3.0
#: a frame with more than this fraction of clipped (saturated or black) pixels is rejected
MAX_CLIPPED_FRACTION = 0.25
#: a frame whose shading (:func:`shading`) is below this share of the background's in some
#: channel shows no image of the gel: its LEDs and lens always shade the frame (the real
#: GelSight Mini frames keep >= 0.97 of their background's, a uniform frame has 0)
MIN_SHADING_RATIO = 0.5
#: horizontally neighbouring pixels (a sample of them) differing by more than this many grey
#: levels in one channel ...
NOISE_STEP_DN = 20.0
#: ... in more than this share of the pairs: the frame is noise, not an image (an image of the
#: gel is smooth at the pixel scale: <= 0.33 % of pairs on the kit's real GelSight Mini frames,
#: 84 % on uniform noise; 50 % would take a camera noise of ~20 grey levels rms, 10x the Mini's)
MAX_NOISE_FRACTION = 0.5


def validate_frame(frame: object, expected_hw: tuple[int, int] | None = None,
                   name: str = "frame", out: np.ndarray | None = None) -> np.ndarray:
    """Check a camera/simulator frame and return it as a float32 (H, W, 3) array.

    Args:
        frame: RGB image, ``uint8`` or float in [0, 255].
        expected_hw: required (rows, cols), e.g. the calibration's shape; None to skip.
        name: used in error messages (file name, "background", ...).
        out: a float32 array of the frame's shape to write the result into (reused scratch
            memory); a new array if None or of another shape.

    Returns:
        float32 array (H, W, 3), values in [0, 255] (``out`` when it was used).

    Raises:
        InputDataError: wrong type, shape or dtype; NaN/Inf; out-of-range values; a frame
            that is mostly saturated or mostly black.
    """
    if not isinstance(frame, np.ndarray):
        raise InputDataError(f"{name}: expected a numpy array, got {type(frame).__name__}")
    if frame.ndim != 3 or frame.shape[2] != 3:
        raise InputDataError(f"{name}: expected an (H, W, 3) RGB image, got shape {frame.shape}")
    if frame.shape[0] < 8 or frame.shape[1] < 8:
        raise InputDataError(f"{name}: image {frame.shape[:2]} is too small (min 8 x 8)")
    if expected_hw is not None and tuple(frame.shape[:2]) != tuple(expected_hw):
        raise InputDataError(f"{name}: size {frame.shape[1]}x{frame.shape[0]} (W x H) does not "
                             f"match the calibration's {expected_hw[1]}x{expected_hw[0]}")
    if frame.dtype != np.uint8 and not np.issubdtype(frame.dtype, np.floating):
        raise InputDataError(f"{name}: dtype {frame.dtype} not supported (uint8 or float)")
    if out is None or out.shape != frame.shape or out.dtype != np.float32:
        out = frame.astype(np.float32)
    else:
        np.copyto(out, frame, casting="unsafe")  # the same conversion as astype(float32)
    if frame.dtype != np.uint8:
        if not np.isfinite(out).all():
            raise InputDataError(f"{name}: contains NaN or Inf")
        if out.min() < 0.0 or out.max() > 255.0:
            raise InputDataError(f"{name}: float values must lie in [0, 255], got "
                                 f"[{out.min():.3g}, {out.max():.3g}]")
    # on every 4th pixel of every 4th row (one compiled pass; fractions as np.mean gives them)
    n_saturated, n_black, n_sub = clipped_counts(out, 4, np.float32(SATURATION_LEVEL),
                                                 np.float32(BLACK_LEVEL))
    saturated, black = n_saturated / n_sub, n_black / n_sub
    if saturated > MAX_CLIPPED_FRACTION:
        raise InputDataError(f"{name}: {saturated:.0%} of pixels are saturated (exposure too "
                             "high or lights too bright)")
    if black > MAX_CLIPPED_FRACTION:
        raise InputDataError(f"{name}: {black:.0%} of pixels are black (camera covered, lights "
                             "off or a dropped frame)")
    return out


def shading(image: np.ndarray) -> np.ndarray:
    """Per-channel coefficient of variation (std / mean) of an (H, W, 3) image, on every 8th
    pixel of every 8th row: how much the illumination and the scene shade it, independent of
    the exposure (3 float values; 0 for a uniform image)."""
    import cv2

    sample = np.ascontiguousarray(np.asarray(image, np.float32)[4::8, 4::8])
    mean, std = cv2.meanStdDev(sample)  # per channel, one pass
    return (std[:, 0] / np.maximum(mean[:, 0], 1.0)).astype(np.float32)


def check_image_content(frame: np.ndarray, background_shading: np.ndarray,
                        name: str = "frame") -> None:
    """Refuse a validated frame that holds no image of the gel.

    Args:
        frame: float32 (H, W, 3), validated (:func:`validate_frame`).
        background_shading: :func:`shading` of the background it is compared with.
        name: used in the error message.

    Raises:
        InputDataError: the frame is uniform (less than ``MIN_SHADING_RATIO`` of the
            background's shading in a channel) or noise (more than ``MAX_NOISE_FRACTION`` of
            sampled neighbouring pixels differ by more than ``NOISE_STEP_DN``).
    """
    own = shading(frame)
    for c, channel in enumerate("RGB"):
        if own[c] < MIN_SHADING_RATIO * background_shading[c]:
            raise InputDataError(
                f"{name}: uniform in {channel} (shading {own[c]:.3f} against the "
                f"background's {background_shading[c]:.3f}): no image of the gel (a camera "
                "resyncing, a placeholder frame or the lens covered?)")
    left, right = frame[::8, 0:-1:4], frame[::8, 1::4]
    pairs = left.shape[0] * left.shape[1]
    for c, channel in enumerate("RGB"):
        noisy = np.count_nonzero(np.abs(left[..., c] - right[..., c]) > NOISE_STEP_DN) / pairs
        if noisy > MAX_NOISE_FRACTION:
            raise InputDataError(
                f"{name}: noise, not an image ({noisy:.0%} of neighbouring pixels differ by "
                f"more than {NOISE_STEP_DN:g} grey levels in {channel}: a corrupted frame?)")


def load_rgb(path: str | os.PathLike[str]) -> np.ndarray:
    """Read an image file as an RGB ``uint8`` array.

    Raises:
        InputDataError: the file is missing or is not a readable 3-channel image.
    """
    import cv2

    if not os.path.isfile(path):
        raise InputDataError(f"image not found: {path}")
    bgr = cv2.imread(os.fspath(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputDataError(f"not a readable image: {path}")
    return np.ascontiguousarray(bgr[:, :, ::-1])
