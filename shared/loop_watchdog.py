"""A process's own watchdog on its asyncio event loop: stuck loop, stacks written, process ended.

A server whose event loop is stuck (a busy loop, a call that never returns, threads
deadlocked) is alive to everything that watches processes: ``restart: on-failure`` in a
container, systemd's ``Restart=`` without a watchdog, a supervisor waiting for its children
to exit. It serves nothing and is never restarted. :func:`loop_watchdog` watches the loop from
a thread of its own: the loop says that it turns every ``REARM_S`` (or a quarter of the
timeout if that is less), and the thread, which wakes as often, ends the process once the loop
has not turned for the timeout. It writes a line saying what is stuck and every thread's
Python stack to standard error first and exits with code 1, for whatever supervises the
process to start it again. The process ends between the timeout and one period after it,
counted from when the loop last turned (between one period before and one after, counted
from when it got stuck).

The stacks are read from the watch's thread with Python's own frame objects, under the
interpreter's lock (GIL), which keeps every read safe while the other threads run on.
:func:`faulthandler.dump_traceback_later`, which
this module used alone before, reads them from a C thread while they run on: a process whose
display thread ran on beside a stuck loop died of SIGSEGV (exit code -11) part way through
its stacks. A loop stuck in C code that holds the GIL for good (so that no other thread runs,
the watch's included) is the one case a Python thread cannot see; there faulthandler stays the
backstop: the watch's thread re-arms its timer ``BACKSTOP_TIMEOUTS`` (2) timeouts ahead at
each of its wakes, so once no Python thread but the stuck one has run for two timeouts,
faulthandler's thread writes the stacks (safe then: every other thread waits for the GIL) and
ends the process with exit code 1, its first line ``Timeout (H:MM:SS)!``. That line also
ends a process that was paused for two timeouts or more (below, paused between a timeout and
two, the watch acts first on resume); its stacks are then read while the threads run again,
as before.

A call the loop awaits in another thread (a frame's sensor read and reconstruction in an
executor) can hang while the loop turns on: the process then serves on without the work that
call was for, and nothing restarts it. Such calls are entered in a :class:`WaitedCalls` given
to the watchdog (``with calls.waiting_for("what"): await ...``): one that has not returned
after the timeout ends the process the same way (at the watch's next wake: up to a period
later), with its thread's stack among those written (a WARNING names it at half the
timeout). A call the loop awaited when the loop itself got stuck is named after the loop
(``the event loop has not turned for 30.1 s (a frame's processing awaited for 30.4 s)``).

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
import os
import sys
import threading
import time
import types
from collections.abc import AsyncIterator, Iterator

from shared.errors import ConfigError

__all__ = ["BACKSTOP_TIMEOUTS", "REARM_S", "WaitedCalls", "check_hang_timeout", "end_process",
           "loop_watchdog", "rearm_period_s", "stacks"]

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
    loop. Entered and left in the event loop's thread (the block wraps the ``await``); read
    from the watch's."""

    def __init__(self) -> None:
        self._began: dict[int, tuple[str, float]] = {}
        self._keys = itertools.count()
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def waiting_for(self, what: str) -> Iterator[None]:
        """The block awaits a call in another thread; ``what`` names it in the log."""
        key = next(self._keys)
        with self._lock:
            self._began[key] = (what, time.monotonic())
        try:
            yield
        finally:
            with self._lock:
                del self._began[key]

    def oldest(self) -> tuple[str, float] | None:
        """The call waited for longest: what it is and when it began (``time.monotonic``);
        None when none is."""
        with self._lock:
            return min(self._began.values(), key=lambda call: call[1], default=None)


def stacks() -> str:
    """Every other thread's Python stack, most recent call first, as faulthandler writes
    them (without source lines: no file is read). Safe beside running threads: the frames
    are read under the interpreter's lock."""
    names = {thread.ident: thread.name for thread in threading.enumerate()}
    lines: list[str] = []
    for ident, frame in sys._current_frames().items():
        if ident == threading.get_ident():
            continue  # the caller's own (the watch's)
        lines.append(f"Thread 0x{ident:016x} {names.get(ident, '?')!r} "
                     "(most recent call first):")
        at: types.FrameType | None = frame
        while at is not None:
            lines.append(f'  File "{at.f_code.co_filename}", line {at.f_lineno} in '
                         f"{at.f_code.co_name}")
            at = at.f_back
        lines.append("")
    return "\n".join(lines)


def end_process(report: str) -> None:
    """Write ``report`` and every thread's stack to standard error (its file descriptor: no
    lock of ``sys.stderr`` or of logging is taken) and end this process with exit code 1 at
    once (:func:`os._exit`: nothing else runs first), whatever fails on the way. The test
    suite's process replaces it (``tests/conftest.py``)."""
    try:
        data = f"{report}\n{stacks()}".encode(errors="replace")
        while data:
            data = data[os.write(2, data):]
    finally:
        os._exit(1)


#: faulthandler's timer, the backstop, ends the process this many timeouts after the watch
#: last ran: the watch acts first on a process that was paused for less than that
BACKSTOP_TIMEOUTS = 2


