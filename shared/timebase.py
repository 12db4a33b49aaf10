"""The one clock every Tele-Touch timestamp comes from.

Timestamps are integer microseconds since the Unix epoch, on a clock that never steps: the
wall clock read once when the process starts, advanced by the monotonic clock
(``time.monotonic_ns``). An NTP step, a person setting the date or a VM's clock jump while
a station runs therefore never makes its stamps jump, and so never makes an arm command or a
tactile frame look younger (or older) than it is. The monotonic clock is still slewed by
NTP (its rate follows the true second), so the stamps stay within a few ppm of true time over
a session. Hosts need not be synchronised: the relay estimates each station's offset against
its own clock with a bound on the error (see :mod:`shared.clocksync`), and a jump that does
reach the stamps (a suspended and resumed host, whose monotonic clock stood still, or a
client written by someone else) is detected there as a clock step.
"""

from __future__ import annotations

import time

__all__ = ["adopt_wall_anchor", "monotonic_s", "now_us", "wall_anchor_ns"]

#: wall-clock time minus monotonic time at start-up (ns)
_ANCHOR_NS = time.time_ns() - time.monotonic_ns()


def wall_anchor_ns() -> int:
    """The wall clock minus the monotonic clock when this process started (ns)."""
    return _ANCHOR_NS


def adopt_wall_anchor(anchor_ns: int) -> None:
    """Stamp on another process's clock: its :func:`wall_anchor_ns` (a station's child).

    The monotonic clock is system wide, so a child that adopts its parent's anchor stamps
    exactly as the parent does, also when the wall clock was stepped between their starts.
    """
    global _ANCHOR_NS
    _ANCHOR_NS = int(anchor_ns)


def now_us() -> int:
    """Return the time in integer microseconds since the Unix epoch (never steps)."""
    return (time.monotonic_ns() + _ANCHOR_NS) // 1000


def monotonic_s() -> float:
    """Return a monotonic time in seconds, for periods and deadlines (never sent on the wire)."""
    return time.monotonic()
