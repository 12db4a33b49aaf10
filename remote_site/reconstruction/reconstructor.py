"""Frame -> height map: colour change -> slopes -> Poisson -> zero level -> (relief) -> mask.

Zero level (stated once, used everywhere): height 0 is the *undeformed gel*, estimated as a
least-squares plane through the reconstructed heights outside the region that rises above
the contact threshold, dilated by ``zero_exclusion_mm`` (so most of the drape around a
contact is excluded too). Positive heights are where the object presses into the gel. The
gel drapes beyond the contact circle, so the rim of a press sits above zero and heights in a
contact are offset upwards against a rigid sphere cap whose rim is at zero. With
``relief="rim"`` (a calibration setting, see :mod:`.relief`) the heights are then referenced
to the detected contact rim instead: the object's relief, without the drape.

Skips: a frame without contact evidence (fewer than ``min_contact_area_mm2`` of pixels whose
colour change exceeds ``contact_evidence_sigmas`` x the calibrated flat-gel noise) returns an
all-zero map without integrating. Only pixels above the dead zone
(``dead_zone_sigmas`` x noise) are fed to the model; the rest get slope 0, which also
removes the slope bias far from the contact. With ``out_pitch_mm`` the colour change (or the
slopes, ``pool="slopes"``) is block-averaged to the output grid before the model and Poisson
run, so a display-sized map costs a fraction of a full one; the calibration blur is then
skipped (block averaging smooths more) and the contact evidence is counted on the pooled grid
(a contact much smaller than one output cell may then read as "no contact").

Plausibility (a frame that is not a tactile image is refused, never shown as a contact): a
frame with contact evidence must show an image of the gel (not uniform, not noise:
:func:`.frames.check_image_content`, against the background in use) and its heights must lie
within ``max_height_mm`` of the free gel (the gel cannot be indented deeper than it is thick).
Found by an audit: a solid grey frame, swapped colour channels, pure noise or a frame 24 %
saturated reconstructed into bumps of 4-16 mm over ~80 % of the pad (the real presses: at most
0.8 mm), carried to the display as contact. Such a frame raises
:class:`~shared.errors.InputDataError` naming why; the station counts it (``bad_frame``) and
goes on with the next frame.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np

from remote_site.reconstruction.calibration import Calibration
from remote_site.reconstruction.features import (
    inverse_background_pct,
    pixel_position,
    relative_change,
    row_medians,
)
from remote_site.reconstruction.frames import check_image_content, shading, validate_frame
from remote_site.reconstruction.grid_predict import GridPredictor
from remote_site.reconstruction.kernels import (
    evidence_kernel,
    free_subsample_kernel,
    plane_normal_equations,
    subtract_plane_kernel,
)
from remote_site.reconstruction.poisson import SOLVERS, PoissonSolver
from remote_site.reconstruction.relief import (
    RELIEF_MODES,
    extension_for_factor,
    rim_level,
    rim_step,
)
from remote_site.reconstruction.workspace import Workspace
from shared.errors import ConfigError, InputDataError

__all__ = ["BORDER_MODES", "FREE_BORDER_SLOPE", "MAX_HEIGHT_MM", "HeightMap",
           "ReconstructionSettings", "Reconstructor"]

log = logging.getLogger(__name__)


#: ``ReconstructionSettings.border`` values
BORDER_MODES = ("auto", "fixed", "free")
#: a border pixel steeper than this (slope magnitude) is free under ``border="free"``
#: (chosen by 2-fold cross-validation on the GelSight Mini train split, docs/reconstruction.md)
FREE_BORDER_SLOPE = 0.1
#: default ``ReconstructionSettings.max_height_mm``
MAX_HEIGHT_MM = 4.0


@dataclass(frozen=True)
class ReconstructionSettings:
    """Knobs of the reconstruction (defaults chosen on the real GelSight Mini data).

    Attributes:
        solver: Poisson solver, ``"dst"`` (Dirichlet, default: flattest far field on the
            real data), ``"dct"`` (Neumann) or ``"fft"`` (periodic).
        zero_level: ``"plane"`` (default), ``"median"`` or ``"none"``.
        contact_threshold_mm: heights above this are in the contact mask.
        zero_exclusion_mm: dilation of the raised region excluded from the zero-level fit.
        dead_zone_sigmas: colour changes below this many noise sigmas get slope 0.
        contact_evidence_sigmas: a pixel counts as contact evidence above this many sigmas.
        min_contact_area_mm2: less evidence than this area means "no contact" (skip).
        pool: ``"change"`` (pool colour change before the model, fastest) or ``"slopes"``.
        relief: ``"plane"`` (heights above the free gel), ``"rim"`` (above the detected
            contact rim, :mod:`.relief`; needs a calibration with a fitted rim extension) or
            None (default): the calibration's ``relief``.
        border: the ``dst`` solver's condition at the frame border: ``"fixed"`` (h = 0 all
            round), ``"free"`` (no condition at border pixels steeper than
            ``FREE_BORDER_SLOPE``: a contact running off the frame, see :mod:`.poisson`) or
            ``"auto"`` (default): ``"free"`` with the rim relief (objects smaller than the
            pad, with free gel around them to anchor the height), ``"fixed"`` with the plane
            relief (a pad pressed flat into tissue: the whole frame may be deformed and the
            border is the only anchor; the palpation analysis was validated with it).
        max_height_mm: a reconstructed |height| beyond this refuses the frame
            (:class:`InputDataError`): the gel cannot be indented deeper than it is thick, a
            few mm on GelSight-type pads (the simulated pad's gel: 3 mm). Default 4 mm: the
            real GelSight Mini ball presses reach 0.84 mm, the simulated palpation at the arm's
            10 N force limit 2.5 mm (its linear gel model overshoots the 3 mm), while swapped
            colour channels or a partly saturated frame read 7-16 mm
            (docs/reconstruction.md, section 6).
    """

    solver: str = "dst"
    zero_level: str = "plane"
    contact_threshold_mm: float = 0.03
    zero_exclusion_mm: float = 1.0
    dead_zone_sigmas: float = 4.0
    contact_evidence_sigmas: float = 6.0
    min_contact_area_mm2: float = 0.1
    pool: str = "change"
    relief: str | None = None
    border: str = "auto"
    max_height_mm: float = MAX_HEIGHT_MM

    def __post_init__(self) -> None:
        if self.solver not in SOLVERS:
            raise ConfigError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        if self.zero_level not in ("plane", "median", "none"):
            raise ConfigError(f"zero_level must be plane, median or none, got {self.zero_level!r}")
        if self.pool not in ("change", "slopes"):
            raise ConfigError(f"pool must be 'change' or 'slopes', got {self.pool!r}")
        if self.relief is not None and self.relief not in RELIEF_MODES:
            raise ConfigError(f"relief must be one of {RELIEF_MODES} or None, "
                              f"got {self.relief!r}")
        if self.border not in BORDER_MODES:
            raise ConfigError(f"border must be one of {BORDER_MODES}, got {self.border!r}")
        for name in ("contact_threshold_mm", "zero_exclusion_mm", "dead_zone_sigmas",
                     "contact_evidence_sigmas", "min_contact_area_mm2"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ConfigError(f"{name} must be finite and >= 0, got {value}")
        if not self.max_height_mm > 0:  # inf switches the check off
            raise ConfigError(f"max_height_mm must be > 0, got {self.max_height_mm}")


@dataclass(frozen=True)
class HeightMap:
    """A reconstructed height map.

    Attributes:
        height_mm: (rows, cols) float32 heights, mm, positive into the gel.
        mask: (rows, cols) bool contact mask: the gel deformed beyond the contact threshold
            (measured above the free gel, whatever the relief reference).
        mm_per_px: pitch of this grid (a multiple of the sensor pixel when pooled).
        skipped: True when no contact evidence was found and integration was skipped.
    """

    height_mm: np.ndarray
    mask: np.ndarray
    mm_per_px: float
    skipped: bool = False

    @property
    def contact(self) -> bool:
        """Whether any pixel is in contact."""
        return bool(self.mask.any())

    @property
    def max_height_mm(self) -> float:
        """Largest height (indentation) in the map, mm."""
        return float(self.height_mm.max()) if self.height_mm.size else 0.0


def _pool_origin(length: int, factor: int) -> int:
    """First pixel of the blocks pooled by ``factor`` along an axis of ``length`` pixels: the
    pixels left over are cut on both sides (the larger half at the end), so the pooled grid's
    centre is the frame's, to half a pixel (cut at the end only, a 300-row frame pooled by 16
    put a press at the frame's centre 0.3 mm off the map's, where the station places the
    pad)."""
    return (length % factor) // 2


def _pool(image: np.ndarray, factor: int) -> np.ndarray:
    import cv2

    rows, cols = image.shape[0] // factor, image.shape[1] // factor
    r0, c0 = _pool_origin(image.shape[0], factor), _pool_origin(image.shape[1], factor)
    cropped = image[r0: r0 + rows * factor, c0: c0 + cols * factor]
    return np.asarray(cv2.resize(cropped, (cols, rows), interpolation=cv2.INTER_AREA))


class Reconstructor:
    """Turns sensor frames into height maps with a fixed calibration.

    Args:
        calibration: the sensor's calibration.
        settings: reconstruction knobs (defaults if None).
    """

    def __init__(self, calibration: Calibration,
                 settings: ReconstructionSettings | None = None) -> None:
        self.calibration = calibration
        self.settings = settings or ReconstructionSettings()
        self._solver = PoissonSolver(self.settings.solver)
        #: "plane" or "rim": the settings' choice, else the calibration's
        self.relief = self.settings.relief or calibration.relief
        if self.relief not in RELIEF_MODES:
            raise ConfigError(f"relief must be one of {', '.join(RELIEF_MODES)}, got "
                              f"{self.relief!r} (from the calibration)")
        if self.relief == "rim":
            extension_for_factor(calibration.rim_extension_mm, 1)  # ConfigError when unfitted
        border = self.settings.border
        #: no h = 0 condition at steep border pixels (see ReconstructionSettings.border)
        self.free_border = self.settings.solver == "dst" and (
            border == "free" or (border == "auto" and self.relief == "rim"))
        background = validate_frame(calibration.background_rgb, name="calibration background")
        self._background = (background, inverse_background_pct(background))
        self._last_bg: tuple[np.ndarray, np.ndarray] | None = None
        self._predictors: dict[int, GridPredictor] = {}
        self._pooled_bg: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._bg_shading: tuple[np.ndarray, np.ndarray] | None = None
        self._workspace = Workspace()

    @classmethod
    def from_file(cls, path: str | os.PathLike[str],
                  settings: ReconstructionSettings | None = None) -> Reconstructor:
        """Load a calibration file and build a reconstructor (raises CalibrationError)."""
        return cls(Calibration.load(path), settings)

    @property
    def shape_hw(self) -> tuple[int, int]:
        """(rows, cols) of accepted frames."""
        return self.calibration.shape_hw

    @property
    def background_rgb(self) -> np.ndarray:
        """The no-contact frame in use (float32, (H, W, 3)); the calibration's until set."""
        return self._background[0]

    def set_background(self, background_rgb: np.ndarray) -> None:
        """Use a fresher no-contact frame from now on, keeping the calibrated model.

        The gel's illumination drifts between calibration day and a session; a background
        captured at the station (pad lifted) replaces the calibration's without refitting.

        Args:
            background_rgb: (H, W, 3) RGB frame of this sensor's size, uint8 or float in
                [0, 255], NaN-free (e.g. the mean of a few no-contact frames).

        Raises:
            InputDataError: wrong shape or dtype, NaN/Inf, out of range, saturated or black.
        """
        validated = validate_frame(background_rgb, self.shape_hw, name="station background")
        self._background = (validated, inverse_background_pct(validated))
        self._pooled_bg.clear()

    def pool_factor(self, out_pitch_mm: float | None) -> int:
        """Integer block size giving the pitch closest to ``out_pitch_mm`` (1 = full res).

        Raises:
            InputDataError: a non-positive or non-finite pitch.
        """
        if out_pitch_mm is None:
            return 1
        if not (np.isfinite(out_pitch_mm) and out_pitch_mm > 0):
            raise InputDataError(f"out_pitch_mm must be positive and finite, got {out_pitch_mm}")
        factor = max(1, round(out_pitch_mm / self.calibration.mm_per_px))
        return int(min(factor, max(1, min(self.shape_hw) // 2)))

    def _background_for(self, background: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(validated background, its inverse), cached while the values passed are the same:
        compared by value, not by the array's ``id`` (found by an audit: a buffer updated in
        place was never read again, and a new temporary taking a freed one's ``id`` was
        reconstructed against the old background)."""
        if background is None:
            return self._background
        last = self._last_bg
        if last is not None and background.shape == last[0].shape \
                and np.array_equal(background, last[0]):
            return last
        validated = validate_frame(background, self.shape_hw, name="background")
        self._last_bg = (validated, inverse_background_pct(validated))
        return self._last_bg

    def _pooled_background(self, background: np.ndarray,
                           factor: int) -> tuple[np.ndarray, np.ndarray]:
        key = (id(background), factor)
        cached = self._pooled_bg.get(key)
        if cached is None or cached[0] is not background:  # an id reused by a new array
            pooled = _pool(background, factor)
            cached = (background, pooled, inverse_background_pct(pooled))
            if len(self._pooled_bg) > 16:
                self._pooled_bg.clear()
            self._pooled_bg[key] = cached  # holds the array, so its id is not reused meanwhile
        return cached[1], cached[2]

    def _grid_predictor(self, factor: int, shape: tuple[int, int]) -> GridPredictor:
        """The calibration model bound to the grid pooled by ``factor`` (built once)."""
        cached = self._predictors.get(factor)
        if cached is None or cached.shape != shape:
            r0 = _pool_origin(self.shape_hw[0], factor)
            c0 = _pool_origin(self.shape_hw[1], factor)
            rows = (r0 + np.arange(shape[0]) * factor + (factor - 1) / 2.0)[:, None]
            cols = (c0 + np.arange(shape[1]) * factor + (factor - 1) / 2.0)[None, :]
            rows, cols = np.broadcast_arrays(rows, cols)
            x, y = pixel_position(self.shape_hw, rows, cols)
            cached = self.calibration.model.grid_predictor(x, y)
            self._predictors[factor] = cached
        return cached

    def _shading_of(self, background: np.ndarray) -> np.ndarray:
        """:func:`.frames.shading` of a validated background (cached while it is in use)."""
        cached = self._bg_shading
        if cached is None or cached[0] is not background:
            cached = (background, shading(background))  # holds it: its id is not reused
            self._bg_shading = cached
        return cached[1]

    def slopes(self, frame_rgb: np.ndarray, background: np.ndarray | None = None,
               factor: int = 1) -> tuple[np.ndarray, np.ndarray, bool]:
        """Slope maps (dh/dx, dh/dy) on the grid pooled by ``factor``, and contact evidence.

        Raises:
            InputDataError: the frame or background fails validation, or a frame with contact
                evidence is no image of the gel (uniform or noise).
        """
        return self._slopes(frame_rgb, background, factor, reuse=False)

    def _slopes(self, frame_rgb: np.ndarray, background: np.ndarray | None, factor: int,
                reuse: bool) -> tuple[np.ndarray, np.ndarray, bool]:
        """:meth:`slopes`; with ``reuse`` the intermediates *and the slope maps* are this
        thread's workspace arrays (valid until its next call)."""
        calib = self.calibration
        ws = self._workspace if reuse else None

        def scratch(name: str, shape: tuple[int, ...], dtype: type = np.float32
                    ) -> np.ndarray | None:
            return None if ws is None else ws.get(name, shape, dtype)

        shape3 = (*self.shape_hw, 3)
        frame = validate_frame(frame_rgb, self.shape_hw, out=scratch("frame", shape3))
        bg, inv_bg = self._background_for(background)
        full_frame, full_bg = frame, bg
        pool_change = factor > 1 and self.settings.pool == "change"
        if pool_change:
            # Pool frame and background first (the ratio of block means ~ the block mean of the
            # ratio for a smooth background); pooling smooths more than the calibration blur.
            frame = _pool(frame, factor)
            bg, inv_bg = self._pooled_background(bg, factor)
            change = relative_change(frame, bg, 0.0, inv_background_pct=inv_bg,
                                     out=scratch("change", frame.shape))
        else:
            change = relative_change(frame, bg, calib.blur_sigma_px, inv_background_pct=inv_bg,
                                     out=scratch("change", shape3),
                                     work=scratch("unblurred", shape3))
        noise = max(calib.noise_pct, 1e-3)
        # one pass: count of evidence pixels and the mask of pixels above the dead zone
        # (float32 thresholds, as numpy compares a float32 array with a Python float)
        evidence, active = evidence_kernel(
            np.ascontiguousarray(change, np.float32),
            np.float32(self.settings.contact_evidence_sigmas * noise),
            np.float32(self.settings.dead_zone_sigmas * noise))
        grid_pitch_mm = calib.mm_per_px * (factor if pool_change else 1)
        min_px = self.settings.min_contact_area_mm2 / grid_pitch_mm**2
        has_contact = evidence >= max(min_px, 1.0)
        grid = change.shape[:2]
        gx = scratch("gx", grid)
        gy = scratch("gy", grid)
        if gx is None or gy is None:
            gx, gy = np.zeros(grid, np.float32), np.zeros(grid, np.float32)
        else:
            gx.fill(0.0)
            gy.fill(0.0)
        if has_contact:  # a frame to integrate must be an image of the gel
            check_image_content(full_frame, self._shading_of(full_bg))
            predictor = self._grid_predictor(factor if pool_change else 1, grid)
            predictor.predict_into(change, active, gx, gy)
        if factor > 1 and not pool_change:
            gx, gy = _pool(gx, factor), _pool(gy, factor)
        return gx, gy, has_contact

    def height_map(self, frame_rgb: np.ndarray, background: np.ndarray | None = None,
                   out_pitch_mm: float | None = None) -> HeightMap:
        """Reconstruct one frame.

        Args:
            frame_rgb: (H, W, 3) RGB frame of this sensor (uint8 or float in [0, 255]).
            background: a fresher no-contact frame; the calibration's background if None.
            out_pitch_mm: output pitch; None for the full sensor resolution. The pitch used
                is the nearest integer multiple of the sensor pixel (see ``mm_per_px``).

        Returns:
            The :class:`HeightMap`.

        Raises:
            InputDataError: bad frame/background (size, dtype, NaN, saturated, black) or pitch;
                an implausible frame: no image of the gel (uniform or noise), or heights
                beyond ``max_height_mm`` (see the module docstring).
        """
        factor = self.pool_factor(out_pitch_mm)
        pitch_mm = self.calibration.mm_per_px * factor
        gx, gy, has_contact = self._slopes(frame_rgb, background, factor, reuse=True)
        if not has_contact:
            zeros = np.zeros(gx.shape, np.float32)
            return HeightMap(zeros, np.zeros(gx.shape, bool), pitch_mm, skipped=True)
        work = self._workspace.get("poisson", gx.shape, self._solver.dtype)
        height = self._solver.integrate(gx, gy, pitch_mm, work=work,
                                        free_border=self._free_border_mask(gx, gy))
        height, mask, finite = self._zero_level_and_mask(height, pitch_mm)
        if not finite:  # cannot happen with finite slopes; never pass it on
            raise InputDataError("reconstruction produced non-finite heights")
        self._check_heights(height)
        if self.relief == "rim" and mask.any():
            # only the heights move: the contact (mask) stays what the gel's deformation
            # says, so a light touch whose cap lies under the threshold is still a contact
            # (the station's background tracker must never take it for the pad lifted)
            self._rim_relief(height, gx, gy, factor)
        return HeightMap(height, mask, pitch_mm, skipped=False)

    def _check_heights(self, height: np.ndarray) -> None:
        """Refuse heights beyond ``max_height_mm`` (deeper than the gel is thick)."""
        limit = self.settings.max_height_mm
        top, bottom = float(height.max()), float(height.min())
        worst = top if top >= -bottom else bottom
        if abs(worst) > limit:
            raise InputDataError(
                f"implausible frame: reconstructed height {worst:+.2f} mm is beyond "
                f"max_height_mm {limit:g} (deeper than the gel is thick): not a tactile image "
                "(colour channels swapped, a corrupted or partly saturated frame, or the wrong "
                "calibration or background?)")

    def _free_border_mask(self, gx: np.ndarray, gy: np.ndarray) -> np.ndarray | None:
        """Border pixels steeper than ``FREE_BORDER_SLOPE`` when the border is free (see
        ``ReconstructionSettings.border``), else None (also when there are none)."""
        if not self.free_border:
            return None
        steep = np.zeros(gx.shape, bool)
        for edge in ((0, slice(None)), (-1, slice(None)), (slice(None), 0), (slice(None), -1)):
            steep[edge] = np.hypot(gx[edge], gy[edge]) > FREE_BORDER_SLOPE
        return steep if steep.any() else None

    def _rim_relief(self, height: np.ndarray, gx: np.ndarray, gy: np.ndarray,
                    factor: int) -> None:
        """Heights above the detected contact rim, in place; see :mod:`.relief`."""
        threshold = self.settings.contact_threshold_mm
        extension = extension_for_factor(self.calibration.rim_extension_mm, factor)
        if extension is None:  # the grid is too coarse for a rim: heights above the free gel
            return
        level = rim_level(height, gx, gy, threshold, extension, step=rim_step(height.shape))
        if level > 0.0:
            np.subtract(height, np.float32(level), out=height)
            np.maximum(height, np.float32(0.0), out=height)

    def _zero_level_and_mask(self, height: np.ndarray,
                             pitch_mm: float) -> tuple[np.ndarray, np.ndarray, bool]:
        """Height minus the zero level, its contact mask and whether it is all finite.

        The height and mask returned are new arrays (``height`` may be workspace memory).

        The free gel is judged on the grid subsampled by ``step`` (the raised region dilated
        by ``zero_exclusion_mm``, evaluated only at the subsampled pixels); the plane is the
        least-squares fit through the free subsampled heights.
        """
        threshold = np.float32(self.settings.contact_threshold_mm)
        mode = self.settings.zero_level
        zero = np.float32(0.0)
        if mode == "none":  # h - 0 == h exactly: the kernel just copies, masks and checks
            out, mask, finite = subtract_plane_kernel(height, zero, zero, zero, threshold)
            return out, mask, bool(finite)
        step = max(1, min(height.shape) // 60)
        sub = height[::step, ::step]
        base = np.float32(row_medians(sub.reshape(1, -1))[0])
        radius_px = round(self.settings.zero_exclusion_mm / pitch_mm)
        integral = self._workspace.get("integral", (height.shape[0] + 1, height.shape[1] + 1),
                                       np.int32)
        free = free_subsample_kernel(height, base, threshold, radius_px, step, integral)
        if np.count_nonzero(free) < 10:
            c0, c1, c2 = base, zero, zero
        elif mode == "median":
            c0 = np.float32(row_medians(sub[free].reshape(1, -1))[0])
            c1, c2 = zero, zero
        else:
            coef = plane_normal_equations(sub, free, step)
            c0, c1, c2 = np.float32(coef[0]), np.float32(coef[1]), np.float32(coef[2])
        out, mask, finite = subtract_plane_kernel(height, c0, c1, c2, threshold)
        return out, mask, bool(finite)
