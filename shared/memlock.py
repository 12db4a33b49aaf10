"""Keep a station's (or the relay's) memory in RAM while it runs (``mlockall``).

A page the kernel has evicted from a running station is read back from disk the next time a
thread touches it: a *major page fault*. Without swap that still happens to file-backed
pages (the interpreter, numpy and OpenCV code, mapped data) under memory pressure or
proactive reclaim (DAMON's ``pageout`` scheme drops memory that went cold); with swap, to
everything. The fault takes as long as the disk does, seconds when it stalls, and the thread
holds the GIL meanwhile: the 1 kHz display loop or the arm watchdog waits on a disk.

:func:`memory_locked` calls ``mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT)`` for the
duration of a block: every page the process has touched, or touches later, stays resident
(``MCL_ONFAULT``: locked when first touched, so the resident size does not grow to the mapped
size). Locking is process-wide; nested blocks share one lock, released when the outermost
ends.

It locks only when the lock cannot make a later allocation fail. With ``MCL_FUTURE`` every
new mapping counts against ``RLIMIT_MEMLOCK``, and one over it fails (a ``MemoryError`` deep in
the station), so the limit must be unlimited (systemd ``LimitMEMLOCK=infinity``, docker
``--ulimit memlock=-1``) or the process must hold ``CAP_IPC_LOCK``. Otherwise nothing is
locked and :attr:`MemoryLock.reason` says what to set. Linux only.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import os
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass

__all__ = ["MemoryLock", "lock_refusal", "memory_locked"]

log = logging.getLogger(__name__)

MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT = 1, 2, 4
CAP_IPC_LOCK = 14

_lock = threading.Lock()
_holders = 0


@dataclass(frozen=True)
class MemoryLock:
    """Whether the process's memory is locked, and if not, why.

    Attributes:
        locked: every touched page stays resident while the block runs.
        reason: why not (None when locked).
    """

    locked: bool
    reason: str | None = None

    def to_dict(self) -> dict[str, object]:
        """For a station's summary."""
        return {"locked": self.locked, "reason": self.reason}


def lock_refusal(soft_limit: int, unlimited: int, cap_ipc_lock: bool) -> str | None:
    """Why locking would be unsafe (None: safe).

    Args:
        soft_limit: ``RLIMIT_MEMLOCK``'s soft limit in bytes.
        unlimited: the value that means no limit (``resource.RLIM_INFINITY``).
        cap_ipc_lock: the process holds ``CAP_IPC_LOCK`` (the limit does not apply).
    """
    if cap_ipc_lock or soft_limit == unlimited:
        return None
    return (f"RLIMIT_MEMLOCK is {soft_limit / 2**20:.3g} MiB: a locked process's later "
            "allocations could fail against it; set it unlimited (systemd "
            "LimitMEMLOCK=infinity, docker --ulimit memlock=-1) or grant CAP_IPC_LOCK")


def _has_cap_ipc_lock() -> bool:
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("CapEff:"):
                    return bool(int(line.split()[1], 16) >> CAP_IPC_LOCK & 1)
    except (OSError, ValueError, IndexError):
        pass
    return False


def _refusal() -> str | None:
    if not sys.platform.startswith("linux"):
        return f"memory locking is implemented for Linux only (this is {sys.platform})"
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    return lock_refusal(soft, resource.RLIM_INFINITY, _has_cap_ipc_lock())


def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)


@contextlib.contextmanager
def memory_locked(enabled: bool = True) -> Iterator[MemoryLock]:
    """Lock the process's memory for the block (see the module docstring).

    Args:
        enabled: False: lock nothing (the station's ``lock_memory = false``).

    Yields:
        What was done: locked, or not and why (logged once at INFO; the station runs either
        way, as it would without the lock).
    """
    global _holders
    if not enabled:
        yield MemoryLock(False, "off (lock_memory = false)")
        return
    with _lock:
        if _holders == 0:
            reason = _refusal()
            if reason is None:
                libc = _libc()
                if libc.mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) != 0:
                    err = ctypes.get_errno()
                    reason = f"mlockall failed: {os.strerror(err)} (errno {err})"
            if reason is not None:
                log.info("memory not locked: %s", reason)
                result = MemoryLock(False, reason)
            else:
                log.info("memory locked (mlockall, on fault): no page of this process is "
                         "evicted while it runs")
                result = MemoryLock(True)
        else:
            result = MemoryLock(True)
        if result.locked:
            _holders += 1
    try:
        yield result
    finally:
        if result.locked:
            with _lock:
                _holders -= 1
                if _holders == 0:
                    _libc().munlockall()
