"""Streaming stiffness: cut the arm's sample stream into loading segments, estimate each.

Only loading is used: a segment opens when the pad starts moving down and closes when it
has risen ``unload_tol_mm`` above its deepest point (unloading), when it has not gone deeper
by ``dwell_tol_mm`` for ``dwell_s`` (dwell), or when it has slid ``max_slide_mm`` sideways.
Samples after the deepest point are discarded, and samples outside segments are never fitted;
:attr:`StiffnessTracker.skipped` counts them (the saving is measured in the benchmark).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from remote_site.stiffness.estimator import StiffnessConfig, StiffnessEstimate, estimate_press
from shared.errors import ConfigError, InputDataError

__all__ = ["PressResult", "SegmentConfig", "StiffnessTracker"]


@dataclass(frozen=True)
class SegmentConfig:
    """Loading-segment detection.

    Attributes:
        unload_tol_mm: rising this far above the deepest point ends loading.
        dwell_tol_mm: going deeper by less than this ...
        dwell_s: ... for this long ends loading.
        max_slide_mm: sliding sideways this far ends the segment.
        max_samples: a segment is closed (and estimated) when it holds this many samples.
    """

    unload_tol_mm: float = 0.05
    dwell_tol_mm: float = 0.03
    dwell_s: float = 0.1
    max_slide_mm: float = 1.0
    max_samples: int = 20_000

    def __post_init__(self) -> None:
        vals = (self.unload_tol_mm, self.dwell_tol_mm, self.dwell_s, self.max_slide_mm)
        if not all(math.isfinite(v) and v > 0 for v in vals) or self.max_samples < 10:
            raise ConfigError("segment settings must be finite and > 0 (max_samples >= 10)")


@dataclass(frozen=True)
class PressResult:
    """A finished loading segment: where it was and what it gave."""

    x_mm: float
    y_mm: float
    t_start_s: float
    t_end_s: float
    n_samples: int
    estimate: StiffnessEstimate


class StiffnessTracker:
    """Feed ``(t, position, force)`` samples; get a :class:`PressResult` per loading segment.

    Args:
        config: estimator settings, with the probe's gel stiffness (calibration data).
        segments: segment detection settings.

    Raises:
        ConfigError: ``config`` has no gel stiffness (no stiffness calibration loaded).
    """

    def __init__(self, config: StiffnessConfig,
                 segments: SegmentConfig | None = None) -> None:
        config.require_gel()
        self.config = config
        self.segments = segments or SegmentConfig()
        self.seen = 0
        self.used = 0
        self._t: list[float] = []
        self._x: list[float] = []
        self._y: list[float] = []
        self._a: list[float] = []
        self._f: list[float] = []
        self._peak_i = -1
        self._peak_a = -math.inf
        self._progress_a = -math.inf
        self._progress_t = 0.0
        self._prev_a: float | None = None

    @property
    def skipped(self) -> int:
        """Samples never fitted (dwell, unloading, lifting, sliding)."""
        return self.seen - self.used

    @property
    def loading(self) -> bool:
        """True while a loading segment is open."""
        return bool(self._t)

    def _reset(self) -> None:
        self._t, self._x, self._y, self._a, self._f = [], [], [], [], []
        self._peak_i, self._peak_a = -1, -math.inf
        self._progress_a, self._progress_t = -math.inf, 0.0

    def _close(self) -> PressResult | None:
        n = self._peak_i + 1
        result = None
        deep_enough = n > 0 and max(self._a[:n]) - min(self._a[:n]) >= self.config.min_depth_mm
        if n >= self.config.min_samples and deep_enough:
            est = estimate_press(self._a[:n], self._f[:n], self.config)
            self.used += n
            result = PressResult(float(np.mean(self._x[:n])), float(np.mean(self._y[:n])),
                                 self._t[0], self._t[n - 1], n, est)
        self._reset()
        return result

    def update(self, t_s: float, position_mm: Sequence[float],
               force_n: float) -> PressResult | None:
        """Add one sample; returns a result when a loading segment has just closed.

        Raises:
            InputDataError: a non-finite time, position or force.
        """
        try:
            x, y, z = (float(v) for v in position_mm)
        except (TypeError, ValueError) as err:
            raise InputDataError(f"position must be three numbers, got {position_mm!r}") from err
        vals = (float(t_s), x, y, z, float(force_n))
        if not all(math.isfinite(v) for v in vals):
            raise InputDataError("stiffness sample must be finite (NaN/Inf rejected)")
        self.seen += 1
        a = -z
        seg = self.segments
        prev, self._prev_a = self._prev_a, a
        result = None
        if self._t:
            slid = math.hypot(x - self._x[0], y - self._y[0]) > seg.max_slide_mm
            unloading = a < self._peak_a - seg.unload_tol_mm
            dwelling = t_s - self._progress_t > seg.dwell_s
            if slid or unloading or dwelling or len(self._t) >= seg.max_samples:
                result = self._close()
        if not self._t and (prev is None or a <= prev):
            return result  # not moving down: nothing to open
        self._t.append(float(t_s))
        self._x.append(x)
        self._y.append(y)
        self._a.append(a)
        self._f.append(float(force_n))
        if a > self._peak_a:
            self._peak_a, self._peak_i = a, len(self._t) - 1
        if a > self._progress_a + seg.dwell_tol_mm:
            self._progress_a, self._progress_t = a, float(t_s)
        return result

    def flush(self) -> PressResult | None:
        """Close the open segment (end of a recording)."""
        return self._close() if self._t else None
