"""The platform read in a process of its own; the newest sample in shared memory.

The station's 1 kHz display loop shares its interpreter, and so the GIL, with every other
thread of the station. The platform's threads were among the busiest: the driver's reader
wakes for every encoder sample (1 kHz), the :class:`PlatformReader` watches its health, and
with the ``sim`` backend the simulated encoder board ticks at 1 kHz beside them. On a busy
host the driver's reader, woken with data waiting, was seen kept from the GIL for 0.25-1 s
(``benchmarks/results/platform_silence.md``), and every wake-up of those threads is one the
display loop may have to wait for.

:class:`ProcessPlatformReader` runs the platform driver and its :class:`PlatformReader`
(reopen with backoff, silence handling, the scripted motion's end) in a child process
(``python -m local_site.agent.platform_child``: a fresh interpreter, nothing of the
station's threads copied). The driver's reader thread copies every sample into a small
shared-memory record as it decodes it (``XYZPlatform.sample_listener``) and the child's main
thread adds the reader's health every 20 ms; the station reads the record (no system call,
no lock: a counter that is odd while the child writes, :class:`SampleRecord`) wherever it
read the in-process reader. Same attributes, same safety meaning:

* ``healthy`` is false while the child reports the device lost and whenever the newest
  sample is older than the read timeout by its own capture stamp (the child hung, was
  stopped or died, or reconnected without a sample yet): the display loop then puts the pins
  in their safe state, and never renders an old position as the current one;
* a child that died, or whose heartbeat stopped for ``hang_timeout_s``, is (killed and)
  started again with the same backoff as a device reopen: the station never gives up; the
  counters carry over and each restart counts as a loss;
* the child ends with the station: on :meth:`ProcessPlatformReader.stop`, at the end of its
  standard input (the station's process is gone), and when its parent changes. It runs in
  a process group of its own, so a Ctrl-C at the terminal reaches the station, which stops
  it (the same session: the kernel's autogroup scheduling still counts it with the
  station's processes).

Measured (``docs/speed.md`` section 13): on a quiet machine the demo used less CPU, its
display loop ran faster with less jitter, and motion-to-touch was shorter; beside four busy
processes the loop still gained but motion-to-touch lost, and with the simulated board's
thread in the child its reader was still seen starved for 259 ms.

The record lives in an anonymous file (``memfd``) handed to each child by descriptor: nothing
is named on a file system, so nothing is left behind by a station that was killed. Capture
stamps cross on the monotonic clock (system wide) and are put back on the station's
wall-clock anchor, so a wall-clock step between the two processes' starts cannot shift them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import mmap
import os
import select
import struct
import subprocess
import sys
import tempfile
import threading
from dataclasses import dataclass
from typing import Any

from local_site.agent.platform_reader import reopen_after, stale_since_s
from local_site.platform.base import PlatformSample, PlatformStats
from shared.counters import add_counters
from shared.errors import ConfigError
from shared.timebase import monotonic_s, wall_anchor_ns

#: a child whose heartbeat stopped this long is killed and started again (more than its
#: ``reopen_after_s``: :class:`ProcessPlatformReader` refuses less)
HANG_TIMEOUT_S = 15.0

__all__ = ["HEARTBEAT_S", "ProcessPlatformReader", "ReaderHealth", "RecordView", "SampleRecord",
           "healthy_copy"]

log = logging.getLogger(__name__)

#: how often the child publishes its health and checks its parent
HEARTBEAT_S = 0.02
#: how often the station's supervisor looks at its child
_SUPERVISE_S = 0.1
#: bytes kept of the child's last error message
_ERROR_BYTES = 240
#: copies a reader tries while the writer is inside a write (a write takes microseconds);
#: then it keeps what it had: the display loop never waits for the child
_TORN_TRIES = 20
#: the child's longest clean stop (its reader may be inside a 2-5 s device open)
_CHILD_STOP_S = 6.0


@dataclass(frozen=True, slots=True)
class ReaderHealth:
    """The child's :class:`PlatformReader` state, as the record last carried it.

    Attributes:
        healthy: the child's reader had the device.
        lost_since_mono_s: when it lost it (monotonic clock; None: not lost).
        reads: samples its reader took.
        errors: loss episodes.
        reconnects: device reopens.
        recoveries: silences that ended on the open port.
        motion_done: the scripted motion ended.
        heartbeat_s: when the child last published this (monotonic clock).
        last_error: its last error message (None: none).
    """

    healthy: bool
    lost_since_mono_s: float | None
    reads: int
    errors: int
    reconnects: int
    recoveries: int
    motion_done: bool
    heartbeat_s: float
    last_error: str | None


_NOT_STARTED = ReaderHealth(False, None, 0, 0, 0, 0, False, 0.0, None)


class SampleRecord:
    """One platform sample and the reader's health in shared memory (one writing process).

    Layout (little endian): a ``uint64`` counter, odd while the writer is inside, then the
    sample (position and velocity, 6 x ``float64``; capture time on the monotonic clock,
    sequence and board time, 3 x ``int64``; clamped and present flags), then the health
    (healthy and motion-done flags, the time the device was lost or NaN, four counters, the
    heartbeat on the monotonic clock) and the last error (length, ``0xFFFF`` for none, then
    UTF-8). A reader copies the record and keeps the copy when the counter was even and
    unchanged around it. The writing process's threads take turns (a lock).

    Args:
        fd: map the record behind this descriptor (shared with another process); None:
            create a new one (an anonymous file), see :attr:`fd`.
    """

    _HEAD = struct.Struct("<Q")
    _SAMPLE = struct.Struct("<6d3q??")
    _HEALTH = struct.Struct("<??d4qdH")
    _SAMPLE_AT = _HEAD.size
    _HEALTH_AT = _SAMPLE_AT + _SAMPLE.size
    _ERROR_AT = _HEALTH_AT + _HEALTH.size
    SIZE = _ERROR_AT + _ERROR_BYTES

    def __init__(self, fd: int | None = None) -> None:
        self._owner = fd is None
        if fd is None:
            fd = _anonymous_file(self.SIZE)
        #: the descriptor behind the record (the creator's; pass it to the writer's process)
        self.fd = fd
        self._buf = mmap.mmap(fd, self.SIZE)
        self._anchor_us = wall_anchor_ns() // 1000
        self._write_lock = threading.Lock()
        if self._owner:
            self.write_health(_NOT_STARTED)

    # ------------------------------------------------------------------ writer (the child)

    def claim(self) -> None:
        """Become the writer: one that died inside a write left the counter odd, and the
        record half new, half old; it is closed as not healthy in the same step (before, the
        mixed sample read as consistent, under the dead writer's healthy health; found by
        audit), so nothing renders from it until the next writer's first health."""
        with self._write_lock:
            counter = self.counter
            if counter & 1:
                now = monotonic_s()
                self._HEALTH.pack_into(self._buf, self._HEALTH_AT, False, False, now, 0, 0, 0,
                                       0, now, 0xFFFF)
                self._HEAD.pack_into(self._buf, 0, counter + 1)

    def write_sample(self, sample: PlatformSample) -> None:
        """Publish a sample (its capture time goes over on the monotonic clock)."""
        (px, py, pz), (vx, vy, vz) = sample.position_mm, sample.velocity_mm_s
        with self._write_lock:
            counter = self.counter + 1
            self._HEAD.pack_into(self._buf, 0, counter)
            self._SAMPLE.pack_into(self._buf, self._SAMPLE_AT, px, py, pz, vx, vy, vz,
                                   sample.t_us - self._anchor_us, sample.seq,
                                   sample.board_t_us, sample.clamped, True)
            self._HEAD.pack_into(self._buf, 0, counter + 1)

    def write_health(self, health: ReaderHealth) -> None:
        """Publish the reader's state and its heartbeat."""
        error = (health.last_error or "").encode("utf-8", "replace")[:_ERROR_BYTES]
        lost = math.nan if health.lost_since_mono_s is None else health.lost_since_mono_s
        with self._write_lock:
            counter = self.counter + 1
            self._HEAD.pack_into(self._buf, 0, counter)
            self._HEALTH.pack_into(self._buf, self._HEALTH_AT, health.healthy,
                                   health.motion_done, lost, health.reads, health.errors,
                                   health.reconnects, health.recoveries, health.heartbeat_s,
                                   len(error) if health.last_error is not None else 0xFFFF)
            self._buf[self._ERROR_AT:self._ERROR_AT + len(error)] = error
            self._HEAD.pack_into(self._buf, 0, counter + 1)

    # ------------------------------------------------------------------ reader (the station)

    @property
    def counter(self) -> int:
        """The write counter (even between writes; it changes with every write)."""
        value: int = self._HEAD.unpack_from(self._buf, 0)[0]
        return value

    def read(self) -> tuple[int, PlatformSample | None, ReaderHealth] | None:
        """A consistent copy.

        Returns:
            (counter, the sample or None before the first, the health); None when the
            writer was inside a write at each of :data:`_TORN_TRIES` tries (it died there,
            is stopped, or was descheduled): the caller keeps its previous copy.
        """
        buf = self._buf
        for _ in range(_TORN_TRIES):
            before = self._HEAD.unpack_from(buf, 0)[0]
            if before & 1:
                continue
            raw = buf[self._SAMPLE_AT:self.SIZE]
            if self._HEAD.unpack_from(buf, 0)[0] == before:
                break
        else:
            return None
        px, py, pz, vx, vy, vz, t_mono_us, seq, board_t_us, clamped, present = \
            self._SAMPLE.unpack_from(raw, 0)
        sample = PlatformSample(position_mm=(px, py, pz), velocity_mm_s=(vx, vy, vz),
                                t_us=t_mono_us + self._anchor_us, seq=seq,
                                board_t_us=board_t_us, clamped=clamped) if present else None
        healthy, done, lost, reads, errors, reconnects, recoveries, beat, n_err = \
            self._HEALTH.unpack_from(raw, self._HEALTH_AT - self._SAMPLE_AT)
        at = self._ERROR_AT - self._SAMPLE_AT
        error = None if n_err == 0xFFFF else raw[at:at + n_err].decode("utf-8", "replace")
        return before, sample, ReaderHealth(
            healthy=healthy, lost_since_mono_s=None if math.isnan(lost) else lost,
            reads=reads, errors=errors, reconnects=reconnects, recoveries=recoveries,
            motion_done=done, heartbeat_s=beat, last_error=error)

    def close(self) -> None:
        """Unmap (the creator also closes its descriptor: the file is gone with the last)."""
        self._buf.close()
        if self._owner:
            os.close(self.fd)


