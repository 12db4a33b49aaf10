"""``shared.loop_watchdog``: a process whose event loop is stuck, or that waits for a call in
another thread that does not return, writes its stacks and ends (exit code 1); one whose loop
keeps turning and whose calls return within the timeout, or that left the block, does not.
Real subprocesses (the watchdog ends its process); the relay's own in
``tests/relay_server/test_relay_health.py``, the stations' in ``test_station_watchdogs.py``."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from shared.errors import ConfigError
from shared.loop_watchdog import check_hang_timeout, loop_watchdog
from tests.support import (
    REAL_DUMP_TRACEBACK_LATER,
    MachineStalls,
    assert_ended_by_loop_watchdog,
    scaled,
)

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
    assert_ended_by_loop_watchdog(done.returncode, done.stderr, "_a_waited_call",
                                  stuck="the test's call has not returned for ")
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
    assert done.returncode == 0 and "Timeout (" not in done.stderr and \
        "Event loop watchdog" not in done.stderr, (done.returncode, done.stderr[-2000:])
    lines = done.stdout.splitlines()
    assert lines[-1] == "returned" and len(lines) == 3, lines
    assert int(lines[1].split()[2]) > int(lines[0].split()[2])  # the ticker ran meanwhile
    assert "WARNING the test's call has not returned for" in done.stderr  # at half


def _fake_arms(monkeypatch: pytest.MonkeyPatch) -> tuple[list[float], list[str]]:
    """faulthandler's timer and the end of the process faked in this process: the
    timeouts armed, and the reports of the ends."""
    import faulthandler

    from shared import loop_watchdog as module

    arms: list[float] = []
    ends: list[str] = []
    monkeypatch.setattr(faulthandler, "dump_traceback_later",
                        lambda timeout_s, file=None, exit=False: arms.append(timeout_s))
    monkeypatch.setattr(module, "end_process", ends.append)
    return arms, ends


def _stuck_until(ends: list[str], limit_s: float) -> None:
    """The event loop stuck (this thread blocks it) until the watch has ended the process
    (faked: ``ends``), or a deadline well past the timeout."""
    deadline = time.monotonic() + limit_s + scaled(5.0)
    while not ends and time.monotonic() < deadline:
        time.sleep(0.01)


async def test_a_call_is_judged_at_each_wake_of_the_watch(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """In this process (faulthandler and the end faked): with calls returning, the watch's
    thread re-arms the backstop two timeouts ahead at each wake; a call waited for half the
    timeout is named once; one waited for the timeout ends the process, the report naming
    it, and the watch stops (no more re-arms)."""
    import asyncio

    from shared.loop_watchdog import WaitedCalls

    arms, ends = _fake_arms(monkeypatch)
    limit_s = scaled(1.0)  # the watch wakes every quarter of it
    calls = WaitedCalls()
    never = asyncio.get_running_loop().create_future()
    async with loop_watchdog(limit_s, calls):
        for _ in range(10):  # calls that return
            with calls.waiting_for("a quick call"):
                await asyncio.sleep(limit_s / 20)
        assert len(arms) >= 3 and set(arms) == {2 * limit_s}, arms
        assert calls.oldest() is None and ends == []
        with calls.waiting_for("a call that does not return"):
            async with asyncio.timeout(scaled(10.0)):
                while not ends:
                    await asyncio.wait({never}, timeout=0.01)
            oldest = calls.oldest()
            assert oldest is not None and oldest[0] == "a call that does not return"
        n = len(arms)
        await asyncio.sleep(limit_s)  # four periods: no re-arm, no second end
        assert len(arms) == n and len(ends) == 1
    assert re.fullmatch(r"Event loop watchdog: a call that does not return has not returned "
                        r"for \d+\.\d s; this process ends with exit code 1 \(hang_timeout_s "
                        rf"{limit_s:g} s\)\. Every thread's stack:", ends[0]), ends
    named = [r.getMessage() for r in caplog.records
             if r.getMessage().startswith("a call that does not return has not returned for ")]
    assert len(named) == 1 and "(hang_timeout_s)" in named[0], caplog.records


async def test_a_call_awaited_by_a_loop_that_stands_still_is_named_after_the_loop(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A call in flight when the loop got stuck reaches the timeout first (it began before
    the loop's last turn): it is judged once the loop has stood still for the timeout too,
    and the report names the loop, and the call after it."""
    import asyncio

    from shared.loop_watchdog import WaitedCalls

    _, ends = _fake_arms(monkeypatch)
    limit_s = scaled(1.0)
    calls = WaitedCalls()
    async with loop_watchdog(limit_s, calls):
        with calls.waiting_for("a frame's processing"):
            await asyncio.sleep(limit_s / 4)  # the call in flight, the loop turning
            _stuck_until(ends, limit_s)  # then the loop stuck
    assert len(ends) == 1 and re.match(
        r"Event loop watchdog: the event loop has not turned for \d+\.\d s \(a frame's "
        r"processing awaited for \d+\.\d s\); ", ends[0]), ends