class _Watch:
    """The watch's thread: wakes every ``period_s``; ends the process (:func:`end_process`)
    once the loop's last turn (:attr:`turned`) or the oldest of ``calls`` is ``limit_s``
    old; otherwise re-arms faulthandler's timer, the backstop, ``BACKSTOP_TIMEOUTS`` timeouts
    ahead, writing to file descriptor ``fd``."""

    def __init__(self, limit_s: float, period_s: float, calls: WaitedCalls | None,
                 fd: int) -> None:
        self.limit_s = limit_s
        self.period_s = period_s
        self.calls = calls
        self.fd = fd
        #: when the event loop last turned (``time.monotonic``), set from the loop's thread
        self.turned = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="loop-watchdog", daemon=True)

    def arm(self) -> None:
        """(Re-)arm the backstop."""
        faulthandler.dump_traceback_later(BACKSTOP_TIMEOUTS * self.limit_s, file=self.fd,
                                          exit=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Stop watching, and the backstop (from the loop's thread; returns once the watch's
        thread has stopped)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()
        faulthandler.cancel_dump_traceback_later()

    def _run(self) -> None:
        backstop = True
        while not self._stop.wait(self.period_s):
            stuck = self.stuck(time.monotonic())
            if stuck is not None:
                end_process(f"Event loop watchdog: {stuck}; this process ends with exit "
                            f"code 1 (hang_timeout_s {self.limit_s:g} s). Every thread's "
                            "stack:")
                return
            if backstop:
                try:
                    self.arm()  # replaces the last
                except Exception as exc:  # said; the watch itself goes on
                    backstop = False
                    faulthandler.cancel_dump_traceback_later()
                    log.error("the event loop watchdog's backstop (faulthandler's timer) "
                              "failed: %r; a loop stuck in C code that keeps the "
                              "interpreter's lock is not watched any more", exc)

    def stuck(self, now: float) -> str | None:
        """What is stuck at ``now``: the loop, the oldest waited call, or None. A call
        waited for the timeout while the loop has not turned for two periods either (an
        await cannot end while the loop stands still) is judged at a later wake: the call's
        if the loop turns again, the loop's once it has stood still for the timeout."""
        stale_s = now - self.turned
        oldest = self.calls.oldest() if self.calls is not None else None
        waited_s = 0.0 if oldest is None else now - oldest[1]
        if stale_s >= self.limit_s:
            text = f"the event loop has not turned for {stale_s:.1f} s"
            if oldest is not None and waited_s >= self.limit_s:
                text += f" ({oldest[0]} awaited for {waited_s:.1f} s)"
            return text
        if oldest is not None and waited_s >= self.limit_s and stale_s <= 2 * self.period_s:
            return f"{oldest[0]} has not returned for {waited_s:.1f} s"
        return None


@contextlib.asynccontextmanager
async def loop_watchdog(timeout_s: float | None, calls: WaitedCalls | None = None
                        ) -> AsyncIterator[None]:
    """While the block runs, end this process (exit code 1, every thread's stack written to
    standard error first) if the running event loop makes no progress for ``timeout_s``, or
    one of ``calls`` has not returned after ``timeout_s`` (seen at the watch's next wake: up
    to a period later).

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
    # sys.stderr's descriptor, taken once (an error is raised here when there is none): the
    # re-arms then neither look sys.stderr up (a redirect would break them) nor flush it
    faulthandler.dump_traceback_later(BACKSTOP_TIMEOUTS * limit_s, exit=True)
    try:
        watch = _Watch(limit_s, period_s, calls, sys.stderr.fileno())
        watch.arm()
        watch.start()
    except BaseException:
        faulthandler.cancel_dump_traceback_later()
        raise
    log.info("event loop watchdog: this process ends, its stacks written, if its event loop is "
             "stuck, or a call it waits for in another thread has not returned, for %g s "
             "(hang_timeout_s; 0 turns it off)", limit_s)

    async def turning() -> None:
        warned: tuple[str, float] | None = None
        while True:
            await asyncio.sleep(period_s)
            watch.turned = time.monotonic()
            oldest = calls.oldest() if calls is not None else None
            waited_s = 0.0 if oldest is None else watch.turned - oldest[1]
            if oldest is not None and oldest != warned and limit_s / 2 <= waited_s < limit_s:
                warned = oldest
                log.warning("%s has not returned for %.1f s: this process ends, its stacks "
                            "written, if it has not returned after %g s (hang_timeout_s)",
                            oldest[0], waited_s, limit_s)

    loop = asyncio.get_running_loop()
    leaving = False
    task: asyncio.Task[None]

    def keep_turning() -> asyncio.Task[None]:
        turner = loop.create_task(turning(), name="loop-watchdog")
        turner.add_done_callback(ended)
        return turner

    def ended(done: asyncio.Task[None]) -> None:
        # the loop turns on without this task, and the watch would end it as stuck
        nonlocal task
        if leaving:
            return
        if done.cancelled():  # by something that cancels every task: turn on
            with contextlib.suppress(RuntimeError):  # (not once the loop has closed)
                task = keep_turning()
                return
        watch.stop()
        log.error("the event loop's watchdog stopped: %s; this process is not watched",
                  "the loop has closed" if done.cancelled() else repr(done.exception()))

    task = keep_turning()
    try:
        yield
    finally:
        leaving = True
        task.cancel()
        watch.stop()
