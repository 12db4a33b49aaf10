"""Calibrated GelSight-style reconstruction: frame -> slopes -> Poisson -> height map (mm).

Typical use::

    from remote_site.reconstruction import Reconstructor
    rec = Reconstructor.from_file("calib.npz")
    hm = rec.height_map(frame_rgb, out_pitch_mm=None)   # HeightMap(height_mm, mask, mm_per_px)

See :mod:`.calibration` for how a calibration is made and :mod:`.reconstructor` for the zero
level and the skips.
"""

from remote_site.reconstruction.calibration import CALIBRATION_VERSION, Calibration, fit_calibration
from remote_site.reconstruction.labels import BallLabel, read_labels_csv, write_labels_csv
from remote_site.reconstruction.poisson import PoissonSolver, integrate_gradients
from remote_site.reconstruction.reconstructor import (
    HeightMap,
    ReconstructionSettings,
    Reconstructor,
)

__all__ = [
    "CALIBRATION_VERSION",
    "BallLabel",
    "Calibration",
    "HeightMap",
    "PoissonSolver",
    "ReconstructionSettings",
    "Reconstructor",
    "fit_calibration",
    "integrate_gradients",
    "read_labels_csv",
    "write_labels_csv",
]
