"""A process's own watchdog on its asyncio event loop: stuck loop, stacks written, process ended.

A server whose event loop is stuck (a busy loop, a call that never returns, threads
deadlocked) is alive to everything that watches processes: ``restart: on-failure`` in a
container, systemd's ``Restart=`` without a watchdog, a supervisor waiting for its children
to exit. It serves nothing and is never restarted. :func:`loop_watchdog` arms
:func:`faulthandler.dump_traceback_later` with ``exit=True`` and re-arms it from the loop
every ``REARM_S`` (or a quarter of the timeout if that is less): if the loop does not come
back within the timeout, faulthandler's own thread (C code, which needs neither the loop nor
the GIL) writes every thread's Python stack to standard error and ends the process with exit
code 1, for whatever supervises it to start it again. The process ends between one re-arm
period before the timeout and the timeout after the loop last turned.

A call the loop awaits in another thread (a frame's sensor read and reconstruction in an
executor) can hang while the loop turns on: the process then serves on without the work that
call was for, and nothing restarts it. Such calls are entered in a :class:`WaitedCalls` given
to the watchdog (``with calls.waiting_for("what"): await ...``): one that has not returned
after the timeout ends the process the same way (at the next re-arm: up to a re-arm period
later), with its thread's stack among those written (a WARNING names it at half the
timeout).

What it cannot tell apart from a hang: a host or process that was paused for longer than the
timeout (a paused VM or container, a debugger), whose clock jumps on resume before the loop
runs again. Such a process ends and is restarted. Nor does it see a loop that turns while its
tasks wait on each other for ever (an asyncio-level deadlock).

faulthandler has one such timer per process: this module is its only user, and a process
should enter the block once (a second block would take the timer over).
"""

from __future__ import annotations

import asyncio
import contextlib
import faulthandler
import itertools
import logging
import math
import time
from collections.abc import AsyncIterator, Iterator

from shared.errors import ConfigError

__all__ = ["REARM_S", "WaitedCalls", "check_hang_timeout", "loop_watchdog", "rearm_period_s"]

log = logging.getLogger(__name__)

#: the longest period between two re-arms
REARM_S = 0.5


def rearm_period_s(timeout_s: float) -> float:
    """How often a loop watched with ``timeout_s`` reports that it turns."""
    return min(REARM_S, timeout_s / 4)


def check_hang_timeout(key: str, value: object) -> None:
    """A process's ``hang_timeout_s`` setting: 0 (no watchdog) or finite seconds >= 1.

    Raises:
        ConfigError: anything else, naming ``key``.
    """
    if isinstance(value, bool) or not isinstance(value, int | float) or not (
            value == 0 or (math.isfinite(value) and value >= 1.0)):
        raise ConfigError(f"{key} must be 0 (no watchdog) or a finite number of seconds >= 1, "
                          f"got {value!r}")


class WaitedCalls:
    """Calls in other threads that the event loop awaits (a device read, a frame's
    processing in an executor), with when each began: a loop watched with them
    (:func:`loop_watchdog`) counts one that has not returned within its timeout as a stuck
    loop. Entered and left in the event loop's thread (the block wraps the ``await``)."""

    def __init__(self) -> None:
        self._began: dict[int, tuple[str, float]] = {}
        self._keys = itertools.count()

    @contextlib.contextmanager
    def waiting_for(self, what: str) -> Iterator[None]:
        """The block awaits a call in another thread; ``what`` names it in the log."""
        key = next(self._keys)
        self._began[key] = (what, time.monotonic())
        try:
            yield
        finally:
            del self._began[key]

    def oldest(self) -> tuple[str, float] | None:
        """The call waited for longest: what it is and when it began (``time.monotonic``);
        None when none is."""
        return min(self._began.values(), key=lambda call: call[1], default=None)


@contextlib.asynccontextmanager
async def loop_watchdog(timeout_s: float | None, calls: WaitedCalls | None = None
                        ) -> AsyncIterator[None]:
    """While the block runs, end this process (exit code 1, every thread's stack written to
    standard error first) if the running event loop makes no progress for ``timeout_s``, or
    one of ``calls`` has not returned after ``timeout_s`` (seen by the next re-arm: up to a
    re-arm period later).

    Args:
        timeout_s: seconds (at least 0.1); None or 0: no watchdog.
        calls: the calls in other threads the loop awaits (None: none watched).

    Raises:
        ValueError: a timeout below 0.1 s.
        RuntimeError, OSError: standard error cannot be written to (no watchdog then).
    """
    if not timeout_s:
        yield
        return
    if timeout_s < 0.1:
        raise ValueError(f"a loop watchdog timeout of {timeout_s!r} s is below 0.1 s")
    limit_s: float = timeout_s
    period_s = rearm_period_s(limit_s)
    faulthandler.dump_traceback_later(limit_s, exit=True)  # armed now: an error is raised
    log.info("event loop watchdog: this process ends, its stacks written, if its event loop is "
             "stuck, or a call it waits for in another thread has not returned, for %g s "
             "(hang_timeout_s; 0 turns it off)", limit_s)

    async def rearm() -> None:
        warned: tuple[str, float] | None = None
        while True:
            await asyncio.sleep(period_s)
            oldest = calls.oldest() if calls is not None else None
            waited_s = 0.0 if oldest is None else time.monotonic() - oldest[1]
            if waited_s >= limit_s:  # that call is stuck: end now, as for a stuck loop
                faulthandler.dump_traceback_later(1e-3, exit=True)
                return
            faulthandler.dump_traceback_later(limit_s, exit=True)  # replaces the last
            if oldest is not None and oldest != warned and waited_s >= limit_s / 2:
                warned = oldest
                log.warning("%s has not returned for %.1f s: this process ends, its stacks "
                            "written, if it has not returned after %g s (hang_timeout_s)",
                            oldest[0], waited_s, limit_s)

    def ended(task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            log.error("the event loop's watchdog stopped: %r; this process is not watched",
                      task.exception())
            faulthandler.cancel_dump_traceback_later()

    task = asyncio.get_running_loop().create_task(rearm(), name="loop-watchdog")
    task.add_done_callback(ended)
    try:
        yield
    finally:
        task.cancel()
        faulthandler.cancel_dump_traceback_later()
