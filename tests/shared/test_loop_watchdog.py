"""``shared.loop_watchdog``: a process whose event loop is stuck, or that waits for a call in
another thread that does not return, writes its stacks and ends (exit code 1); one whose loop
keeps turning and whose calls return within the timeout, or that left the block, does not.
Real subprocesses (the watchdog ends its process); the relay's own in
``tests/relay_server/test_relay_health.py``, the stations' in ``test_station_watchdogs.py``."""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
import time

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


_CALLS_PROGRAM = textwrap.dedent('''
    import asyncio, logging, sys, time
    from shared.loop_watchdog import WaitedCalls, loop_watchdog

    TIMEOUT_S, CALL_S, N = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")

    def _a_waited_call(seconds):
        time.sleep(seconds)

    async def main():
        calls = WaitedCalls()
        loop = asyncio.get_running_loop()
        ticks = 0

        async def ticker():  # the loop turns all along
            nonlocal ticks
            while True:
                await asyncio.sleep(0.01)
                ticks += 1

        task = asyncio.create_task(ticker())
        async with loop_watchdog(TIMEOUT_S, calls):
            for _ in range(N):
                print("call", time.monotonic(), ticks, flush=True)
                with calls.waiting_for("the test's call"):
                    await loop.run_in_executor(None, _a_waited_call, CALL_S)
        task.cancel()
        print("returned", flush=True)

    asyncio.run(main())
''')


def _run_calls(timeout_s: float, call_s: float, n: int
               ) -> tuple[subprocess.CompletedProcess[str], float]:
    done = subprocess.run([sys.executable, "-c", _CALLS_PROGRAM, str(timeout_s), str(call_s),
                           str(n)], capture_output=True, text=True,
                          timeout=scaled(60.0) + 10 * timeout_s, check=False)
    return done, time.monotonic()


def test_a_call_that_does_not_return_ends_its_process_at_the_timeout() -> None:
    """The loop turns all along (its ticker counts on between the calls); the call waited
    for does not return: the process ends the timeout after the call began, not before,
    with a WARNING naming it at half the timeout and the call's stack among those written."""
    timeout_s = scaled(3.0)
    done, ended = _run_calls(timeout_s, 3600.0, 1)
    assert_ended_by_loop_watchdog(done.returncode, done.stderr, "_a_waited_call")
    began = float(done.stdout.split()[1])
    assert timeout_s - 0.05 <= ended - began <= timeout_s + scaled(5.0), ended - began
    assert re.search(r"^WARNING the test's call has not returned for \d+\.\d s: this process "
                     r"ends, its stacks written, if it has not returned after "
                     rf"{timeout_s:g} s \(hang_timeout_s\)$", done.stderr, re.M), done.stderr


def test_calls_that_return_just_within_the_timeout_end_nothing() -> None:
    """Two calls of the timeout less 0.6 s, one after the other, the loop turning all
    along: neither ends the process, each is named at half the timeout."""
    timeout_s = scaled(3.0)
    done, _ = _run_calls(timeout_s, timeout_s - scaled(0.6), 2)
    assert done.returncode == 0 and "Timeout (" not in done.stderr, (done.returncode,
                                                                       done.stderr[-2000:])
    lines = done.stdout.splitlines()
    assert lines[-1] == "returned" and len(lines) == 3, lines
    assert int(lines[1].split()[2]) > int(lines[0].split()[2])  # the ticker ran meanwhile
    assert "WARNING the test's call has not returned for" in done.stderr  # at half


async def test_a_call_is_judged_at_each_re_arm(monkeypatch: pytest.MonkeyPatch,
                                               caplog: pytest.LogCaptureFixture) -> None:
    """In this process (faulthandler faked): with calls returning, each re-arm sets the
    timer a whole timeout ahead; a call waited for half the timeout is named once; one
    waited for the timeout has the timer set to end the process at once, and the re-arms
    stop (faulthandler's thread would end the process)."""
    import asyncio
    import faulthandler

    from shared.loop_watchdog import WaitedCalls

    arms: list[float] = []
    monkeypatch.setattr(faulthandler, "dump_traceback_later",
                        lambda timeout_s, exit=False: arms.append(timeout_s))
    monkeypatch.setattr(faulthandler, "cancel_dump_traceback_later", lambda: None)
    calls = WaitedCalls()
    never = asyncio.get_running_loop().create_future()
    async with loop_watchdog(0.4, calls):  # re-armed every 0.1 s
        for _ in range(3):  # calls that return
            with calls.waiting_for("a quick call"):
                await asyncio.sleep(0.05)
        assert arms and set(arms) == {0.4}, arms
        assert calls.oldest() is None
        with calls.waiting_for("a call that does not return"):
            async with asyncio.timeout(scaled(10.0)):
                while arms[-1] != 1e-3:
                    await asyncio.wait({never}, timeout=0.01)
            oldest = calls.oldest()
            assert oldest is not None and oldest[0] == "a call that does not return"
        n = len(arms)
        await asyncio.sleep(0.3)  # three re-arm periods: none more
        assert len(arms) == n
    named = [r.getMessage() for r in caplog.records
             if r.getMessage().startswith("a call that does not return has not returned for ")]
    assert len(named) == 1 and "(hang_timeout_s)" in named[0], caplog.records


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
