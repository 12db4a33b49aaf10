"""The supervisor of ``teletouch relay --workers N`` (:mod:`relay_server.workers`): the clock
and the events it hands its workers, what it tells systemd, and the watch that kills and
replaces a worker that hangs without dying (real spawned processes whose event loop blocks)."""

from __future__ import annotations

import asyncio
import dataclasses
import faulthandler
import logging
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from relay_server import server, workers
from relay_server.config import RelayConfig
from shared import timebase
from shared.loop_watchdog import loop_watchdog
from shared.sd_notify import Notifier
from tests.support import NotifySocket, assert_ended_by_loop_watchdog, scaled, wait_until


class _Beat:
    """A worker's shared beat counter (``multiprocessing.Value``), faked."""

    def __init__(self) -> None:
        self.value = 0


class _Failure:
    """A worker's shared start error (``multiprocessing.Array`` of bytes), faked."""

    def __init__(self) -> None:
        self.value = b""


#: the fake contexts' ``Array``
_ARRAY = staticmethod(lambda typecode, size, lock: _Failure())


def test_a_supervisors_workers_stamp_on_its_clock(monkeypatch: pytest.MonkeyPatch) -> None:
    """``run_workers`` hands its wall anchor to every worker it starts, and a worker adopts
    it before serving: the workers of one supervisor stamp on one clock, also when the wall
    clock was stepped between their starts (here: the supervisor's anchor 7 s off)."""
    monkeypatch.setattr(timebase, "_ANCHOR_NS", timebase.wall_anchor_ns() + 7_000_000_000)
    supervisor_anchor = timebase.wall_anchor_ns()
    started: list[tuple[Any, ...]] = []

    class _Process:  # the spawned worker, not started: its arguments are what it would get
        pid = None
        exitcode = 0

        def __init__(self, target: Any, args: tuple[Any, ...], name: str) -> None:
            started.append((target, *args))

        def start(self) -> None:
            if len(started) == 2:  # both spawned: the supervisor is asked to stop
                signal.raise_signal(signal.SIGTERM)

        def is_alive(self) -> bool:
            return False

        def join(self, timeout: float | None = None) -> None:
            pass

    class _Context:
        Process = _Process
        Event = threading.Event
        Value = staticmethod(lambda typecode, value, lock: _Beat())
        Array = _ARRAY

    monkeypatch.setattr(workers.mp, "get_context", lambda method: _Context())
    config = RelayConfig(nats_url="nats://127.0.0.1:1", port=18765, tcp_port=18766,
                         allow_any_token=True)
    workers.run_workers(config, 2)
    assert [(s[0], s[3]) for s in started] == [(workers._worker_main, supervisor_anchor)] * 2
    assert started[0][1] == dataclasses.replace(config, reuse_port=True)

    # the worker's side: its clock is the supervisor's once it serves
    monkeypatch.setattr(timebase, "_ANCHOR_NS", supervisor_anchor - 9_000_000_000)
    seen: list[int] = []

    async def serve(config: RelayConfig, started: Any = None) -> None:
        seen.append(timebase.wall_anchor_ns())

    monkeypatch.setattr(server, "serve_forever", serve)
    old_sigint = signal.getsignal(signal.SIGINT)
    try:
        workers._worker_main(*started[0][1:])
    finally:
        signal.signal(signal.SIGINT, old_sigint)
        faulthandler.unregister(workers.STACK_DUMP_SIGNAL)
    assert seen == [supervisor_anchor]


