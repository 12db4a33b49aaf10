"""The one clock every Tele-Touch timestamp comes from.

Timestamps are integer microseconds of the host's wall clock (``time.time_ns() // 1000``).
Hosts need not be synchronised: the relay estimates each station's offset against its own
clock (see :mod:`shared.clocksync`) and the latency ledger corrects with it.
"""

from __future__ import annotations

import time

__all__ = ["monotonic_s", "now_us"]


def now_us() -> int:
    """Return the wall-clock time in integer microseconds since the Unix epoch."""
    return time.time_ns() // 1000


def monotonic_s() -> float:
    """Return a monotonic time in seconds, for periods and deadlines (never sent on the wire)."""
    return time.monotonic()
