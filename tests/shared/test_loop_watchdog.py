"""``shared.loop_watchdog``: a process whose event loop is stuck writes its stacks and ends
(exit code 1); one whose loop keeps turning, or that left the block, does not. Real
subprocesses (the watchdog ends its process); the relay's own in
``tests/relay_server/test_relay_health.py``."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from shared.errors import ConfigError
from shared.loop_watchdog import check_hang_timeout, loop_watchdog
from tests.support import REAL_DUMP_TRACEBACK_LATER, assert_ended_by_loop_watchdog, scaled

_PROGRAM = textwrap.dedent('''
    import asyncio, sys, time
    from shared.loop_watchdog import loop_watchdog

    TIMEOUT_S = float(sys.argv[1])
    SCENARIO = sys.argv[2]

    def _stuck_in_a_blocking_call():
        time.sleep(3600)

    async def main():
        async with loop_watchdog(TIMEOUT_S):
            # turning: short blocking calls and awaits for 3 timeouts
            end = time.monotonic() + 3 * TIMEOUT_S
            while time.monotonic() < end:
                time.sleep(TIMEOUT_S / 10)
                await asyncio.sleep(TIMEOUT_S / 10)
            print("turned", flush=True)
            if SCENARIO == "stuck":
                _stuck_in_a_blocking_call()
        if SCENARIO == "left":  # out of the block: no watchdog any more
            time.sleep(3 * TIMEOUT_S)
            print("left", flush=True)

    asyncio.run(main())
''')


def _run(timeout_s: float, scenario: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", _PROGRAM, str(timeout_s), scenario],
                          capture_output=True, text=True, timeout=scaled(60.0) + 10 * timeout_s,
                          check=False)


def test_a_stuck_loop_ends_its_process_with_its_stacks() -> None:
    timeout_s = scaled(3.0)
    done = _run(timeout_s, "stuck")
    assert_ended_by_loop_watchdog(done.returncode, done.stderr, "_stuck_in_a_blocking_call")
    assert done.stdout == "turned\n"  # it ran three timeouts first: no early end


@pytest.mark.parametrize("scenario", ["turning", "left"])
def test_a_turning_loop_or_one_that_left_the_block_is_not_ended(scenario: str) -> None:
    done = _run(scaled(3.0), scenario)
    assert done.returncode == 0 and "Timeout (" not in done.stderr, (done.returncode,
                                                                       done.stderr[-2000:])
    assert done.stdout == ("turned\nleft\n" if scenario == "left" else "turned\n")


@pytest.mark.parametrize("off", [None, 0, 0.0])
async def test_off_is_no_watchdog(off: float | None, monkeypatch: pytest.MonkeyPatch) -> None:
    import asyncio
    import faulthandler

    calls: list[object] = []
    monkeypatch.setattr(faulthandler, "dump_traceback_later", lambda *a, **k: calls.append(a))
    async with loop_watchdog(off):
        await asyncio.sleep(0.05)
    assert calls == []


async def test_a_timeout_below_a_tenth_of_a_second_is_refused() -> None:
    with pytest.raises(ValueError, match=r"a loop watchdog timeout of 0\.05 s is below 0\.1 s"):
        async with loop_watchdog(0.05):
            pass


async def test_a_watchdog_that_cannot_write_is_refused_at_the_start(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import faulthandler

    monkeypatch.setattr(faulthandler, "dump_traceback_later", REAL_DUMP_TRACEBACK_LATER)
    monkeypatch.setattr(sys, "stderr", None)
    with pytest.raises(RuntimeError, match=r"sys\.stderr is None"):
        async with loop_watchdog(10.0):
            pass


async def test_a_re_arm_that_fails_is_said_and_leaves_no_timer(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """A timer left armed by a re-arm task that died would end a healthy process: it is
    cancelled, and an ERROR says the process is not watched. (faulthandler faked: this is
    the test runner's process.)"""
    import asyncio
    import faulthandler

    calls: list[str] = []

    def arm(timeout_s: float, exit: bool = False) -> None:
        calls.append("arm")
        if len(calls) == 3:
            raise OSError("stderr gone")

    monkeypatch.setattr(faulthandler, "dump_traceback_later", arm)
    monkeypatch.setattr(faulthandler, "cancel_dump_traceback_later",
                        lambda: calls.append("cancel"))
    async with loop_watchdog(0.4):  # re-armed every 0.1 s
        async with asyncio.timeout(scaled(10.0)):
            while "cancel" not in calls:
                await asyncio.sleep(0.01)
        assert calls == ["arm", "arm", "arm", "cancel"]
    assert [r.getMessage() for r in caplog.records] == [
        "the event loop's watchdog stopped: OSError('stderr gone'); this process is not "
        "watched"]


@pytest.mark.parametrize("good", [0, 0.0, 1, 1.0, 30.0, 3600])
def test_a_hang_timeout_is_off_or_at_least_a_second(good: float) -> None:
    check_hang_timeout("x.hang_timeout_s", good)


@pytest.mark.parametrize("bad", [0.99, 0.1, -1.0, -1e-9, float("nan"), float("inf"), True,
                                 "10", None])
def test_anything_else_is_refused_by_name(bad: object) -> None:
    with pytest.raises(ConfigError, match=r"^x\.hang_timeout_s must be 0 \(no watchdog\) or a "
                                          r"finite number of seconds >= 1, got "):
        check_hang_timeout("x.hang_timeout_s", bad)
