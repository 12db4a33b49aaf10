"""Loop-period statistics: a fixed-size ring of periods, percentiles on demand."""

from __future__ import annotations

import threading

import numpy as np

from shared.errors import ConfigError

__all__ = ["PeriodStats"]


class PeriodStats:
    """Records the start times of a periodic loop and reports its rate and jitter.

    Args:
        target_period_s: the period the loop aims at (jitter is ``|period - target|``).
        capacity: periods kept (older ones are overwritten); 2**17 holds 131 s at 1 kHz.

    Raises:
        ConfigError: a non-positive target or capacity.
    """

    def __init__(self, target_period_s: float, capacity: int = 1 << 17) -> None:
        if not target_period_s > 0 or capacity < 2:
            raise ConfigError("PeriodStats needs target_period_s > 0 and capacity >= 2")
        self.target_period_s = float(target_period_s)
        self._periods_s = np.zeros(capacity)
        self._n = 0
        self._last_start_s: float | None = None
        self._first_start_s: float | None = None
        self._lock = threading.Lock()
        self.iterations = 0
        self.overruns = 0

    def tick(self, start_s: float) -> None:
        """Record that an iteration started at ``start_s`` (``time.perf_counter``)."""
        last = self._last_start_s
        self._last_start_s = start_s
        self.iterations += 1
        if last is None:
            self._first_start_s = start_s
            return
        with self._lock:
            self._periods_s[self._n % self._periods_s.size] = start_s - last
            self._n += 1

    @property
    def recorded(self) -> int:
        """Periods recorded so far (older ones may be overwritten; see :meth:`since`)."""
        return self._n

    def since(self, recorded: int) -> tuple[int, np.ndarray]:
        """The periods recorded after the first ``recorded`` (those still kept), and the new
        count: how another process mirrors this one (:meth:`extend`)."""
        with self._lock:
            n = min(self._n - max(0, recorded), self._periods_s.size)
            end = self._n % self._periods_s.size
            idx = np.arange(end - n, end) % self._periods_s.size
            return self._n, self._periods_s[idx].copy()

    def extend(self, periods_s: np.ndarray, iterations: int, overruns: int) -> None:
        """Add periods measured elsewhere (:meth:`since`) and take over its totals."""
        periods = np.asarray(periods_s, dtype=float).ravel()[-self._periods_s.size:]
        with self._lock:
            size = self._periods_s.size
            idx = np.arange(self._n, self._n + periods.size) % size
            self._periods_s[idx] = periods
            self._n += periods.size
        self.iterations = iterations
        self.overruns = overruns

    def restart(self) -> None:
        """Forget the last start (after a pause, e.g. a device reconnect): no fake period."""
        self._last_start_s = None

    def periods_s(self, last: int | None = None) -> np.ndarray:
        """The recorded periods, oldest first (at most ``last`` of them)."""
        with self._lock:
            size = self._periods_s.size
            n = min(self._n, size)
            if last is not None:
                n = min(n, last)
            end = self._n % size
            idx = (np.arange(end - n, end)) % size
            return self._periods_s[idx].copy()

    def summary(self, last: int | None = None) -> dict[str, float | int | None]:
        """Rate and period/jitter percentiles in ms (None before two iterations)."""
        periods = self.periods_s(last)
        out: dict[str, float | int | None] = {
            "target_hz": 1.0 / self.target_period_s, "iterations": self.iterations,
            "overruns": self.overruns, "rate_hz": None, "period_p50_ms": None,
            "period_p99_ms": None, "period_max_ms": None, "jitter_p50_ms": None,
            "jitter_p99_ms": None}
        if periods.size:
            jitter = np.abs(periods - self.target_period_s)
            out.update(rate_hz=float(1.0 / periods.mean()),
                       period_p50_ms=float(np.percentile(periods, 50) * 1e3),
                       period_p99_ms=float(np.percentile(periods, 99) * 1e3),
                       period_max_ms=float(periods.max() * 1e3),
                       jitter_p50_ms=float(np.percentile(jitter, 50) * 1e3),
                       jitter_p99_ms=float(np.percentile(jitter, 99) * 1e3))
        return out
