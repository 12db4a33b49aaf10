"""Where the pad was at a given moment: recent arm positions, interpolated.

A tactile frame is placed on the phantom by the pad position it was felt at. The station
reads the arm (its monitor loop, 250 Hz, and the frame pipeline) and the sensor captures
its image at other moments; at 45 mm/s a 17 ms difference moves the frame by 0.77 mm, which
smears a tumor's edge in the palpation maps (and made a benign tumor look infiltrating on
a loaded machine). So every arm reading is kept with the time it was read (the station's
clock, :func:`shared.timebase.now_us`, the clock of the sensor frame's capture stamp) and the
frame takes the position interpolated at its capture time.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections import deque
from collections.abc import Sequence

from remote_site.arm.base import Vec3

__all__ = ["PoseHistory"]


class PoseHistory:
    """The last ``size`` arm positions with their read times (thread-safe).

    Args:
        size: positions kept (at 250 Hz, 64 cover a quarter of a second).
        max_hold_us: a time after the newest reading by at most this much gets the newest
            position (no extrapolation); later, or before the oldest reading: unknown.
    """

    def __init__(self, size: int = 64, max_hold_us: int = 50_000) -> None:
        self._samples: deque[tuple[int, Vec3]] = deque(maxlen=size)
        self._lock = threading.Lock()
        self.max_hold_us = max_hold_us

    def add(self, t_us: int, position_mm: Sequence[float]) -> None:
        """Keep one reading (non-finite positions are ignored)."""
        x, y, z = (float(v) for v in position_mm)
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            return
        with self._lock:
            self._samples.append((int(t_us), (x, y, z)))

    def __len__(self) -> int:
        return len(self._samples)

    def at(self, t_us: int) -> Vec3 | None:
        """The position at ``t_us``, linearly interpolated between the readings around it.

        Returns:
            The position, or None when ``t_us`` is before the oldest reading kept, more
            than ``max_hold_us`` after the newest, or nothing was read yet.
        """
        with self._lock:
            samples = sorted(self._samples)  # two threads add: nearly, not strictly, ordered
        if not samples:
            return None
        times = [t for t, _ in samples]
        i = bisect.bisect_right(times, t_us)
        if i == len(samples):
            t_last, p_last = samples[-1]
            return p_last if t_us - t_last <= self.max_hold_us else None
        if i == 0:
            return samples[0][1] if t_us == times[0] else None
        (t0, p0), (t1, p1) = samples[i - 1], samples[i]
        if t1 == t0:
            return p1
        w = (t_us - t0) / (t1 - t0)
        return (p0[0] + w * (p1[0] - p0[0]), p0[1] + w * (p1[1] - p0[1]),
                p0[2] + w * (p1[2] - p0[2]))
