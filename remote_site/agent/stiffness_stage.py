"""The station's stiffness state: loading-only tracker, the scan's map, the current estimate.

The arm monitor feeds every arm reading (time, pad pose, measured force) to
:meth:`StiffnessStage.add_sample`; only loading segments are fitted
(:class:`~remote_site.stiffness.tracker.StiffnessTracker`), each valid press is added to the
:class:`~remote_site.stiffness.stiffness_map.StiffnessMap` at the pad centre, and the latest
valid press is the *current estimate*. The frame pipeline reads the map from another thread,
so both sides go through :attr:`StiffnessStage.lock`.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

from remote_site.stiffness.estimator import StiffnessConfig
from remote_site.stiffness.stiffness_map import MapBounds, StiffnessMap
from remote_site.stiffness.tracker import PressResult, SegmentConfig, StiffnessTracker

__all__ = ["StiffnessCounters", "StiffnessStage"]

log = logging.getLogger(__name__)


@dataclass
class StiffnessCounters:
    """Running totals of the stiffness stage."""

    presses: int = 0
    valid: int = 0
    invalid_reasons: Counter[str] = field(default_factory=Counter)
    samples_outside_map: int = 0


class StiffnessStage:
    """Tracker + map + current estimate, thread-safe.

    Args:
        config: estimator settings, with the probe's gel stiffness (calibration data).
        bounds: the stiffness map's rectangle and cell size (phantom mm).
        segments: loading-segment detection settings.

    Raises:
        ConfigError: ``config`` has no gel stiffness.
    """

    def __init__(self, config: StiffnessConfig, bounds: MapBounds | None = None,
                 segments: SegmentConfig | None = None) -> None:
        self.tracker = StiffnessTracker(config, segments)
        self.map = StiffnessMap(bounds)
        self.lock = threading.Lock()
        self.counters = StiffnessCounters()
        self.last_press: PressResult | None = None
        self._last_t_s: float | None = None

    @property
    def current_n_per_mm(self) -> float | None:
        """Tissue stiffness of the latest valid press (N/mm), or None."""
        press = self.last_press
        return None if press is None else press.estimate.k_tissue_n_per_mm

    def add_sample(self, t_s: float, position_mm: Sequence[float],
                   force_n: float) -> PressResult | None:
        """Feed one arm reading; returns a press result when a loading segment closed.

        Readings with a time not after the previous one (the same arm step read twice) are
        ignored.

        Raises:
            InputDataError: a non-finite sample.
        """
        with self.lock:
            if self._last_t_s is not None and t_s <= self._last_t_s:
                return None
            self._last_t_s = t_s
            result = self.tracker.update(t_s, position_mm, force_n)
            if result is not None:
                self._record(result)
            return result

    def flush(self) -> PressResult | None:
        """Close the open segment (at shutdown)."""
        with self.lock:
            result = self.tracker.flush()
            if result is not None:
                self._record(result)
            return result

    def _record(self, result: PressResult) -> None:
        self.counters.presses += 1
        est = result.estimate
        if not est.valid:
            self.counters.invalid_reasons[est.reason] += 1
            return
        self.counters.valid += 1
        self.last_press = result
        if not self.map.add(result.x_mm, result.y_mm, est.k_tissue_n_per_mm):
            self.counters.samples_outside_map += 1
        log.info("press at (%.1f, %.1f) mm: k = %.3f N/mm (%s, %d samples)", result.x_mm,
                 result.y_mm, est.k_tissue_n_per_mm, est.reason, est.n_used)

    def summary(self) -> dict[str, object]:
        """Counters for the station's summary."""
        with self.lock:
            press = self.last_press
            return {
                "presses": self.counters.presses,
                "estimates_valid": self.counters.valid,
                "invalid_reasons": dict(self.counters.invalid_reasons),
                "samples_seen": self.tracker.seen,
                "samples_used": self.tracker.used,
                "samples_skipped_not_loading": self.tracker.skipped,
                "map_cells_known": int((self.map.count > 0).sum()),
                "last_k_n_per_mm": None if press is None else press.estimate.k_tissue_n_per_mm,
                "last_press_mm": None if press is None else [press.x_mm, press.y_mm],
            }