def test_the_supervisor_is_ready_once_every_worker_serves(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``READY=1`` waits for the last worker's ports (its ``serving`` event), not for the
    spawn; pings go out meanwhile (a slow start is not a hang). Workers faked, events real."""
    notify = NotifySocket()
    notifier = Notifier({"NOTIFY_SOCKET": notify.name, "WATCHDOG_USEC": "100000"})
    monkeypatch.setattr(workers, "process_notifier", lambda: notifier)
    serving: list[Any] = []
    before_last: list[list[str]] = []

    class _Process:
        pid = None
        exitcode = 0

        def __init__(self, target: Any, args: tuple[Any, ...], name: str) -> None:
            serving.append(args[3])

        def start(self) -> None:
            pass

        def is_alive(self) -> bool:
            return True

        def join(self, timeout: float | None = None) -> None:
            pass

        def kill(self) -> None:
            pass

    class _Context:
        Process = _Process
        Event = threading.Event
        Value = staticmethod(lambda typecode, value, lock: _Beat())
        Array = _ARRAY

    def workers_come_up() -> None:
        serving[0].set()
        # a worker still starting: the supervisor pings, and says nothing more
        notify.until(lambda got: len(got) >= 3, scaled(10.0))
        before_last.append(notify.texts())
        serving[1].set()
        notify.until(lambda got: any(t.startswith("READY=1") for _, t in got), scaled(10.0))
        signal.raise_signal(signal.SIGTERM)  # then the supervisor is stopped

    monkeypatch.setattr(workers.mp, "get_context", lambda method: _Context())
    starter = threading.Timer(0.1, workers_come_up)
    starter.start()
    try:
        workers.run_workers(RelayConfig(nats_url="nats://127.0.0.1:1", port=18765,
                                        tcp_port=18766, hang_timeout_s=0,
                                        allow_any_token=True), 2)
        notify.until(lambda got: bool(got) and got[-1][1] == "STOPPING=1", scaled(10.0))
    finally:
        starter.join()
        texts = notify.texts()
        notify.close()
    assert before_last and set(before_last[0]) == {"WATCHDOG=1"}, before_last
    said = [t for t in texts if t != "WATCHDOG=1"]
    assert said[0].startswith("READY=1\nSTATUS=relay supervisor: 2 workers") and \
        said[-1] == "STOPPING=1" and len(said) == 2, texts


# --------------------------------------------------------------------------- hung workers


class _Ready:
    """A worker's ``serving`` event, faked (set: its ports are bound)."""

    def __init__(self, is_set: bool = True) -> None:
        self._set = is_set

    def is_set(self) -> bool:
        return self._set

    def set(self) -> None:
        self._set = True


@pytest.mark.parametrize("timeout_s", [1.0, 10.0, 120.0])
def test_a_beat_that_stands_still_past_the_timeout_is_stuck(timeout_s: float) -> None:
    """Stuck exactly when the beat has not moved for more than the limit since it last
    moved (or since the spawn, or an excuse): ``timeout_s`` once the worker serves, the start
    allowance (or ``timeout_s`` if longer) before; the reason says which."""
    beat, ready = _Beat(), _Ready(False)
    watch = workers._Progress(beat, ready, 100.0, timeout_s)
    start_limit = max(timeout_s, workers.START_ALLOWANCE_S)
    assert watch.stuck(100.0 + start_limit) is None
    why = watch.stuck(100.0 + start_limit + 0.2)
    assert why == (f"made no progress for {start_limit + 0.2:.1f} s while starting (its "
                   f"event loop is stuck; {start_limit:g} s allowed before it serves)")
    watch.excuse(200.0)
    assert watch.stuck(200.0 + start_limit) is None
    beat.value += 1  # beats, still starting: the allowance, counted from this beat
    assert watch.stuck(300.0) is None
    assert watch.stuck(300.0 + start_limit) is None
    assert watch.stuck(300.0 + start_limit + 0.2) is not None
    ready.set()  # serving: the timeout, from the last beat seen
    beat.value += 1
    assert watch.stuck(400.0) is None
    assert watch.stuck(400.0 + timeout_s) is None
    assert watch.stuck(400.0 + timeout_s + 0.2) == (
        f"made no progress for {timeout_s + 0.2:.1f} s (its event loop is stuck, and it did "
        f"not end itself; limit {timeout_s:g} s)")
    beat.value += 1
    assert watch.stuck(500.0 + timeout_s * 5) is None  # moved: counted from this round
    assert watch.stuck(500.0 + timeout_s * 6) is None
    assert watch.stuck(500.0 + timeout_s * 6 + 0.2) is not None
    watch.excuse(600.0)
    assert watch.stuck(600.0 + timeout_s) is None
    assert watch.stuck(600.0 + timeout_s + 0.2) is not None


class _FakeClock:
    """``time`` for the supervisor: ``sleep`` advances ``now`` and, up to the sleep
    ``beats_until`` (sleeps counted from 1), the worker's beat; ``pauses`` maps a sleep to
    one that lasts that long with no beat (the host frozen: the supervisor and its worker
    alike). The supervisor is stopped after ``rounds`` sleeps."""

    def __init__(self, beat: _Beat, rounds: int, pauses: dict[int, float],
                 beats_until: int) -> None:
        self.now = 1000.0
        self.beat = beat
        self.rounds = 0
        self.last = rounds
        self.pauses = pauses
        self.beats_until = beats_until
        self.beats: list[float] = []  # when the beat moved

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.rounds += 1
        if self.rounds in self.pauses:
            self.now += self.pauses[self.rounds]
            return
        self.now += seconds
        if self.rounds <= self.beats_until:
            self.beat.value += 1
            self.beats.append(self.now)
        if self.rounds >= self.last:
            signal.raise_signal(signal.SIGTERM)


def _fake_supervisor(monkeypatch: pytest.MonkeyPatch, clock: _FakeClock,
                     kills: list[float]) -> None:
    """``run_workers`` with workers faked (alive, serving, sharing ``clock.beat``) and its
    clock ``clock``; a kill is recorded at the time the supervisor decided it (before its
    wait for the stacks)."""
    class _Process:
        pid = None
        exitcode = None

        def __init__(self, target: Any, args: tuple[Any, ...], name: str) -> None:
            self.alive = True

        def start(self) -> None:
            pass

        def is_alive(self) -> bool:
            return self.alive

        def join(self, timeout: float | None = None) -> None:
            pass

        def kill(self) -> None:
            self.alive = False
            if clock.rounds < clock.last:  # not the supervisor's own stop
                kills.append(clock.now - workers._DUMP_WAIT_S)

    class _Context:
        Process = _Process
        Event = _Ready
        Value = staticmethod(lambda typecode, value, lock: clock.beat)
        Array = _ARRAY

    monkeypatch.setattr(workers.mp, "get_context", lambda method: _Context())
    monkeypatch.setattr(workers, "time", clock)


#: the supervisor's limit for a worker that did not end itself, 10.1 s: it falls between
#: two of the supervisor's rounds (0.2 s apart)
_CONFIG = RelayConfig(nats_url="nats://127.0.0.1:1", port=18765, tcp_port=18766,
                      hang_timeout_s=10.1 - workers.SELF_EXIT_MARGIN_S, allow_any_token=True)


def test_a_supervisor_that_did_not_run_gives_its_workers_a_fresh_timeout(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """A host frozen for 30 s (both the supervisor and its worker, whose beat stood still
    meanwhile) is not a hung worker: the supervisor sees its own gap and restarts the count.
    A worker whose beat then stays still is killed one timeout later, not before."""
    # the round after the pause is the worker's last beat: it hangs from then on
    clock = _FakeClock(_Beat(), rounds=200, pauses={20: 30.0}, beats_until=21)
    kills: list[float] = []
    _fake_supervisor(monkeypatch, clock, kills)
    workers.run_workers(_CONFIG, 1)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(m.startswith("relay supervisor did not run for 30.0 s") for m in warned), warned
    # the beat moved last in the round after the pause (the 30 s before it excused): killed
    # in the first round more than 10.1 s after it; each replacement (same fake beat, still)
    # gets its own 10.1 s from its spawn, after the wait for the stacks
    last_beat = clock.beats[-1]
    assert last_beat == pytest.approx(1000.0 + 20 * 0.2 + 30.0)
    assert kills and kills[0] == pytest.approx(last_beat + 10.2), (kills, last_beat)
    spawned = [kill + workers._DUMP_WAIT_S for kill in kills[:-1]]
    assert all(10.1 < kill - spawn <= 10.3
               for spawn, kill in zip(spawned, kills[1:], strict=True)), kills


def test_without_the_gap_a_stood_still_beat_is_killed(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """The same worker, the same 30 s with no beat, but the supervisor ran through them: a
    hang, killed in the first round past the timeout (the control of the test above)."""
    clock = _FakeClock(_Beat(), rounds=100, pauses={}, beats_until=20)
    kills: list[float] = []
    _fake_supervisor(monkeypatch, clock, kills)
    workers.run_workers(_CONFIG, 1)
    last_beat = clock.beats[-1]
    assert last_beat == pytest.approx(1000.0 + 20 * 0.2)
    assert len(kills) == 1 and kills[0] == pytest.approx(last_beat + 10.2), (kills, last_beat)
    assert not [r for r in caplog.records if "did not run" in r.getMessage()]


def test_no_watch_with_the_hang_timeout_off(monkeypatch: pytest.MonkeyPatch) -> None:
    """``hang_timeout_s`` 0 (a debugger's breakpoint stops the loop): a worker whose beat
    stands still for longer than the start allowance is left alone."""
    clock = _FakeClock(_Beat(), rounds=400, pauses={}, beats_until=5)
    kills: list[float] = []
    _fake_supervisor(monkeypatch, clock, kills)
    workers.run_workers(dataclasses.replace(_CONFIG, hang_timeout_s=0.0), 1)
    assert clock.now - clock.beats[-1] > workers.START_ALLOWANCE_S + 10.0 and not kills


def test_the_command_line_sets_the_hang_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    from lab.cli import build_parser
    from relay_server import cli

    got: list[tuple[RelayConfig, int]] = []
    monkeypatch.setattr(workers, "run_workers", lambda config, count: got.append((config,
                                                                                  count)))
    args = build_parser().parse_args(["relay", "--workers", "2", "--nats", "nats://127.0.0.1:1",
                                      "--hang-timeout-s", "3.5"])
    assert cli.run(args) == 0
    assert [(config.hang_timeout_s, count) for config, count in got] == [(3.5, 2)]


def _stuck_in_a_blocking_call() -> None:
    time.sleep(3600)  # a call that does not return, on the event loop's thread


def _worker_that_hangs(config: RelayConfig, log_level: int, anchor_ns: int | None = None,
                       serving: Any = None, beat: Any = None, failure: Any = None) -> None:
    """The real worker (``workers._worker_main``) with a relay whose event loop blocks for
    good once it serves and has beaten twice; with ``TT_TEST_WORKER_WATCHDOG`` set, under
    the loop watchdog the relay's serving uses. Started by ``run_workers`` in a process of
    its own."""
    with Path(os.environ["TT_TEST_WORKER_PIDS"]).open("a") as pids:
        pids.write(f"{os.getpid()}\n")
    own_watchdog = config.hang_timeout_s if os.environ.get("TT_TEST_WORKER_WATCHDOG") else 0

    async def serve(config: RelayConfig, started: Any = None) -> None:
        if started is not None:
            started(None)
        async with loop_watchdog(own_watchdog):
            while beat.value < 2:
                await asyncio.sleep(0.01)
            _stuck_in_a_blocking_call()

    server.serve_forever = serve  # this process is the worker: nothing else runs here
    workers._worker_main(config, log_level, anchor_ns, serving, beat, failure)


@pytest.mark.parametrize("ends_itself", [False, True])
def test_a_worker_that_hangs_is_replaced_with_its_stacks_logged(
        ends_itself: bool, monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
        capfd: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture) -> None:
    """A spawned worker whose event loop blocks (alive, but serving nothing) is replaced,
    its threads' stacks (the blocking call among them) written first. With its own loop
    watchdog (as every relay has) it ends itself at ``hang_timeout_s`` and the supervisor
    starts another on its exit, before its own limit; without one (a worker that cannot end
    itself) the supervisor finds it once its beat has stood still for ``hang_timeout_s``
    and the margin, and kills it."""
    pids = tmp_path / "pids"
    monkeypatch.setenv("TT_TEST_WORKER_PIDS", str(pids))
    if ends_itself:
        monkeypatch.setenv("TT_TEST_WORKER_WATCHDOG", "1")
    monkeypatch.setattr(workers, "_worker_main", _worker_that_hangs)
    caplog.set_level(logging.WARNING, logger="relay_server.workers")

    def started() -> list[int]:
        return [int(pid) for pid in pids.read_text().split()] if pids.exists() else []

    failed: list[BaseException] = []

    def stop_once_replaced() -> None:
        try:
            wait_until(lambda: len(started()) >= 2, 60.0, "a second worker", poll_s=0.05)
        except BaseException as err:
            failed.append(err)
        finally:
            signal.raise_signal(signal.SIGTERM)  # the supervisor stops (also on a failure)

    stopper = threading.Thread(target=stop_once_replaced)
    stopper.start()
    try:
        workers.run_workers(dataclasses.replace(_CONFIG, hang_timeout_s=scaled(1.0)), 1)
    finally:
        stopper.join()
    assert not failed, failed
    first = started()[0]
    said = [(r.levelno, r.getMessage()) for r in caplog.records]
    errors = [text for level, text in said if level >= logging.ERROR]
    stderr = capfd.readouterr().err
    if ends_itself:
        assert not errors, said
        assert (logging.WARNING, f"relay worker {first} exited (code 1; if its own watchdog "
                "ended it, its stacks are above); starting another in 1 s") in said, said
        assert_ended_by_loop_watchdog(1, stderr, "_stuck_in_a_blocking_call",
                                      stuck="the event loop has not turned for ")
        return
    assert len(errors) == 1 and errors[0].startswith(
        f"relay worker {first} made no progress for "), said
    assert "(its event loop is stuck, and it did not end itself; limit" in errors[0], errors
    assert (logging.WARNING, f"relay worker {first} killed (the stacks it wrote, if it had "
            "started, are above)") in said, said
    assert "in _stuck_in_a_blocking_call" in stderr, stderr[-3000:]
