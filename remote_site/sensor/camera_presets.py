"""How a camera's raw image becomes a sensor frame: named crop / size presets.

A GelSight Mini's raw camera image shows the sensor housing at its border; like the vendor
SDK, ``mini-raw`` crops 1/7 of the height and of the width off each side and resizes the rest
to 320 x 240 (0.0634 mm/px). A recording of the Mini's *output* (what the SDK saves, e.g. the
kit's presses) is already cropped and sized: ``mini-recording`` takes it as it is and refuses
a frame of another size rather than rescaling it (scale and calibration would no longer
match).

A preset is only defaults: ``crop_fraction`` / ``out_hw`` / ``mm_per_px`` given to the camera
source override it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.errors import ConfigError, InputDataError

__all__ = ["CAMERA_PRESETS", "DEFAULT_PRESET", "GELSIGHT_MINI_MM_PER_PX", "CameraPreset",
           "camera_preset", "shape_frame"]

#: GelSight Mini at 320 x 240 after the standard crop
GELSIGHT_MINI_MM_PER_PX = 0.0634


@dataclass(frozen=True)
class CameraPreset:
    """Crop and size of the frames a camera source delivers.

    Attributes:
        name: the preset's name.
        crop_fraction: fraction of the height / width removed on each side (0 = none).
        out_hw: delivered (rows, cols).
        resize: resize the cropped image to ``out_hw``; False: the image must already have
            that size (a frame of another size is refused).
        mm_per_px: pixel pitch of the delivered frames on the gel.
    """

    name: str
    crop_fraction: float
    out_hw: tuple[int, int]
    resize: bool
    mm_per_px: float

    def __post_init__(self) -> None:
        if not 0.0 <= self.crop_fraction < 0.5:
            raise ConfigError(f"camera preset {self.name!r}: crop_fraction must lie in "
                              f"[0, 0.5), got {self.crop_fraction}")
        if len(self.out_hw) != 2 or min(self.out_hw) < 8:
            raise ConfigError(f"camera preset {self.name!r}: out_hw must be two sizes >= 8, "
                              f"got {self.out_hw}")
        if not (np.isfinite(self.mm_per_px) and self.mm_per_px > 0):
            raise ConfigError(f"camera preset {self.name!r}: mm_per_px must be > 0, got "
                              f"{self.mm_per_px}")


CAMERA_PRESETS: dict[str, CameraPreset] = {
    "mini-raw": CameraPreset("mini-raw", 1.0 / 7.0, (240, 320), True, GELSIGHT_MINI_MM_PER_PX),
    "mini-recording": CameraPreset("mini-recording", 0.0, (240, 320), False,
                                   GELSIGHT_MINI_MM_PER_PX),
}

#: the preset of a live camera (today's behaviour)
DEFAULT_PRESET = "mini-raw"


def camera_preset(name: str) -> CameraPreset:
    """The preset called ``name``.

    Raises:
        ConfigError: an unknown name.
    """
    try:
        return CAMERA_PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown camera preset {name!r}; known: "
                          f"{sorted(CAMERA_PRESETS)}") from None


def shape_frame(bgr: np.ndarray, preset: CameraPreset) -> np.ndarray:
    """Crop and (if the preset says so) resize a raw BGR frame; return it as RGB.

    Args:
        bgr: (H, W, 3) uint8 frame from OpenCV (BGR order).
        preset: crop and size to apply.

    Returns:
        (rows, cols, 3) uint8 RGB frame of ``preset.out_hw``.

    Raises:
        InputDataError: without resizing, the cropped frame does not have ``out_hw``.
    """
    h, w = bgr.shape[:2]
    top, left = int(h * preset.crop_fraction), int(w * preset.crop_fraction)
    cropped = bgr[top:h - top, left:w - left]
    rows, cols = preset.out_hw
    if cropped.shape[:2] != (rows, cols):
        if not preset.resize:
            raise InputDataError(f"frame is {cropped.shape[1]}x{cropped.shape[0]} after the "
                                 f"crop but preset {preset.name!r} delivers {cols}x{rows} "
                                 "without resizing (wrong preset for this source?)")
        import cv2

        cropped = cv2.resize(cropped, (cols, rows), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(cropped[:, :, ::-1])
