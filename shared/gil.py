"""The interpreter's GIL switch interval for the duration of a block.

CPython lets a thread that waits for the GIL ask the running thread to drop it only after the
*switch interval* (``sys.setswitchinterval``, 5 ms by default). A station's latency-critical
thread (the local display loop, the remote's event loop receiving commands) may wait that
long behind another thread of its own process that runs Python code. A shorter interval
bounds the wait at the cost of more GIL hand-overs (measured per station in docs/speed.md).
"""

from __future__ import annotations

import contextlib
import math
import sys
from collections.abc import Iterator

__all__ = ["switch_interval"]


@contextlib.contextmanager
def switch_interval(seconds: float) -> Iterator[float]:
    """Set the GIL switch interval to ``seconds`` inside the block (0: leave it alone);
    the previous value is restored on exit. Yields the interval in force.

    Raises:
        ValueError: ``seconds`` not finite or negative.
    """
    if not (math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"switch interval must be finite and >= 0, got {seconds!r}")
    previous = sys.getswitchinterval()
    if seconds > 0:
        sys.setswitchinterval(seconds)
    try:
        yield sys.getswitchinterval()
    finally:
        sys.setswitchinterval(previous)