async def test_a_turning_task_that_something_cancels_is_started_again(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Something cancels every task (its own task tearing down, say) while the block runs:
    the watch would end a healthy process without the task that tells it the loop turns; a
    new one is started, and a loop stuck after that is still seen."""
    import asyncio

    _, ends = _fake_arms(monkeypatch)
    limit_s = scaled(1.0)
    async with loop_watchdog(limit_s):
        for _ in range(2):
            [task] = [t for t in asyncio.all_tasks() if t.get_name() == "loop-watchdog"]
            task.cancel()
            await asyncio.sleep(1.5 * limit_s)  # the loop turning
        assert ends == [], ends
        _stuck_until(ends, limit_s)
        assert len(ends) == 1 and "the event loop has not turned for" in ends[0], ends
    assert not any(t.name == "loop-watchdog" for t in threading.enumerate())
    assert [r for r in caplog.records if r.levelname == "ERROR"] == []


async def test_a_watch_that_cannot_start_leaves_no_timer(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import faulthandler

    from shared import loop_watchdog as module

    _fake_arms(monkeypatch)
    cancels: list[None] = []
    monkeypatch.setattr(faulthandler, "cancel_dump_traceback_later",
                        lambda: cancels.append(None))

    def no_thread(self: object) -> None:
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(module._Watch, "start", no_thread)
    with pytest.raises(RuntimeError, match="can't start new thread"):
        async with loop_watchdog(scaled(1.0)):
            pass
    assert cancels == [None]


def test_a_stuck_loop_ends_its_process_with_its_stacks() -> None:
    timeout_s = scaled(3.0)
    done = _run(timeout_s, "stuck")
    assert_ended_by_loop_watchdog(done.returncode, done.stderr, "_stuck_in_a_blocking_call",
                                  stuck="the event loop has not turned for ")
    assert done.stdout == "turned\n"  # it ran three timeouts first: no early end


_BESIDE_THREADS_PROGRAM = textwrap.dedent('''
    import asyncio, ctypes, sys, threading, time
    from shared.loop_watchdog import loop_watchdog

    TIMEOUT_S, HOLDING_THE_GIL = float(sys.argv[1]), sys.argv[2] == "holding"

    def _deep(n):  # frames pushed and popped across the data stack's chunks all along
        return _deep(n - 1) if n else 0

    def _running_on():
        while True:
            _deep(900)

    def _stuck():
        if HOLDING_THE_GIL:  # C code that keeps the interpreter's lock: no thread runs
            ctypes.PyDLL(None).sleep(3600)
        time.sleep(3600)

    async def main():
        for _ in range(2):
            threading.Thread(target=_running_on, daemon=True).start()
        async with loop_watchdog(TIMEOUT_S):
            await asyncio.sleep(TIMEOUT_S / 2)
            print("stuck", time.monotonic(), flush=True)
            _stuck()

    asyncio.run(main())
''')


def test_a_stuck_loop_beside_threads_that_run_on_ends_with_its_stacks() -> None:
    """Two threads run Python on beside the stuck loop, their frames coming and going: the
    stacks are read where that is safe. (faulthandler's timer alone, the design before,
    read them while the threads ran on: it died of SIGSEGV (exit code -11) in a CI run, and
    in 10 of 20 runs of this program.) Five runs."""
    for _ in range(5):
        done = subprocess.run([sys.executable, "-c", _BESIDE_THREADS_PROGRAM,
                               str(scaled(1.0)), "sleeping"], capture_output=True, text=True,
                              timeout=scaled(60.0), check=False)
        assert_ended_by_loop_watchdog(done.returncode, done.stderr, "_stuck",
                                      stuck="the event loop has not turned for ")
        assert len(re.findall(r"^  File .+ in _running_on$", done.stderr, re.M)) == 2, \
            done.stderr[-2000:]


def test_a_loop_stuck_in_c_code_that_holds_the_gil_is_ended_by_the_backstop() -> None:
    """No Python thread runs, the watch's neither: faulthandler's thread ends the process
    (its ``Timeout`` line), two timeouts after the watch last ran: at the earliest about a
    period (a quarter of the timeout here) before the loop got stuck. (Armed only at the
    start, it would end half a timeout earlier.)"""
    timeout_s = scaled(1.0)
    with MachineStalls() as stalls:  # a stall before "stuck" can put off the last re-arm
        done = subprocess.run([sys.executable, "-c", _BESIDE_THREADS_PROGRAM, str(timeout_s),
                               "holding"], capture_output=True, text=True,
                              timeout=scaled(60.0), check=False)
    ended = time.monotonic()
    assert_ended_by_loop_watchdog(done.returncode, done.stderr, "_stuck", backstop=True)
    assert "Event loop watchdog" not in done.stderr
    stuck = float(done.stdout.split()[1])
    # (less a tenth of a timeout: the watch's wakes come late while the threads hold the
    # GIL in turns, a run saw 1.746 timeouts; armed only at the start: 1.5 timeouts)
    assert timeout_s * (2 - 0.25 - 0.1) - stalls.total_s <= ended - stuck <= \
        2 * timeout_s + scaled(5.0), (ended - stuck, stalls.stalls_s)


_PAUSED_PROGRAM = textwrap.dedent('''
    import asyncio, sys, threading
    from shared.loop_watchdog import loop_watchdog

    TIMEOUT_S = float(sys.argv[1])

    def _deep(n):
        return _deep(n - 1) if n else 0

    def _running_on():
        while True:
            _deep(900)

    async def main():
        for _ in range(2):
            threading.Thread(target=_running_on, daemon=True).start()
        async with loop_watchdog(TIMEOUT_S):
            print("watching", flush=True)
            await asyncio.sleep(3 * TIMEOUT_S)

    asyncio.run(main())
''')


def test_a_process_paused_for_less_than_two_timeouts_is_not_ended_by_the_backstop() -> None:
    """SIGSTOP for 1.1 timeouts (a paused container, a debugger): on resume the loop turns
    on, or the watch ends the process with its own reading of the stacks; faulthandler's
    backstop, which reads them while the threads run again, does not act (it had, at one
    timeout: a review). The watch has 0.9 timeouts less a period to run after SIGCONT."""
    timeout_s = scaled(2.0)
    proc = subprocess.Popen([sys.executable, "-c", _PAUSED_PROGRAM, str(timeout_s)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "watching\n"
        proc.send_signal(signal.SIGSTOP)
        time.sleep(1.1 * timeout_s)  # the pause itself
        proc.send_signal(signal.SIGCONT)
        _, stderr = proc.communicate(timeout=scaled(60.0))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "Timeout (" not in stderr, stderr[-2000:]
    if proc.returncode != 0:
        assert_ended_by_loop_watchdog(proc.returncode, stderr, "_run_once",
                                      stuck="the event loop has not turned for ")


def test_stacks_are_every_other_thread_s_most_recent_call_first() -> None:
    from shared.loop_watchdog import stacks

    release = threading.Event()

    def _a_waiting_function() -> None:
        release.wait()

    thread = threading.Thread(target=_a_waiting_function, name="the-waiting-thread")
    thread.start()
    try:
        text = stacks()
    finally:
        release.set()
        thread.join()
    blocks = {block.splitlines()[0]: block.splitlines()[1:] for block in text.split("\n\n")
              if block}
    [header] = [h for h in blocks if "'the-waiting-thread'" in h]
    assert re.fullmatch(rf"Thread 0x{thread.ident:016x} 'the-waiting-thread' \(most recent call "
                        r"first\):", header), header
    frames = blocks[header]
    assert all(re.fullmatch(r'  File ".+", line \d+ in \S+', line) for line in frames), frames
    names = [line.rsplit(" in ", 1)[1] for line in frames]
    assert names.index("wait") < names.index("_a_waiting_function") < names.index("run")
    assert not any(f"0x{threading.get_ident():016x}" in h for h in blocks)  # not the caller's


@pytest.mark.parametrize("scenario", ["turning", "left"])
def test_a_turning_loop_or_one_that_left_the_block_is_not_ended(scenario: str) -> None:
    done = _run(scaled(3.0), scenario)
    assert done.returncode == 0 and "Timeout (" not in done.stderr and \
        "Event loop watchdog" not in done.stderr, (done.returncode, done.stderr[-2000:])
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


async def test_a_backstop_that_cannot_be_re_armed_is_said_and_the_watch_goes_on(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """The watch's thread fails to re-arm faulthandler's timer: the timer is cancelled (one
    left armed would end a healthy process), an ERROR says what is no longer watched, and
    the watch itself goes on: a loop stuck after that still ends the process. (faulthandler
    faked: this is the test runner's process.)"""
    import asyncio
    import faulthandler

    from shared import loop_watchdog as module

    ends: list[str] = []
    monkeypatch.setattr(module, "end_process", ends.append)
    calls: list[str] = []

    def arm(timeout_s: float, file: object = None, exit: bool = False) -> None:
        calls.append("arm")
        if len(calls) == 4:
            raise OSError("stderr gone")

    monkeypatch.setattr(faulthandler, "dump_traceback_later", arm)
    monkeypatch.setattr(faulthandler, "cancel_dump_traceback_later",
                        lambda: calls.append("cancel"))
    limit_s = scaled(1.0)
    async with loop_watchdog(limit_s):  # armed twice at the start, then at each wake
        async with asyncio.timeout(scaled(10.0)):
            while "cancel" not in calls:
                await asyncio.sleep(0.01)
        await asyncio.sleep(limit_s)  # four more wakes: no re-arm
        assert calls == ["arm", "arm", "arm", "arm", "cancel"] and ends == [], (calls, ends)
        _stuck_until(ends, limit_s)
        assert len(ends) == 1 and "the event loop has not turned for" in ends[0], ends
    assert [r.getMessage() for r in caplog.records if r.levelname == "ERROR"] == [
        "the event loop watchdog's backstop (faulthandler's timer) failed: OSError('stderr "
        "gone'); a loop stuck in C code that keeps the interpreter's lock is not watched any "
        "more"]


@pytest.mark.parametrize("good", [0, 0.0, 1, 1.0, 30.0, 3600])
def test_a_hang_timeout_is_off_or_at_least_a_second(good: float) -> None:
    check_hang_timeout("x.hang_timeout_s", good)


@pytest.mark.parametrize("bad", [0.99, 0.1, -1.0, -1e-9, float("nan"), float("inf"), True,
                                 "10", None])
def test_anything_else_is_refused_by_name(bad: object) -> None:
    with pytest.raises(ConfigError, match=r"^x\.hang_timeout_s must be 0 \(no watchdog\) or a "
                                          r"finite number of seconds >= 1, got "):
        check_hang_timeout("x.hang_timeout_s", bad)
