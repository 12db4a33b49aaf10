"""Fit the rim relief's one parameter on labelled calibration presses (see :mod:`.relief`).

For every pooling factor in ``factors`` the training presses are reconstructed with the
calibration (free-gel zero level), the soft rim of each is measured, and the tangent
extension that makes the relief peak equal the press depth derived from the label
(d = R - sqrt(R^2 - a^2), the *labelled* contact radius a) is the median over presses.
Only the presses passed in are used: give it the training split, measure on the test split.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from remote_site.reconstruction.calibration import Calibration
from remote_site.reconstruction.labels import BallLabel
from remote_site.reconstruction.reconstructor import ReconstructionSettings, Reconstructor
from remote_site.reconstruction.relief import RimStats, fit_rim_extension, rim_stats, rim_step
from remote_site.reconstruction.sphere import cap_depth_mm
from shared.errors import CalibrationError

__all__ = ["DEFAULT_RIM_FACTORS", "MIN_CELLS_ACROSS", "fit_rim_relief", "label_depth_mm"]

log = logging.getLogger(__name__)

#: pooling factors tried (full resolution up to ~2 mm cells on a 0.06 mm/px sensor)
DEFAULT_RIM_FACTORS = (1, 2, 4, 8, 16, 32)
#: a factor is fitted only where the median labelled contact spans this many cells across:
#: on a coarser grid the pooled peak falls below the cap and the fit chases a rim level
#: below the free gel that the relief can never use (it is clamped to 0)
MIN_CELLS_ACROSS = 6.0


def label_depth_mm(label: BallLabel, ball_radius_mm: float, mm_per_px: float) -> float:
    """Indentation of the ball for the labelled contact radius: R - sqrt(R^2 - a^2)."""
    try:
        return cap_depth_mm(ball_radius_mm, label.radius_px * mm_per_px)
    except CalibrationError as err:
        raise CalibrationError(f"{label.image}: {err}") from err


def fit_rim_relief(calibration: Calibration, presses: Sequence[tuple[np.ndarray, BallLabel]],
                   factors: Sequence[int] = DEFAULT_RIM_FACTORS) -> Calibration:
    """A copy of ``calibration`` set to ``relief="rim"`` with the extension fitted per factor.

    Args:
        calibration: a fitted calibration (with ``ball_radius_mm``).
        presses: labelled ball presses (the training split).
        factors: pooling factors to fit; a factor whose grid has no usable rim is left out.

    Raises:
        CalibrationError: no ball radius, or no factor could be fitted.
    """
    if not calibration.ball_radius_mm > 0:
        raise CalibrationError("the rim relief needs the calibration ball's radius")
    # heights above the free gel, with the border the rim relief reconstructs with
    settings = ReconstructionSettings(relief="plane", border="free")
    rec = Reconstructor(calibration, settings)
    depths = [label_depth_mm(lb, calibration.ball_radius_mm, calibration.mm_per_px)
              for _, lb in presses]
    table: dict[int, float] = {}
    diameter_px = 2.0 * float(np.median([lb.radius_px for _, lb in presses])) if presses else 0.0
    for factor in factors:
        if factor < 1 or factor > min(calibration.shape_hw) // 2:
            continue
        if diameter_px / factor < MIN_CELLS_ACROSS:
            log.info("rim relief: pooling factor %d not fitted (the contact spans %.1f cells)",
                     factor, diameter_px / factor)
            continue
        pitch = None if factor == 1 else factor * calibration.mm_per_px
        stats: list[RimStats] = []
        used: list[float] = []
        for (frame, _), depth in zip(presses, depths, strict=True):
            hm = rec.height_map(frame, out_pitch_mm=pitch)
            if hm.skipped:
                continue
            gx, gy, _ = rec.slopes(frame, factor=rec.pool_factor(pitch))
            st = rim_stats(hm.height_mm, gx, gy, settings.contact_threshold_mm,
                           step=rim_step(hm.height_mm.shape))
            if st is not None:
                stats.append(st)
                used.append(depth)
        try:
            table[rec.pool_factor(pitch)] = fit_rim_extension(stats, used)
        except CalibrationError as err:
            log.info("rim relief: pooling factor %d not fitted (%s)", factor, err)
    if not table:
        raise CalibrationError("no press gave a usable contact rim; cannot fit the rim relief")
    log.info("rim relief fitted on %d presses: extension mm by pooling factor %s",
             len(presses), {f: round(e, 4) for f, e in table.items()})
    return dataclasses.replace(calibration, relief="rim", rim_extension_mm=table,
                               stats={**calibration.stats, "rim_presses": float(len(presses))})
