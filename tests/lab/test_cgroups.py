"""CPU groups for the benchmarks (``lab/bench/cgroups.py``): systemd's weights, the mount
found, and on a machine where the cpu controller is writable, the kernel ranking two busy
processes by their groups' weights and budgeting real time per group."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import pytest

from lab.bench.cgroups import (
    CgroupError,
    CpuGroups,
    _write_budget,
    cpu_v1_mount,
    shares_for_weight,
)
from tests.support import scaled, wait_until


def test_a_weight_becomes_shares_as_systemd_converts_it() -> None:
    assert shares_for_weight(100) == 1024  # both defaults
    assert shares_for_weight(1000) == 10240
    assert shares_for_weight(1) == 10 and shares_for_weight(10000) == 102400
    for bad in (0, 10001, -5):
        with pytest.raises(ValueError, match=r"1\.\.10000"):
            shares_for_weight(bad)


def test_the_v1_cpu_mount_is_found_and_other_layouts_are_refused() -> None:
    mounts = ["tmpfs /sys/fs/cgroup tmpfs rw,relatime,mode=755 0 0",
              "cgroup /sys/fs/cgroup/cpuacct cgroup rw,relatime,cpuacct 0 0",
              "cgroup /sys/fs/cgroup/cpu,cpuacct cgroup rw,nosuid,cpu,cpuacct 0 0",
              "cgroup2 /sys/fs/cgroup/unified cgroup2 rw,relatime 0 0"]
    assert cpu_v1_mount(mounts) == Path("/sys/fs/cgroup/cpu,cpuacct")
    with pytest.raises(CgroupError, match="cgroup v2"):
        cpu_v1_mount(["cgroup2 /sys/fs/cgroup cgroup2 rw,nosuid 0 0"])
    with pytest.raises(CgroupError, match="no cgroup cpu controller"):
        cpu_v1_mount(mounts[:2])


def _groups() -> CpuGroups:
    try:
        return CpuGroups(parent=f"teletouch-test-{os.getpid()}")
    except (CgroupError, OSError) as exc:
        pytest.skip(f"no writable cgroup v1 cpu controller here: {exc}")


#: a child that sleeps until argv[1] and spins from then until argv[2] (CLOCK_MONOTONIC,
#: shared by all processes) on the CPU argv[3], then prints its CPU seconds in that window
SPIN = """import os, sys, time
start, end, cpu = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
os.sched_setaffinity(0, {cpu})
time.sleep(max(0.0, start - time.monotonic()))
used = sum(os.times()[:2])
while time.monotonic() < end:
    pass
print(sum(os.times()[:2]) - used)
"""


def test_the_kernel_shares_a_cpu_by_the_groups_weights() -> None:
    cpu = str(min(os.sched_getaffinity(0)))
    procs: list[subprocess.Popen[str]] = []
    with _groups() as groups:
        try:
            groups.make("heavy", 1000)
            groups.make("light", 100)
            # one window for both, far enough ahead for both interpreters to have started
            start = time.monotonic() + scaled(1.0)
            window = [str(start), str(start + 1.5), cpu]
            procs = [subprocess.Popen([sys.executable, "-c", SPIN, *window],
                                      stdout=subprocess.PIPE, text=True,
                                      preexec_fn=partial(groups.enter, name))
                     for name in ("heavy", "light")]
            heavy, light = (float(p.communicate(timeout=scaled(30))[0]) for p in procs)
        finally:
            for p in procs:
                p.kill()
                p.wait()
    # 10:1 by the weights, both spinning in the same window on one CPU and under the same
    # parent, so load from outside does not change the ratio. Equal weights give ~1:1.
    assert heavy > 3 * light, (heavy, light)
    assert not groups.parent.exists()


def test_a_group_grants_real_time_only_where_it_was_given_a_budget() -> None:
    fifo = ("import os\nos.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))\n"
            "print(open('/proc/self/cgroup').read())")
    with _groups() as groups:
        if not (groups.make("plain", 100) / "cpu.rt_runtime_us").exists():
            pytest.skip("this kernel does not budget real time per group")
        groups.make("budget", 100, rt_runtime_us=100_000)
        runs = {name: subprocess.run([sys.executable, "-c", fifo], capture_output=True,
                                     text=True, timeout=scaled(30),
                                     preexec_fn=partial(groups.enter, name))
                for name in ("plain", "budget")}
    assert runs["budget"].returncode == 0, runs["budget"].stderr
    assert f"{groups.parent.name}/budget" in runs["budget"].stdout  # it ran in the group
    assert "PermissionError" in runs["plain"].stderr  # no budget: SCHED_FIFO refused


def test_a_budget_beyond_the_real_time_period_is_refused_clearly() -> None:
    with _groups() as groups:
        group = groups.make("plain", 100)
        if not (group / "cpu.rt_runtime_us").exists():
            pytest.skip("this kernel does not budget real time per group")
        period = int((group / "cpu.rt_period_us").read_text())
        with pytest.raises(CgroupError, match=r"real-time budget .* refused"):
            _write_budget(groups.parent / "cpu.rt_runtime_us", period + 1, wait_s=0.2)


def test_closing_moves_a_left_over_process_out_and_removes_every_group() -> None:
    """A failed run may leave its children in a group: closing must not give up on it (nor on
    the groups after it) and must not kill the process."""
    with _groups() as groups:
        groups.make("a", 100)
        groups.make("b", 100)
        with pytest.raises(CgroupError, match="cannot move process"):
            groups.add("no-such-group", os.getpid())
        sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"],
                                   preexec_fn=partial(groups.enter, "a"))
        try:
            wait_until(lambda: str(sleeper.pid) in (groups.parent / "a" / "cgroup.procs")
                       .read_text().split(), 10, "the sleeper in group a")
            groups.close()
            assert not groups.parent.exists()
            assert sleeper.poll() is None  # moved, not killed
            own = Path(f"/proc/{sleeper.pid}/cgroup").read_text()
            assert groups.parent.name not in own
        finally:
            sleeper.kill()
            sleeper.wait()