_Copy = tuple[int, PlatformSample | None, ReaderHealth]


class RecordView:
    """The newest consistent copy of a :class:`SampleRecord`, for each thread that reads it.

    A thread keeps its last copy and copies the record again only when its counter moved;
    a write that does not finish (the writer died or is stopped inside it) is not retried
    for the same counter. Nothing here waits for the writer: the real-time display loop
    reads through it.

    Args:
        record: the record (mapped in this process).
        read_timeout_s: the oldest a sample may be, by its capture stamp, for the platform
            to count healthy (:meth:`healthy`).
    """

    def __init__(self, record: SampleRecord, read_timeout_s: float) -> None:
        self.record = record
        self.read_timeout_s = read_timeout_s
        self._local = threading.local()
        self._torn_counter: int | None = None

    def read(self) -> _Copy | None:
        """This thread's newest copy; None before one could be taken, or once unmapped."""
        local = self._local
        cached: _Copy | None = getattr(local, "cached", None)
        try:
            counter = self.record.counter
            if counter == self._torn_counter:  # the same unfinished write: do not retry
                return cached
            if cached is not None and counter == cached[0]:
                return cached
            read = self.record.read()
        except ValueError:  # unmapped meanwhile
            return None
        if read is None:  # the writer is (or died) inside a write: keep what we had
            self._torn_counter = counter
            return cached
        if cached is not None and read[1] is not None and read[1] == cached[1]:
            # the same sample object until a newer one is published (the uplink and the
            # renderer tell a new sample by its identity)
            read = (read[0], cached[1], read[2])
        local.cached = read
        return read

    @property
    def latest(self) -> PlatformSample | None:
        """The newest sample (None before the first)."""
        copy = self.read()
        return None if copy is None else copy[1]

    @property
    def healthy(self) -> bool:
        """The writer's reader has the device and the newest sample is younger than the read
        timeout by its capture stamp (a hung, stopped or dead writer's is not)."""
        copy = self.read()
        return copy is not None and healthy_copy(copy, self.read_timeout_s)


