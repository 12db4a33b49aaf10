"""Helpers shared by the test suite.

Timeouts scale with ``TELETOUCH_TEST_TIMEOUT_SCALE`` (default 1) so slow or loaded
machines do not flake: write ``scaled(2.0)`` instead of ``2.0``, and wait for a condition
with :func:`wait_until` / :func:`async_wait_until` instead of sleeping a fixed time.
Subprocesses started by a test inherit the variable through the environment.

The team kit (design doc, real GelSight data) lies beside the repository, at
``<repo>/../shared``; :func:`kit_path` names a file in it and :func:`require_kit` skips a test
whose kit data is missing, or fails it when ``CI=true``.
"""

from __future__ import annotations

import asyncio
import faulthandler
import os
import re
import shutil
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from shared.protocol import DataMessage, Hop, PlatformState, TactileFrame

TIMEOUT_SCALE = float(os.environ.get("TELETOUCH_TEST_TIMEOUT_SCALE", "1"))

#: the repository's root (this file is ``<repo>/tests/support.py``)
REPO_ROOT = Path(__file__).resolve().parents[1]


#: faulthandler's own, before the suite's fixture made it inert (``tests/conftest.py``)
REAL_DUMP_TRACEBACK_LATER = faulthandler.dump_traceback_later


def assert_ended_by_loop_watchdog(returncode: int | None, stderr: str, frame: str, *,
                                  stuck: str = "", backstop: bool = False) -> None:
    """A process ended by its own event-loop watchdog (:mod:`shared.loop_watchdog`): exit
    code 1, the watch's first line (saying ``stuck`` is what is stuck, when given), or with
    ``backstop`` faulthandler's ``Timeout (H:MM:SS)!``, and every thread's stack, with the
    function ``frame`` among them."""
    assert returncode == 1, (returncode, stderr[-3000:])
    first = (r"^Timeout \(\d+:\d\d:\d\d(\.\d+)?\)!$" if backstop else
             rf"^Event loop watchdog: {re.escape(stuck)}.*; this process ends with exit code 1 "
             r"\(hang_timeout_s \S+ s\)\. Every thread's stack:$")
    assert re.search(first, stderr, re.MULTILINE), stderr[-3000:]
    assert re.search(rf"^  File \".+\", line \d+ in {re.escape(frame)}$", stderr, re.MULTILINE), \
        stderr[-3000:]


def scaled(seconds: float) -> float:
    """Return ``seconds`` times the timeout scale of this machine."""
    return seconds * TIMEOUT_SCALE


def wait_until(predicate: Callable[[], object], timeout_s: float, what: str = "condition",
               *, poll_s: float = 0.005) -> None:
    """Poll ``predicate()`` until it is true; fail the test after ``scaled(timeout_s)``.

    Args:
        predicate: the condition to wait for (called from this thread).
        timeout_s: unscaled longest wait.
        what: what is awaited, for the failure message.
        poll_s: polling period.

    Raises:
        AssertionError: the condition did not hold within the scaled timeout.
    """
    deadline = time.monotonic() + scaled(timeout_s)
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {scaled(timeout_s):.2f} s waiting for {what}")
        time.sleep(poll_s)


async def async_wait_until(predicate: Callable[[], object], timeout_s: float,
                           what: str = "condition", *, poll_s: float = 0.005) -> None:
    """Like :func:`wait_until`, polling with ``asyncio.sleep`` so the event loop runs.

    Raises:
        AssertionError: the condition did not hold within the scaled timeout.
    """
    try:
        async with asyncio.timeout(scaled(timeout_s)):
            while not predicate():
                await asyncio.sleep(poll_s)
    except TimeoutError as err:
        raise AssertionError(
            f"timed out after {scaled(timeout_s):.2f} s waiting for {what}") from err


class MachineStalls:
    """Stalls of this whole process (the machine did not run it: host steal, SIGSTOP, a
    swapped-out page), seen by a thread that sleeps ``tick_s`` at a time: the time it woke
    later than asked, where that exceeded ``over_s``. A timing assertion of a test on this
    shared, sometimes loaded machine may allow for what the machine took away. The thread
    sleeps without the GIL and takes it within the interpreter's switch interval, so the
    event loop (or any other thread) kept busy by the product is not counted as a stall.
    Use as a context manager (also in async code), or :meth:`start` and :meth:`stop`; read
    the figures after the stop, which counts a stall still under way."""

    def __init__(self, tick_s: float = 0.01, over_s: float = 0.03) -> None:
        self.tick_s, self.over_s = tick_s, over_s
        self.stalls_s: list[float] = []
        #: each stall's (start, end), ``time.monotonic`` (asyncio's loop time)
        self.spans: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="machine-stalls", daemon=True)

    def start(self) -> MachineStalls:
        """Start watching; returns self."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop watching (a stall under way is counted); nothing if never started."""
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join()

    def __enter__(self) -> MachineStalls:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _watch(self) -> None:
        while True:
            before = time.monotonic()
            stopped = self._stop.wait(self.tick_s)
            woke = time.monotonic()
            late = woke - before - self.tick_s
            if late > self.over_s:
                self.stalls_s.append(late)
                self.spans.append((woke - late, woke))
            if stopped:
                return

    def overlaps(self, start: float, end: float) -> bool:
        """Whether a stall (widened by ``over_s``, the shortest one seen) overlapped the
        interval from ``start`` to ``end`` (``time.monotonic``)."""
        return any(a - self.over_s < end and start < b + self.over_s for a, b in self.spans)

    def count(self, longer_than_s: float) -> int:
        """How many stalls were longer than ``longer_than_s``."""
        return sum(1 for s in self.stalls_s if s > longer_than_s)

    @property
    def total_s(self) -> float:
        """The stalls' total."""
        return sum(self.stalls_s)


