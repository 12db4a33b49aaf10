"""Tissue stiffness from one loading segment of arm approach and force.

Pipeline for one press (``approach_mm`` = how far the pad has moved down, any zero;
``force_n`` = measured normal force):

1. Validate (finite, same length; NaN is rejected, never propagated).
2. Contact point: samples with ``F >= contact_force_n`` are certainly in contact; a line fit
   over them gives the approach where the force extrapolates to zero, ``a_c``.
3. Minimum depth: only samples indented at least ``min_depth_mm`` past ``a_c`` are used (no
   ratio or slope from the noisy first tenths of a mm), and the fit is repeated on them
   (this removes the bias of selecting near-threshold samples by their noisy force).
4. Regression of force on approach: ``ols``, ``theil_sen`` (default) or ``huber``; or the
   paper's plain ``ratio`` (median of ``F / (a - a_first)`` with ``a_first`` the first sample
   over the contact force, i.e. without extrapolating the contact point).
5. Gel compensation: the sensor gel and the tissue are springs in series,
   ``1/k_meas = 1/k_tissue + 1/k_gel``, so ``k_tissue = 1 / (1/k_meas - 1/k_gel)``. A measured
   stiffness at or above ``k_gel / (1 + 1/max_ratio)`` means the tissue is too stiff to
   resolve through the gel: the result is clamped to ``max_stiffness_n_per_mm`` and flagged
   ``saturated``. ``k_gel`` is calibration data (the probe's
   :class:`~shared.stiffness_calibration.StiffnessCalibration`), never a built-in constant: a
   configuration without it refuses to estimate (:class:`~shared.errors.ConfigError`).

6. Significance: the force must rise with depth beyond its noise. The slope's t statistic
   (slope over its standard error, from the residuals' robust scale) must reach
   ``min_slope_t``, and the deepest sample must lie at least ``min_depth_mm`` past the
   contact point. Without it a pad moved through air with a noisy force reading gave a valid
   stiffness in about a quarter of such presses (found by an audit: an offset of 0.1 N and
   0.1 N of noise, the arm model's own), some with the contact point beyond the deepest
   sample.

Invalid presses (no contact, too shallow, force not rising) give ``valid=False`` with a
reason and zero stiffness, never NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from remote_site.stiffness.regression import fit_ols, get_fit
from shared.errors import ConfigError, InputDataError
from shared.stiffness_calibration import StiffnessCalibration

__all__ = ["METHODS", "StiffnessConfig", "StiffnessEstimate", "compensate_gel", "estimate_press"]

METHODS = ("ratio", "ols", "theil_sen", "huber")


@dataclass(frozen=True)
class StiffnessConfig:
    """Settings of the stiffness stage (resolve with section ``stiffness``).

    Attributes:
        method: one of :data:`METHODS`.
        contact_force_n: force above which a sample is in contact (>= 5x the force noise).
        min_depth_mm: samples shallower than this past the contact point are not used.
        min_samples: fewer usable samples give an invalid estimate.
        max_samples: longer segments are decimated uniformly before fitting (Theil-Sen is
            O(n^2)).
        gel_stiffness_n_per_mm: the sensor gel as a series spring, from the probe's stiffness
            calibration (:meth:`with_calibration`); None refuses to estimate.
        max_stiffness_n_per_mm: clamp for saturated (too stiff) tissue.
        min_slope_t: the slope must be at least this many standard errors above zero (the
            force rises beyond its noise), else ``not_loading``.
    """

    method: str = "theil_sen"
    contact_force_n: float = 0.1
    min_depth_mm: float = 0.3
    min_samples: int = 8
    max_samples: int = 400
    gel_stiffness_n_per_mm: float | None = None
    max_stiffness_n_per_mm: float = 100.0
    min_slope_t: float = 5.0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError(f"stiffness method must be one of {METHODS}, got {self.method!r}")
        vals = (self.contact_force_n, self.max_stiffness_n_per_mm,
                *(() if self.gel_stiffness_n_per_mm is None else (self.gel_stiffness_n_per_mm,)))
        if not all(math.isfinite(v) and v > 0 for v in vals):
            raise ConfigError("stiffness: force threshold and stiffnesses must be finite and > 0")
        if not (math.isfinite(self.min_depth_mm) and self.min_depth_mm >= 0):
            raise ConfigError("stiffness: min_depth_mm must be >= 0")
        if not (math.isfinite(self.min_slope_t) and self.min_slope_t >= 0):
            raise ConfigError("stiffness: min_slope_t must be finite and >= 0")
        if self.min_samples < 3 or self.max_samples < self.min_samples:
            raise ConfigError("stiffness: need 3 <= min_samples <= max_samples")

    def with_calibration(self, calibration: StiffnessCalibration) -> StiffnessConfig:
        """These settings with the gel stiffness of ``calibration``."""
        return replace(self, gel_stiffness_n_per_mm=calibration.gel_stiffness_n_per_mm)

    def require_gel(self) -> float:
        """The gel stiffness, or a clear error when no calibration supplied it.

        Raises:
            ConfigError: no gel stiffness (no stiffness calibration was loaded).
        """
        if self.gel_stiffness_n_per_mm is None:
            raise ConfigError("stiffness: no gel stiffness; load the probe's stiffness "
                              "calibration (--stiffness-calibration FILE, made by `teletouch "
                              "sensor calibrate-stiffness`)")
        return self.gel_stiffness_n_per_mm


@dataclass(frozen=True)
class StiffnessEstimate:
    """One press's result (all finite).

    Attributes:
        valid: False when the press could not give a stiffness (see ``reason``).
        reason: ``ok``, ``saturated``, ``no_contact``, ``too_shallow``, ``not_loading``.
        k_measured_n_per_mm: slope of force on approach (tissue and gel in series).
        k_tissue_n_per_mm: after gel compensation.
        contact_approach_mm: approach at which contact started.
        max_indentation_mm: deepest approach past contact in the segment.
        n_used: samples in the final fit.
        residual_std_n: robust (MAD) scale of the fit residuals.
        method: the estimator used.
    """

    valid: bool
    reason: str
    k_measured_n_per_mm: float = 0.0
    k_tissue_n_per_mm: float = 0.0
    contact_approach_mm: float = 0.0
    max_indentation_mm: float = 0.0
    n_used: int = 0
    residual_std_n: float = 0.0
    method: str = "theil_sen"


def compensate_gel(k_measured_n_per_mm: float, gel_stiffness_n_per_mm: float,
                   max_stiffness_n_per_mm: float) -> tuple[float, bool]:
    """Remove the gel's series compliance: ``1 / (1/k_meas - 1/k_gel)``.

    Returns:
        (k_tissue, saturated); saturated results are clamped to ``max_stiffness_n_per_mm``.

    Raises:
        InputDataError: a non-finite or negative measured stiffness.
    """
    if not (math.isfinite(k_measured_n_per_mm) and k_measured_n_per_mm >= 0):
        raise InputDataError("measured stiffness must be finite and >= 0")
    if k_measured_n_per_mm == 0.0:
        return 0.0, False
    inv_meas = 1.0 / k_measured_n_per_mm
    if not math.isfinite(inv_meas):  # subnormal stiffness: the gel's share is negligible
        return k_measured_n_per_mm, False
    inv = inv_meas - 1.0 / gel_stiffness_n_per_mm
    if inv <= 1.0 / max_stiffness_n_per_mm:
        return max_stiffness_n_per_mm, True
    return 1.0 / inv, False


def _as_samples(approach_mm: ArrayLike, force_n: ArrayLike) -> tuple[NDArray[np.float64],
                                                                     NDArray[np.float64]]:
    a = np.asarray(approach_mm, dtype=float).ravel()
    f = np.asarray(force_n, dtype=float).ravel()
    if a.shape != f.shape:
        raise InputDataError(f"approach and force differ in length ({a.size} vs {f.size})")
    if not (np.isfinite(a).all() and np.isfinite(f).all()):
        raise InputDataError("approach and force samples must be finite (NaN/Inf rejected)")
    return a, f


def _decimate(x: NDArray[np.float64], y: NDArray[np.float64],
              max_n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    if x.size <= max_n:
        return x, y
    idx = np.linspace(0, x.size - 1, max_n).round().astype(int)
    return x[idx], y[idx]


def _mad(r: NDArray[np.float64]) -> float:
    return 1.4826 * float(np.median(np.abs(r - np.median(r)))) if r.size else 0.0


def _slope_t(x: NDArray[np.float64], resid: NDArray[np.float64], slope: float) -> float:
    """The slope's t statistic: ``slope / se`` with ``se = s / sqrt(sum((x - mean x)^2))``
    and ``s`` the residuals' robust (MAD) scale, so a few outliers do not hide the noise;
    inf for an exact fit."""
    spread = math.sqrt(float(np.sum((x - x.mean()) ** 2)))
    scale = _mad(resid)
    if scale == 0.0:
        return math.inf if slope > 0 else 0.0
    return slope * spread / scale if spread > 0 else 0.0


def estimate_press(approach_mm: ArrayLike, force_n: ArrayLike,
                   config: StiffnessConfig) -> StiffnessEstimate:
    """Estimate tissue stiffness from one loading segment.

    Args:
        approach_mm: downward pad travel per sample (mm; larger = deeper).
        force_n: measured normal force per sample (N).
        config: settings with the probe's gel stiffness.

    Returns:
        The estimate; ``valid`` is False (stiffness 0) when the press cannot give one.

    Raises:
        InputDataError: NaN/Inf samples or mismatched lengths.
        ConfigError: ``config`` has no gel stiffness (no stiffness calibration).
    """
    cfg = config
    cfg.require_gel()
    a, f = _as_samples(approach_mm, force_n)
    method = cfg.method
    touching = f >= cfg.contact_force_n
    if np.count_nonzero(touching) < 2:
        return StiffnessEstimate(False, "no_contact", method=method)
    a_t, f_t = a[touching], f[touching]
    if float(np.ptp(a_t)) <= cfg.min_depth_mm or np.ptp(a_t) <= 0:
        return StiffnessEstimate(False, "too_shallow", method=method)

    if method == "ratio":
        a_first = float(a[int(np.argmax(touching))])
        depth = a - a_first
        use = touching & (depth >= max(cfg.min_depth_mm, 1e-9))
        if np.count_nonzero(use) < cfg.min_samples:
            return StiffnessEstimate(False, "too_shallow", method=method)
        # force must rise with depth to be loading; samples all at one depth give no slope
        # (0/0 = NaN, which "<= 0" let through as loading: found by review)
        slope = fit_ols(a[use], f[use])[0] if np.ptp(a[use]) > 0 else math.nan
        if not (math.isfinite(slope) and slope > 0):
            return StiffnessEstimate(False, "not_loading", method=method)
        # significance over every sample past that depth, not only those over the contact
        # force (selected by their noisy force, they understate the noise)
        deep = depth >= max(cfg.min_depth_mm, 1e-9)
        d_slope, d_icpt = fit_ols(a[deep], f[deep])
        if _slope_t(a[deep], f[deep] - (d_icpt + d_slope * a[deep]), d_slope) < cfg.min_slope_t:
            return StiffnessEstimate(False, "not_loading", method=method)
        k_meas = float(np.median(f[use] / depth[use]))
        resid = f[use] - k_meas * depth[use]
        return _finish(cfg, k_meas, a_first, float(depth.max()), int(np.count_nonzero(use)),
                       _mad(resid), method)

    fit = get_fit(method)
    x, y = _decimate(a_t, f_t, cfg.max_samples)
    slope, intercept = fit_ols(x, y) if x.size < 3 else fit(x, y)
    if not (math.isfinite(slope) and slope > 0):
        return StiffnessEstimate(False, "not_loading", method=method)
    a_c = -intercept / slope
    use = (a - a_c) >= cfg.min_depth_mm
    if np.count_nonzero(use) < cfg.min_samples:
        return StiffnessEstimate(False, "too_shallow", contact_approach_mm=a_c, method=method)
    x, y = _decimate(a[use], f[use], cfg.max_samples)
    if float(np.ptp(x)) <= 0:
        return StiffnessEstimate(False, "too_shallow", contact_approach_mm=a_c, method=method)
    slope, intercept = fit(x, y)
    if not (math.isfinite(slope) and slope > 0 and math.isfinite(intercept)):
        return StiffnessEstimate(False, "not_loading", contact_approach_mm=a_c, method=method)
    a_c = -intercept / slope
    resid = y - (intercept + slope * x)
    if _slope_t(x, resid, slope) < cfg.min_slope_t:
        return StiffnessEstimate(False, "not_loading", contact_approach_mm=a_c, method=method)
    if float(a.max() - a_c) < cfg.min_depth_mm:  # the refit's contact point: past the samples
        return StiffnessEstimate(False, "too_shallow", contact_approach_mm=a_c, method=method)
    return _finish(cfg, slope, a_c, float(a.max() - a_c), int(x.size), _mad(resid), method)


def _finish(cfg: StiffnessConfig, k_meas: float, a_c: float, max_depth: float, n_used: int,
            resid_std: float, method: str) -> StiffnessEstimate:
    if not (math.isfinite(k_meas) and k_meas > 0):
        return StiffnessEstimate(False, "not_loading", method=method)
    k_tissue, saturated = compensate_gel(k_meas, cfg.require_gel(),
                                         cfg.max_stiffness_n_per_mm)
    return StiffnessEstimate(True, "saturated" if saturated else "ok", k_meas, k_tissue, a_c,
                             max_depth, n_used, resid_std, method)