def healthy_copy(copy: _Copy, read_timeout_s: float) -> bool:
    """A copy's reader had the device and its sample is younger than ``read_timeout_s``."""
    _, sample, health = copy
    return health.healthy and sample is not None \
        and stale_since_s(sample, read_timeout_s) is None


def _anonymous_file(size: int) -> int:
    """A descriptor of a ``size``-byte file with no name (``memfd`` where there is one)."""
    if hasattr(os, "memfd_create"):
        fd = os.memfd_create("teletouch-platform", os.MFD_CLOEXEC)
    else:  # pragma: no cover - POSIX without memfd: a temporary file, unlinked at once
        fd, path = tempfile.mkstemp(prefix="teletouch-platform-")
        os.unlink(path)
    os.ftruncate(fd, size)
    return fd


class _Flag:
    """``motion_done`` as the station reads it (``is_set``), backed by the record."""

    def __init__(self, owner: ProcessPlatformReader) -> None:
        self._owner = owner

    def is_set(self) -> bool:
        return self._owner._health().motion_done


def _add_stats(a: PlatformStats | None, b: PlatformStats | None) -> PlatformStats | None:
    """Counters of two children added up (None: none reported)."""
    if a is None or b is None:
        return a if b is None else b
    return add_counters(a, b)


class ProcessPlatformReader:
    """A :class:`PlatformReader` in a child process (see the module docstring).

    Args:
        spec: the platform to open (``open_platform`` spec: a name or a URL).
        options: the platform's options (JSON values: they cross to the child).
        read_timeout_s: as for :class:`PlatformReader` (run in the child); here also the
            oldest a sample may be, by its capture stamp, for the platform to count healthy.
        reopen_after_s: as for :class:`PlatformReader`.
        retry_min_s: first delay before reopening the device, or starting the child again.
        retry_max_s: largest such delay.
        motion_duration_s: as for :class:`PlatformReader`.
        hang_timeout_s: a child whose heartbeat stopped this long (stopped, deadlocked) is
            killed and started again; it also covers a child's start-up.
        lock_memory: the child locks its memory as the station does (:mod:`shared.memlock`).

    Raises:
        ConfigError: bad timeouts (as :class:`PlatformReader`), options that are not JSON.
    """

    def __init__(self, spec: str, options: dict[str, Any] | None = None, *,
                 read_timeout_s: float = 0.1, reopen_after_s: float | None = None,
                 retry_min_s: float = 0.2, retry_max_s: float = 5.0,
                 motion_duration_s: float | None = None,
                 hang_timeout_s: float = HANG_TIMEOUT_S, lock_memory: bool = False) -> None:
        if not read_timeout_s > 0:
            raise ConfigError(f"read_timeout_s must be > 0, got {read_timeout_s}")
        reopen_after_s = reopen_after(read_timeout_s, reopen_after_s)
        if not hang_timeout_s > reopen_after_s:
            raise ConfigError(f"hang_timeout_s must be > reopen_after_s ({reopen_after_s}), "
                              f"got {hang_timeout_s}")
        self.spec = spec
        self._options = dict(options or {})
        try:
            json.dumps(self._options)
        except (TypeError, ValueError) as err:
            raise ConfigError("platform options must be JSON values to cross to the platform "
                              f"process: {err}") from err
        self._read_timeout_s = read_timeout_s
        self._hang_timeout_s = hang_timeout_s
        self._lock_memory = lock_memory
        self._child_args = dict(read_timeout_s=read_timeout_s, reopen_after_s=reopen_after_s,
                                retry_min_s=retry_min_s, retry_max_s=retry_max_s,
                                motion_duration_s=motion_duration_s)
        self._retry_min_s = retry_min_s
        self._retry_max_s = retry_max_s
        self._record: SampleRecord | None = None
        self._view: RecordView | None = None
        self._process: subprocess.Popen[bytes] | None = None
        self._stats_fd: int | None = None
        self._spawned_s = 0.0
        self._spawn_lock = threading.Lock()
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._stopped: tuple[int, PlatformSample | None, ReaderHealth] = (
            0, None, dataclasses.replace(_NOT_STARTED, lost_since_mono_s=monotonic_s()))
        self._carried = (0, 0, 0, 0)  # reads, errors, reconnects, recoveries of dead children
        self._stats: PlatformStats | None = None
        #: the link counters of the children before the running one (those that ended on
        #: their own: a killed child writes none)
        self._carried_stats: PlatformStats | None = None
        #: times a child process was started again after it died or hung
        self.restarts = 0
        #: why the last child ended unasked (None: none did)
        self.child_error: str | None = None
        self.motion_done = _Flag(self)

    # ------------------------------------------------------------------ the record

    def _read(self) -> tuple[int, PlatformSample | None, ReaderHealth]:
        """The newest consistent copy for this thread (never waits for the child)."""
        view = self._view
        copy = None if view is None else view.read()
        return self._stopped if copy is None else copy

    def _health(self) -> ReaderHealth:
        """The health with the counters of the children that died before this one."""
        health = self._read()[2]
        return self._fold(health) if any(self._carried) else health

    @property
    def read_timeout_s(self) -> float:
        """The oldest a sample may be, by its capture stamp, for the platform to count
        healthy."""
        return self._read_timeout_s

    @property
    def record_fd(self) -> int | None:
        """The descriptor of the shared record (for another reading process; None while
        stopped). It stays the same when the child is started again."""
        record = self._record
        return None if record is None else record.fd

    @property
    def latest(self) -> PlatformSample | None:
        """The newest sample the child published (None before the first; after a stop, the
        last one)."""
        return self._read()[1]

    @property
    def healthy(self) -> bool:
        """The child has the device and its newest sample is younger than the read timeout
        (by its capture stamp: a hung, stopped or dead child, or one reconnecting, is not)."""
        return healthy_copy(self._read(), self._read_timeout_s)

    @property
    def lost_since_s(self) -> float | None:
        """When the platform was lost, on the monotonic clock; None: healthy."""
        _, sample, health = self._read()
        if self.healthy:
            return None
        if health.lost_since_mono_s is not None:
            return health.lost_since_mono_s
        if sample is None:
            return self._stopped[2].lost_since_mono_s
        # samples stopped coming: lost a read timeout after the last one was taken
        return stale_since_s(sample, self._read_timeout_s) or monotonic_s()

    @property
    def reads(self) -> int:
        """Samples the children's reader took (board sequence advances)."""
        return self._health().reads

    @property
    def errors(self) -> int:
        """Loss episodes: the children's, and each child that died or hung."""
        return self._health().errors

    @property
    def reconnects(self) -> int:
        """Device reopens in the children."""
        return self._health().reconnects

    @property
    def recoveries(self) -> int:
        """Silences that ended on the open port, in the children."""
        return self._health().recoveries

    @property
    def last_error(self) -> str | None:
        """The child's last error, or why the last child ended unasked."""
        return self._health().last_error or self.child_error

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Start the child and its supervisor (idempotent)."""
        if self._supervisor is not None:
            return
        self._stop.clear()
        self._record = SampleRecord()
        self._view = RecordView(self._record, self._read_timeout_s)
        self._spawn()
        self._supervisor = threading.Thread(target=self._supervise, name="platform-process",
                                            daemon=True)
        self._supervisor.start()

    def _spawn(self) -> None:
        record = self._record
        with self._spawn_lock:
            if record is None or self._stop.is_set():
                return
            stats_r, stats_w = os.pipe()
            settings = {"spec": self.spec, "options": self._options,
                        "reader": self._child_args, "record_fd": record.fd,
                        "stats_fd": stats_w, "parent": os.getpid(),
                        "log_level": logging.getLogger().getEffectiveLevel(),
                        "lock_memory": self._lock_memory}
            try:
                self._process = subprocess.Popen(
                    [sys.executable, "-P", "-m", "local_site.agent.platform_child",
                     json.dumps(settings)], stdin=subprocess.PIPE,
                    pass_fds=(record.fd, stats_w), process_group=0)
            except OSError as err:
                self._process = None
                self.child_error = f"cannot start the platform process: {err}"
                log.error("%s", self.child_error)
                os.close(stats_r)
            else:
                self._stats_fd = stats_r
            finally:
                os.close(stats_w)
            self._spawned_s = monotonic_s()

    def _supervise(self) -> None:
        """Start the child again, with backoff, when it died or hung (a station never gives
        up); the dead child's counters carry over."""
        delay = self._retry_min_s
        while not self._stop.wait(_SUPERVISE_S):
            process = self._process
            running = process is not None and process.poll() is None
            beat = max(self._read()[2].heartbeat_s, self._spawned_s)
            if running and monotonic_s() - beat <= self._hang_timeout_s:
                if self.healthy:
                    delay = self._retry_min_s
                continue
            if running and process is not None:
                why = f"hung (no heartbeat for {monotonic_s() - beat:.1f} s): killed"
                process.kill()
                process.wait()
            else:
                why = ("could not start" if process is None
                       else f"exited with {process.returncode}")
            self.child_error = f"platform process {why}"
            log.error("%s; starting it again in %.1f s", self.child_error, delay)
            self._retire(process)
            if self._stop.wait(delay):
                return
            delay = min(self._retry_max_s, delay * 2.0)
            self.restarts += 1
            self._spawn()

    def _retire(self, process: subprocess.Popen[bytes] | None) -> None:
        """Close a dead child's pipes and carry its counters over (a death is a loss)."""
        if process is not None and process.stdin is not None:
            with contextlib.suppress(OSError):
                process.stdin.close()
        if self._stats_fd is not None:
            # a child that ended on its own wrote its link counters on the way out (a killed
            # one could not: those are lost, the reader's counters below are not)
            self._carried_stats = _add_stats(self._carried_stats, self._read_stats())
            os.close(self._stats_fd)
            self._stats_fd = None
        health = self._read()[2]
        reads, errors, reconnects, recoveries = self._carried
        self._carried = (reads + health.reads, errors + health.errors + 1,
                         reconnects + health.reconnects, recoveries + health.recoveries)
        if self._record is not None:  # the next child starts its counters at zero
            self._record.claim()  # (the dead child may have stopped inside a write)
            self._record.write_health(dataclasses.replace(
                _NOT_STARTED, lost_since_mono_s=monotonic_s(), heartbeat_s=monotonic_s()))

    def stop(self, timeout_s: float = _CHILD_STOP_S) -> None:
        """Stop the child: it closes the device and reports its link counters.

        Args:
            timeout_s: how long the child may take (then it is killed, logged).
        """
        self._stop.set()
        with self._spawn_lock:  # no child is started after this
            pass
        if self._supervisor is not None:
            self._supervisor.join(timeout_s)
            self._supervisor = None
        process, self._process = self._process, None
        # (a child that already ended, e.g. one waiting for its restart, has nothing to hear)
        if process is not None and process.poll() is not None and process.stdin is not None:
            with contextlib.suppress(OSError):
                process.stdin.close()
        elif process is not None:
            try:
                process.communicate(b"stop\n", timeout=timeout_s)
            except (subprocess.TimeoutExpired, OSError, ValueError) as err:
                log.warning("platform process did not stop in %.1f s (%s): killed", timeout_s,
                            err)
                process.kill()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    process.wait(timeout_s)
        # (also when no child runs: the children before it that ended on their own count)
        stats = _add_stats(self._carried_stats, self._read_stats())
        if stats is not None:  # (a second stop() keeps the first one's)
            self._stats = stats
        self._carried_stats = None
        if self._stats_fd is not None:
            os.close(self._stats_fd)
            self._stats_fd = None
        record, self._record = self._record, None
        self._view = None
        if record is not None:
            copy = record.read()
            sample, health = (copy[1], copy[2]) if copy is not None else (None, _NOT_STARTED)
            now = monotonic_s()
            self._stopped = (0, sample, dataclasses.replace(
                self._fold(health), healthy=False, lost_since_mono_s=now, heartbeat_s=now))
            self._carried = (0, 0, 0, 0)
            record.close()

    def _fold(self, health: ReaderHealth) -> ReaderHealth:
        """``health`` with the dead children's counters added."""
        reads, errors, reconnects, recoveries = self._carried
        return dataclasses.replace(health, reads=health.reads + reads,
                                   errors=health.errors + errors,
                                   reconnects=health.reconnects + reconnects,
                                   recoveries=health.recoveries + recoveries)

    def _read_stats(self) -> PlatformStats | None:
        """The child's link counters from its stats pipe (None when it wrote none)."""
        fd = self._stats_fd
        if fd is None:
            return None
        chunks = []
        while select.select([fd], [], [], 0)[0]:
            chunk = os.read(fd, 4096)
            if not chunk:
                break
            chunks.append(chunk)
        try:
            return PlatformStats(**json.loads(b"".join(chunks)))
        except (ValueError, TypeError):
            return None

    def platform_stats(self) -> PlatformStats:
        """The device link's counters as the children reported them: the running child's
        at :meth:`stop` plus those of the children before it that ended on their own (a
        child killed as hung writes none)."""
        return self._stats if self._stats is not None else PlatformStats()

    def disconnect(self) -> None:
        """The child closes the device when it stops (nothing to do here)."""
