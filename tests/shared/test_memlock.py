"""Memory locking for the stations (shared/memlock.py): when it locks, what it locks, and
that it never locks where a later allocation could fail against RLIMIT_MEMLOCK.

The real locks run in a fresh interpreter: a lock is process-wide and must not outlive the
test in pytest's own process.
"""

from __future__ import annotations

import json
import resource
import shutil
import subprocess
import sys
import textwrap

import pytest
from hypothesis import given
from hypothesis import strategies as st

import shared.memlock as memlock
from shared.memlock import lock_refusal, memory_locked
from tests.support import scaled

INF = resource.RLIM_INFINITY

# In a fresh interpreter: the lock's result and VmLck inside a block, inside a nested block,
# after the nested block and after the outer one.
PROBE = textwrap.dedent("""
    import json, sys
    from shared.memlock import memory_locked

    def vmlck():
        for line in open("/proc/self/status"):
            if line.startswith("VmLck:"):
                return int(line.split()[1])

    out = {}
    with memory_locked(True) as outer:
        big = bytearray(32 * 2**20)  # touched after the lock: locked too (MCL_FUTURE)
        out["outer"] = [outer.locked, outer.reason]
        out["inside"] = vmlck()
        with memory_locked(True) as inner:
            out["inner"] = inner.locked
        out["after_inner"] = vmlck()
    out["after"] = vmlck()
    print(json.dumps(out))
""")


def _probe(*prefix: str) -> dict[str, object]:
    done = subprocess.run([*prefix, sys.executable, "-c", PROBE], capture_output=True,
                          text=True, timeout=scaled(60.0), check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    result: dict[str, object] = json.loads(done.stdout)
    return result


@given(soft=st.integers(min_value=0, max_value=2**62), cap=st.booleans())
def test_a_lock_is_refused_exactly_when_a_finite_limit_applies(soft: int, cap: bool) -> None:
    refusal = lock_refusal(soft, INF, cap)
    assert (refusal is None) == cap
    if refusal is not None:
        assert "LimitMEMLOCK=infinity" in refusal and "CAP_IPC_LOCK" in refusal
    assert lock_refusal(INF, INF, cap) is None


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mlockall is Linux's")
def test_a_real_lock_holds_every_page_until_the_outermost_block_ends() -> None:
    out = _probe()
    if memlock._refusal() is not None:  # this machine's user may not lock: nothing was
        assert out["outer"] == [False, memlock._refusal()] and out["inside"] == 0
        pytest.skip(f"locking refused here: {memlock._refusal()}")
    assert out["outer"] == [True, None] and out["inner"] is True
    assert isinstance(out["inside"], int) and out["inside"] >= 32 * 1024  # kB: the buffer
    assert out["after_inner"] == out["inside"]  # the nested block does not unlock
    assert out["after"] == 0


@pytest.mark.skipif(shutil.which("setpriv") is None or shutil.which("prlimit") is None
                    or not sys.platform.startswith("linux"), reason="needs util-linux")
def test_without_cap_ipc_lock_and_with_a_finite_limit_nothing_is_locked() -> None:
    # the same user without CAP_IPC_LOCK (also dropped from the bounding set) and a 64 MiB
    # limit, which the probe's 32 MiB would fit today but a station's later growth might not
    _soft, hard = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    limit = 64 * 2**20 if hard == INF else min(hard, 64 * 2**20)
    cmd = ["prlimit", f"--memlock={limit}:{limit}", "setpriv", "--inh-caps=-ipc_lock",
           "--bounding-set=-ipc_lock", sys.executable, "-c", PROBE]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=scaled(60.0),
                          check=False)
    if done.returncode != 0 and ("setpriv" in done.stderr or "prlimit" in done.stderr):
        pytest.skip(f"util-linux refused here: {done.stderr.strip()[-300:]}")
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout)
    locked, reason = out["outer"]
    assert locked is False and "RLIMIT_MEMLOCK is" in reason and "LimitMEMLOCK" in reason
    assert out["inside"] == 0 and out["inner"] is False and out["after"] == 0


def test_off_locks_nothing_and_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse() -> str:
        raise AssertionError("the lock must not even be considered when it is off")

    monkeypatch.setattr(memlock, "_refusal", refuse)
    with memory_locked(False) as result:
        assert result.locked is False and result.reason == "off (lock_memory = false)"
    assert result.to_dict() == {"locked": False, "reason": "off (lock_memory = false)"}


def test_a_refused_lock_never_calls_mlockall(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(memlock, "_holders", 0)  # (whatever an in-process station left)
    monkeypatch.setattr(memlock, "_refusal", lambda: "RLIMIT_MEMLOCK is 8 MiB: ...")
    monkeypatch.setattr(memlock, "_libc", lambda: pytest.fail("mlockall called"))
    with memory_locked(True) as result:
        assert result == memlock.MemoryLock(False, "RLIMIT_MEMLOCK is 8 MiB: ...")


@pytest.mark.parametrize("value", ["yes", 1, None])
def test_the_stations_settings_take_only_true_or_false(value: object) -> None:
    from local_site.agent import LocalAgentConfig
    from remote_site.agent.config import RemoteAgentConfig
    from shared.errors import ConfigError

    with pytest.raises(ConfigError, match=r"local\.agent\.lock_memory"):
        LocalAgentConfig(lock_memory=value)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"remote\.agent\.lock_memory"):
        RemoteAgentConfig(lock_memory=value)  # type: ignore[arg-type]
