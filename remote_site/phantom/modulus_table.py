"""Precomputed column modulus of a phantom, sampled per sensor frame.

The column modulus ``E_col(x, y)`` of :class:`~remote_site.phantom.phantom.Phantom` is static:
only the pose of the pad changes between frames. Evaluating it exactly on the sensor's
320 x 240 pixel grid costs ~10 ms per frame (hypot, arctan2, erfc, sqrt per pixel near a
tumor). This module tabulates, once per pixel pitch, each tumor's *compliance excess*
``f_t (E_bg / E_t - 1)`` on a patch covering the tumor's reach, at ``oversample`` samples per
sensor pixel, and samples it per frame by bilinear interpolation. Because the table step is
the pixel pitch divided by an integer, the fractional offset is the same for every pixel of a
frame, so a frame costs four strided slices per tumor in view (~0.3 ms for the whole map).

Away from all tumors the excess is exactly 0, so the sampled modulus is exactly ``E_bg`` there
(and 0 outside the footprint, as in the exact computation). Near a tumor the interpolation
error is largest at a sharp (benign) boundary; the test suite bounds it against the exact
computation (see ``tests/remote_site/test_phantom_modulus_table.py``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from remote_site.phantom.tumor import Tumor, tumor_column_fraction
from shared.errors import ConfigError

__all__ = ["ColumnModulusTable"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Patch:
    """One tumor's compliance excess on a regular grid (sample [0, 0] at (x0, y0))."""

    x0_mm: float
    y0_mm: float
    excess: NDArray[np.float32]  # (ny, nx)


def _axis_overlap(start_index: float, n_out: int, m: int, n_table: int
                  ) -> tuple[int, int, int, float] | None:
    """Output indices [lo, hi) whose table cells k0 + j*m, k0 + j*m + 1 lie in the table.

    Returns (lo, hi, k0, t) with the common fractional offset ``t``, or None if no overlap.
    """
    k0 = math.floor(start_index)
    t = start_index - k0
    lo = 0 if k0 >= 0 else (-k0 + m - 1) // m  # first j with k0 + j*m >= 0
    last_cell = n_table - 2  # the cell k and k + 1 must both exist
    if k0 + lo * m > last_cell:
        return None
    hi = min(n_out, (last_cell - k0) // m + 1)
    if hi <= lo:
        return None
    return lo, hi, k0, t


class ColumnModulusTable:
    """Tabulated column modulus of a layer with tumors, at one sensor pixel pitch.

    Args:
        size_mm: (width, depth) of the phantom footprint.
        modulus_kpa: background modulus ``E_bg``.
        thickness_mm: layer thickness.
        weight_radius_mm: loaded-disc radius of the depth weighting (the pad's effective one).
        tumors: the inclusions.
        pitch_mm: the sensor pixel pitch this table serves.
        oversample: table samples per pixel pitch (>= 1).

    Raises:
        ConfigError: a non-positive pitch or oversample.
    """

    def __init__(self, size_mm: tuple[float, float], modulus_kpa: float, thickness_mm: float,
                 weight_radius_mm: float, tumors: Sequence[Tumor], pitch_mm: float,
                 oversample: int = 2) -> None:
        if not (math.isfinite(pitch_mm) and pitch_mm > 0) or oversample < 1:
            raise ConfigError("modulus table: pitch must be > 0 and oversample >= 1")
        self.half_x_mm = size_mm[0] / 2.0
        self.half_y_mm = size_mm[1] / 2.0
        self.modulus_kpa = float(modulus_kpa)
        self.pitch_mm = float(pitch_mm)
        self.oversample = int(oversample)
        self.step_mm = self.pitch_mm / self.oversample
        self._patches = [self._build_patch(t, thickness_mm, weight_radius_mm) for t in tumors]
        if log.isEnabledFor(logging.DEBUG):
            cells = sum(p.excess.size for p in self._patches)
            log.debug("column modulus table: %d tumors, %d cells at %.4g mm", len(tumors),
                      cells, self.step_mm)

    def _build_patch(self, tumor: Tumor, thickness_mm: float, weight_radius_mm: float) -> _Patch:
        step = self.step_mm
        reach = tumor.reach_mm
        n = math.ceil(reach / step) + 2
        offsets = np.arange(-n, n + 1, dtype=np.float64) * step
        cx, cy = tumor.center_mm
        frac = tumor_column_fraction(tumor, offsets[None, :], offsets[:, None],
                                     weight_radius_mm, thickness_mm)
        excess = frac * (self.modulus_kpa / tumor.modulus_kpa - 1.0)
        # the exact computation evaluates a tumor only inside its reach square
        outside = np.abs(offsets) > reach
        excess[outside, :] = 0.0
        excess[:, outside] = 0.0
        return _Patch(cx - n * step, cy - n * step, excess.astype(np.float32))

    def sample(self, x_mm: float, y_mm: float, width_px: int, height_px: int
               ) -> NDArray[np.float32]:
        """Column modulus (kPa) on the pixel grid centred on (x, y), rows along +y.

        Args:
            x_mm, y_mm: pad centre in phantom coordinates (finite).
            width_px, height_px: pixel grid size at this table's pitch.

        Returns:
            (height_px, width_px) float32, 0 outside the footprint.
        """
        p, m = self.pitch_mm, self.oversample
        x_first = x_mm - (width_px - 1) / 2.0 * p
        y_first = y_mm - (height_px - 1) / 2.0 * p
        compliance = np.ones((height_px, width_px), np.float32)
        for patch in self._patches:
            cols = _axis_overlap((x_first - patch.x0_mm) / self.step_mm, width_px, m,
                                 patch.excess.shape[1])
            rows = _axis_overlap((y_first - patch.y0_mm) / self.step_mm, height_px, m,
                                 patch.excess.shape[0])
            if cols is None or rows is None:
                continue
            j0, j1, kx, tx = cols
            i0, i1, ky, ty = rows
            a, b = ky + i0 * m, ky + (i1 - 1) * m + 1
            c, d = kx + j0 * m, kx + (j1 - 1) * m + 1
            e = patch.excess
            top = e[a:b:m, c:d:m] * np.float32(1.0 - tx)
            top += e[a:b:m, c + 1:d + 1:m] * np.float32(tx)
            bottom = e[a + 1:b + 1:m, c:d:m] * np.float32(1.0 - tx)
            bottom += e[a + 1:b + 1:m, c + 1:d + 1:m] * np.float32(tx)
            top *= np.float32(1.0 - ty)
            bottom *= np.float32(ty)
            top += bottom
            compliance[i0:i1, j0:j1] += top
        modulus = np.float32(self.modulus_kpa) / compliance
        # outside the footprint: no material (same <= test as the exact computation)
        xs = x_first + np.arange(width_px) * p
        ys = y_first + np.arange(height_px) * p
        modulus[np.abs(ys) > self.half_y_mm, :] = 0.0
        modulus[:, np.abs(xs) > self.half_x_mm] = 0.0
        return modulus
