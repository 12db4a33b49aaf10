"""Frame loading and validation: the gate every sensor image passes before any arithmetic.

A frame is an RGB image, ``(H, W, 3)``, ``uint8`` (or a float array with values in
[0, 255]). Images on disk are read with OpenCV and converted from BGR to RGB once, here.
Rejected (:class:`~shared.errors.InputDataError`): wrong rank/shape/dtype, NaN/Inf,
values outside [0, 255], frames that are mostly saturated or mostly black (no
photometric information is left in them).
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
    "SATURATION_LEVEL",
    "load_rgb",
    "validate_frame",
]

log = logging.getLogger(__name__)

#: a channel value at or above this counts as saturated
SATURATION_LEVEL = 254.5
#: a pixel whose channels are all at or below this counts as black
BLACK_LEVEL = 3.0
#: a frame with more than this fraction of clipped (saturated or black) pixels is rejected
MAX_CLIPPED_FRACTION = 0.25


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
