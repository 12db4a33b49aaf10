"""Calibration of the *simulated* sensor, made exactly like a real one (ball presses).

The demo needs a calibration for ``open_sensor("sim")``. It ships as package data,
``remote_site/sensor/data/sim_calib.npz`` (about 50 kB), regenerated with::

    python -m remote_site.sensor.sim_calibration

which renders ``n_presses`` presses of a 4 mm ball at random positions and depths with the
default :class:`~remote_site.sensor.photometric.PhotometricSettings` and fits the default
(polynomial) model with :func:`~remote_site.reconstruction.calibration.fit_calibration`.
:func:`simulated_calibration` loads the shipped file, or, if it is missing or was made
for other settings (shape/scale mismatch), computes one in about a second.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np

from remote_site.reconstruction.calibration import Calibration, fit_calibration
from remote_site.reconstruction.labels import BallLabel
from remote_site.sensor.photometric import PhotometricModel, PhotometricSettings
from remote_site.sensor.shapes import ball_depth_mm
from shared.errors import CalibrationError

__all__ = ["SIM_CALIBRATION_PATH", "calibrate_simulator", "render_ball_presses",
           "simulated_calibration"]

log = logging.getLogger(__name__)

SIM_CALIBRATION_PATH = Path(__file__).resolve().parent / "data" / "sim_calib.npz"
SIM_BALL_DIAMETER_MM = 4.0


def render_ball_presses(model: PhotometricModel, n_presses: int, ball_diameter_mm: float,
                        seed: int = 0, depth_range_mm: tuple[float, float] = (0.15, 0.6),
                        ) -> list[tuple[np.ndarray, BallLabel]]:
    """Render ``n_presses`` ball presses with their exact contact-circle labels."""
    rng = np.random.default_rng(seed)
    rows, cols = model.settings.shape_hw
    pitch = model.settings.mm_per_px
    radius_mm = ball_diameter_mm / 2.0
    presses = []
    for i in range(n_presses):
        cx, cy = rng.uniform(0.15, 0.85) * cols, rng.uniform(0.15, 0.85) * rows
        depth = float(rng.uniform(*depth_range_mm))
        contact_px = np.sqrt(radius_mm**2 - (radius_mm - depth) ** 2) / pitch
        frame = model.render(ball_depth_mm((rows, cols), pitch, cx, cy, radius_mm, depth))
        presses.append((frame, BallLabel(f"sim_press_{i:02d}.png", cx, cy, contact_px)))
    return presses


def calibrate_simulator(settings: PhotometricSettings | None = None, n_presses: int = 24,
                        seed: int = 0) -> Calibration:
    """Calibrate a simulated sensor from its own rendered ball presses (about 1 s)."""
    model = PhotometricModel(settings, seed=seed)
    presses = render_ball_presses(model, n_presses, SIM_BALL_DIAMETER_MM, seed=seed)
    # the rendered labels are exact: moving them to the contact edge would only add the edge
    # fit's own error (0.03-0.07 px here), and the shipped file is this call's output
    return fit_calibration(model.background_rgb, presses, SIM_BALL_DIAMETER_MM,
                           model.settings.mm_per_px, trim_px=2.0, centres="label")


def simulated_calibration(settings: PhotometricSettings | None = None) -> Calibration:
    """The calibration for the simulated sensor: shipped file if it fits, else computed."""
    settings = settings or PhotometricSettings()
    if settings == PhotometricSettings() and SIM_CALIBRATION_PATH.is_file():
        try:
            calib = Calibration.load(SIM_CALIBRATION_PATH)
            if calib.shape_hw == settings.shape_hw and np.isclose(calib.mm_per_px,
                                                                  settings.mm_per_px):
                return calib
            log.warning("shipped simulator calibration does not match; recomputing")
        except CalibrationError as err:
            log.warning("shipped simulator calibration unusable (%s); recomputing", err)
    return calibrate_simulator(settings)


def main() -> int:
    """Regenerate the shipped simulator calibration."""
    logging.basicConfig(level=logging.INFO)
    SIM_CALIBRATION_PATH.parent.mkdir(parents=True, exist_ok=True)
    calibrate_simulator().save(SIM_CALIBRATION_PATH)
    log.info("wrote %s (%d bytes)", SIM_CALIBRATION_PATH, SIM_CALIBRATION_PATH.stat().st_size)
    return 0


if __name__ == "__main__":
    sys.exit(main())
