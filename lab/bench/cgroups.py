"""CPU groups for benchmarks: each job in a group of its own with a CPU weight.

This is how a deployment ranks the stations above other jobs on the same host: systemd puts
every service and slice in a control group, and ``CPUWeight=`` (default 100) sets how the
CPU is shared between sibling groups when they all want more than there is. Inside a group
that is not the root, the kernel does not apply autogroup (``sched(7)``): its threads compete
by their nice values among themselves only. ``nice`` alone cannot rank one service above
another (docs/speed.md section 34); a group's weight can.

Only the cgroup v1 ``cpu`` controller is handled (this machine's): a weight becomes
``cpu.shares`` as systemd converts it (``weight * 1024 / 100``, clamped to 2..262144). A kernel
with real-time group scheduling (``cpu.rt_runtime_us`` present) gives a new group no
real-time budget, so a ``SCHED_FIFO`` request inside it fails; :meth:`CpuGroups.make` grants
one where asked. A cgroup v2 host (``cpu.weight``) is refused with a clear error: not run here.
"""

from __future__ import annotations

import contextlib
import errno
import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path

#: systemd's default CPUWeight= and cgroup v1's default cpu.shares
DEFAULT_WEIGHT = 100
DEFAULT_SHARES = 1024


class CgroupError(RuntimeError):
    """The cpu controller is missing, not writable, or of a layout not handled here."""


def shares_for_weight(weight: int) -> int:
    """systemd's CPUWeight= (1..10000) as cgroup v1 ``cpu.shares``."""
    if not 1 <= weight <= 10000:
        raise ValueError(f"a CPU weight is 1..10000 (systemd's CPUWeight=), got {weight}")
    return min(max(weight * DEFAULT_SHARES // DEFAULT_WEIGHT, 2), 262144)


def cpu_v1_mount(mounts: Iterable[str]) -> Path:
    """Where the cgroup v1 ``cpu`` controller is mounted, from ``/proc/self/mounts`` lines."""
    v2 = None
    for line in mounts:
        fields = line.split()
        if len(fields) < 4:
            continue
        if fields[2] == "cgroup" and "cpu" in fields[3].split(","):
            return Path(fields[1])
        if fields[2] == "cgroup2":
            v2 = fields[1]
    if v2 is not None:
        raise CgroupError(f"only a cgroup v2 hierarchy ({v2}) has the cpu controller here: "
                          "cpu.weight groups are not handled (only v1 cpu.shares was run)")
    raise CgroupError("no cgroup cpu controller is mounted")


class CpuGroups:
    """Groups under ``<mount>/<parent>``, each with a weight; :meth:`close` removes them.

    A context manager: leaving it closes the groups. Every filesystem error is a
    :class:`CgroupError` naming the file."""

    def __init__(self, mount: Path | None = None, parent: str = "teletouch-bench") -> None:
        try:
            if mount is None:
                with open("/proc/self/mounts", encoding="ascii") as f:
                    mount = cpu_v1_mount(f)
            self.mount = mount
            self.parent = mount / parent
            self.parent.mkdir(exist_ok=True)
        except OSError as exc:
            raise CgroupError(f"cannot make a cpu group: {exc} (needs root and a writable "
                              "cgroup v1 cpu mount)") from exc
        self._made: list[Path] = [self.parent]

    def __enter__(self) -> CpuGroups:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def make(self, name: str, weight: int, rt_runtime_us: int = 0) -> Path:
        """A group ``name`` at ``weight``; ``rt_runtime_us`` of each real-time period for its
        ``SCHED_FIFO`` threads, where the kernel budgets real time per group (the parent's
        budget is raised to the sum of its groups' first, every group under it counted)."""
        group = self.parent / name
        try:
            group.mkdir(exist_ok=True)
            if group not in self._made:
                self._made.append(group)
            (group / "cpu.shares").write_text(f"{shares_for_weight(weight)}\n")
            if rt_runtime_us and (group / "cpu.rt_runtime_us").exists():
                siblings = sum(_read_int(g / "cpu.rt_runtime_us")
                               for g in self.parent.iterdir() if g.is_dir() and g != group)
                _write_budget(self.parent / "cpu.rt_runtime_us", siblings + rt_runtime_us)
                _write_budget(group / "cpu.rt_runtime_us", rt_runtime_us)
        except OSError as exc:
            raise CgroupError(f"cannot set up the cpu group {group}: {exc}") from exc
        return group

    def add(self, name: str, pid: int) -> None:
        """Move process ``pid`` (all its threads) into group ``name``; its children inherit it."""
        procs = self.parent / name / "cgroup.procs"
        try:
            procs.write_text(f"{pid}\n")
        except OSError as exc:
            raise CgroupError(f"cannot move process {pid} into {procs}: {exc}") from exc

    def enter(self, name: str) -> None:
        """Move the calling process into group ``name`` (e.g. from a ``preexec_fn``)."""
        self.add(name, os.getpid())

    def close(self) -> None:
        """Remove the groups and the parent. A process still in one (a run that failed and left
        its children) is moved back to the mount's root group first, not killed; every group
        is tried, and what could not be removed is reported at the end."""
        failed = []
        for group in reversed(self._made):
            try:
                for pid in _read_pids(group / "cgroup.procs"):
                    with contextlib.suppress(ProcessLookupError, OSError):
                        (self.mount / "cgroup.procs").write_text(f"{pid}\n")
                _remove(group)
            except OSError as exc:
                failed.append(f"{group}: {exc}")
        self._made.clear()
        if failed:
            raise CgroupError("cpu groups left behind: " + "; ".join(failed))


def _read_pids(path: Path) -> list[int]:
    try:
        return [int(line) for line in path.read_text().split()]
    except FileNotFoundError:
        return []


def _retrying(action: Callable[[], object], code: int, wait_s: float, poll_s: float) -> None:
    """Run ``action``, again while it fails with errno ``code``, until ``wait_s`` has passed
    (then the last error is raised): the kernel finishes some cgroup changes a moment late."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            action()
            return
        except OSError as exc:
            if exc.errno != code or time.monotonic() > deadline:
                raise
            time.sleep(poll_s)


def _remove(group: Path, wait_s: float = 2.0) -> None:
    """rmdir a group; one whose last process was just moved out or ended may still count as
    busy for a moment (EBUSY)."""
    with contextlib.suppress(FileNotFoundError):
        _retrying(group.rmdir, errno.EBUSY, wait_s, 0.02)


def _write_budget(path: Path, runtime_us: int, wait_s: float = 5.0) -> None:
    """Write a real-time budget; the kernel refuses one its parent cannot cover (EINVAL), and
    frees a removed group's budget only some time after its ``rmdir``."""
    try:
        _retrying(lambda: path.write_text(f"{runtime_us}\n"), errno.EINVAL, wait_s, 0.05)
    except OSError as exc:
        raise CgroupError(f"{path}: a real-time budget of {runtime_us} us refused "
                          f"({exc}): more than its parent has free") from exc


def _read_int(path: Path) -> int:
    try:
        return int(path.read_text().split()[0])
    except FileNotFoundError:
        return 0