def free_tcp_port() -> int:
    """Return a TCP port on 127.0.0.1 that is free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def kit_path(*parts: str) -> Path:
    """A path inside the team kit, ``<repo>/../shared/<parts...>`` (may not exist)."""
    return (REPO_ROOT / ".." / "shared").resolve().joinpath(*parts)


def require_kit(path: Path) -> Path:
    """Return ``path`` if the kit data is there; skip the test otherwise (fail under CI).

    Raises:
        pytest.fail.Exception: the data is missing and the environment says ``CI=true``.
        pytest.skip.Exception: the data is missing outside CI.
    """
    if path.exists():
        return path
    message = f"team kit data not found at {path} (the kit belongs at {kit_path()})"
    if os.environ.get("CI", "").strip().lower() in ("true", "1", "yes"):
        pytest.fail(message)
    pytest.skip(message)


def teletouch_cmd() -> list[str]:
    """The ``teletouch`` command as a new user runs it (the console script, else the module)."""
    exe = shutil.which("teletouch")
    return [exe] if exe else [sys.executable, "-m", "lab.cli"]


def motion_state(seq: int, motion_us: int | None, capture_us: int) -> PlatformState:
    """A ``platform_state`` stamped as a local station stamps it: ``local.motion`` (when
    given) and ``local.capture``."""
    capture = Hop("local", "capture", capture_us)
    hops = (capture,) if motion_us is None else (Hop("local", "motion", motion_us), capture)
    return PlatformState(seq=seq, ts_us=capture_us, hops=hops)


def motion_frame(seq: int, motion_us: int | None, capture_us: int) -> TactileFrame:
    """A 4 x 4 ``tactile_frame`` answering :func:`motion_state` ``(seq, motion_us,
    capture_us)``: that state's stamps and the remote's own, as the remote stamps them."""
    hops = (*motion_state(seq, motion_us, capture_us).hops,
            Hop("remote", "arm_command", capture_us + 100),
            Hop("remote", "sensor_frame", capture_us + 200),
            Hop("remote", "sensor_arrival", capture_us + 250),
            Hop("remote", "tactile_ready", capture_us + 300))
    return TactileFrame(seq=seq, ts_us=capture_us + 200, hops=hops,
                        layers={"height_mm": np.zeros((4, 4), np.float32)})


def motion_of(msg: DataMessage) -> int | None:
    """The ``local.motion`` stamp of a message (None without one)."""
    return next((h.t_us for h in msg.hops if h.stage == "motion" and h.clock == "local"),
                None)


class NotifySocket:
    """A socket listening as systemd's ``NOTIFY_SOCKET`` does (abstract namespace), read all
    along by a thread as systemd reads it (a unix datagram queue holds as few as 10), keeping
    what arrives with the sender's pid (``SO_PASSCRED``, as systemd checks ``NotifyAccess``)."""

    def __init__(self) -> None:
        import threading
        import uuid

        self.name = f"@teletouch-test-{uuid.uuid4().hex}"
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
        self._sock.bind("\0" + self.name[1:])
        self._sock.settimeout(0.1)  # how soon the reader sees close()
        self.messages: list[tuple[int, str]] = []
        self._arrived = threading.Condition()
        self._closed = False
        self._reader = threading.Thread(target=self._read, name="notify-socket", daemon=True)
        self._reader.start()

    def env(self, watchdog_usec: int | None = None) -> dict[str, str]:
        """The variables systemd gives a ``Type=notify`` service (with ``WatchdogSec=``)."""
        env = {"NOTIFY_SOCKET": self.name}
        if watchdog_usec is not None:
            env["WATCHDOG_USEC"] = str(watchdog_usec)
        return env

    def _read(self) -> None:
        import struct

        creds = struct.calcsize("iII")
        while not self._closed:
            try:
                data, ancdata, _, _ = self._sock.recvmsg(4096, socket.CMSG_SPACE(creds))
            except TimeoutError:
                continue
            except OSError:
                return
            pid = -1
            for level, kind, payload in ancdata:
                if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS:
                    pid = struct.unpack("iII", payload[:creds])[0]
            with self._arrived:
                self.messages.append((pid, data.decode()))
                self._arrived.notify_all()

    def texts(self, pid: int | None = None) -> list[str]:
        """What has arrived (from ``pid`` only, when given)."""
        with self._arrived:
            return [text for sender, text in self.messages if pid is None or sender == pid]

    def until(self, predicate: Callable[[list[tuple[int, str]]], bool],
              timeout_s: float) -> None:
        """Until ``predicate(messages)`` holds, woken by each message (not polled).

        Raises:
            TimeoutError: not within ``timeout_s``.
        """
        with self._arrived:
            if not self._arrived.wait_for(lambda: predicate(list(self.messages)), timeout_s):
                raise TimeoutError(f"not told within {timeout_s} s: {self.messages}")

    async def wait_for(self, predicate: Callable[[list[tuple[int, str]]], bool],
                       timeout_s: float) -> None:
        """:meth:`until`, from a coroutine (the event loop goes on meanwhile)."""
        await asyncio.to_thread(self.until, predicate, timeout_s)

    def close(self) -> None:
        self._closed = True
        self._reader.join()
        self._sock.close()
