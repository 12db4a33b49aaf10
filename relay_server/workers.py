"""Relay workers on one host: ``teletouch relay --workers N --nats URL``.

``run_workers`` runs N relay processes (*workers*, joined by NATS: :mod:`relay_server.cluster`)
all bound to the same ports with SO_REUSEPORT, so the kernel spreads new connections over
them, and supervises them:

* before it starts any, it builds what every worker would (the token authority from the
  credentials and the token file, the TLS context, the NATS CA): a bad setting is one clear
  error, not N workers dying at start; ``view`` is refused with more than one worker (each
  would bind it);
* a worker that **dies before it ever served** (bound its ports) ends the supervisor with its
  error (exit 1): a worker that cannot start would not start the next time either;
* a worker that **dies** after it served is started again, after a delay that doubles with
  each quick death (``_RESTART_MIN_S`` to ``_RESTART_MAX_S``; back to the shortest once one
  ran ``_STEADY_S``): never given up, never a hot crash loop;
* a worker that **hangs** without dying is killed and started again. A relay process ends
  itself when its event loop is stuck for ``hang_timeout_s`` (:mod:`shared.loop_watchdog`:
  within a beat of it),
  and its supervisor then starts another as for any death; the supervisor's own watch is for
  a worker that cannot end itself (stopped, or not scheduled while the supervisor is).
  Every worker's event loop advances a counter in memory shared with its supervisor (its
  *beat*, every ``BEAT_S``, or a quarter of the timeout if that is less); one whose beat
  stands still for ``hang_timeout_s`` + ``SELF_EXIT_MARGIN_S`` (``START_ALLOWANCE_S`` until
  it serves) is stuck. SO_REUSEPORT would otherwise keep handing it new connections that it
  never serves. Before the kill the worker is sent ``STACK_DUMP_SIGNAL``, on which it writes
  every thread's stack to its standard error (:mod:`faulthandler`, which needs no help from
  the stuck interpreter, and reads the stacks of threads that may run on: a dump can be cut
  short by SIGSEGV, of a worker being killed anyway): the log says where it hung. A
  supervisor that was itself not
  running for a while (a paused VM, a starved host) gives every worker a fresh timeout
  rather than blaming them for its own gap. ``hang_timeout_s`` 0: neither watch;
* under systemd it alone speaks for the service: ``READY=1`` once every worker serves,
  ``WATCHDOG=1`` from its loop, ``STOPPING=1`` (:mod:`shared.sd_notify`);
* its wall anchor goes to every worker it starts, so one host's workers stamp on one clock.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import faulthandler
import logging
import multiprocessing as mp
import os
import signal
import time
from typing import Any

from relay_server.cluster import redact_url
from relay_server.config import RelayConfig
from shared.errors import ConfigError
from shared.loop_watchdog import rearm_period_s
from shared.sd_notify import SAY_WAIT_S, process_notifier
from shared.timebase import adopt_wall_anchor, wall_anchor_ns

__all__ = ["BEAT_S", "SELF_EXIT_MARGIN_S", "STACK_DUMP_SIGNAL", "START_ALLOWANCE_S", "run_workers",
           "worker_count"]

log = logging.getLogger(__name__)

#: a worker's event loop advances its beat this often
BEAT_S = 0.5
#: the supervisor's limit for a beat that stands still, beyond ``hang_timeout_s``: a stuck
#: worker that can end itself (its own watchdog, at ``hang_timeout_s``) does so first
SELF_EXIT_MARGIN_S = 2.0
#: a worker's beat may stand still this long until it serves (or the limit above if longer):
#: an interpreter's start and the relay's imports and TLS set-up take seconds on a loaded host
START_ALLOWANCE_S = 60.0
#: a worker writes every thread's stack to its standard error on this signal (and goes on)
STACK_DUMP_SIGNAL = signal.SIGUSR2
#: how long stuck workers are given to write their stacks before they are killed
_DUMP_WAIT_S = 1.0
#: how long the supervisor waits for a killed worker to end before it goes on
_REAP_WAIT_S = 0.1
#: the supervisor's loop period
_ROUND_S = 0.2
#: a worker that died after it served is started again after this delay, doubled for each
#: further death of its replacements up to ``_RESTART_MAX_S``...
_RESTART_MIN_S = 1.0
_RESTART_MAX_S = 30.0
#: ...until one of them ran this long (then the shortest delay again)
_STEADY_S = 60.0
#: room for a worker's start error, told to its supervisor (``_worker_main``'s ``failure``)
_FAILURE_BYTES = 1024
#: a supervisor round that came this much later than due (or half the hang timeout, if less)
#: means the supervisor itself was not running (the workers were probably not either): every
#: worker gets a fresh timeout
_SUPERVISOR_GAP_S = 2.0


def worker_count(config: RelayConfig) -> int:
    """Worker processes to run: ``workers``, else one per core when clustered, else 1."""
    if config.workers:
        return config.workers
    return (os.cpu_count() or 1) if config.nats_url else 1


async def _beat(beat: Any, period_s: float) -> None:
    """Advance ``beat`` (a shared unsigned counter) every ``period_s`` while the loop runs."""
    while True:
        beat.value += 1
        await asyncio.sleep(period_s)


async def _serve_beating(config: RelayConfig, serving: Any, beat: Any) -> None:
    from relay_server.server import serve_forever

    period_s = rearm_period_s(config.hang_timeout_s) if config.hang_timeout_s else BEAT_S
    beating = None if beat is None else asyncio.create_task(_beat(beat, period_s),
                                                            name="worker-beat")
    try:
        await serve_forever(config, None if serving is None else lambda relay: serving.set())
    finally:
        if beating is not None:
            beating.cancel()


def _worker_main(config: RelayConfig, log_level: int, anchor_ns: int | None = None,
                 serving: Any = None, beat: Any = None, failure: Any = None) -> None:
    """A worker of ``run_workers``: serve until SIGTERM; set ``serving`` (an event) once the
    ports are bound; advance ``beat`` (a shared counter) from the event loop; an error before
    ``serving`` is set goes to ``failure`` (a shared byte array) for the supervisor. The
    optional arguments may be missing (a supervisor of an earlier release)."""
    if anchor_ns is not None:  # None: started by a supervisor of an earlier release
        adopt_wall_anchor(anchor_ns)  # the supervisor's clock: its workers' stamps agree
    logging.basicConfig(level=log_level,
                        format=f"%(asctime)s worker-{os.getpid()} %(levelname)s %(name)s: "
                               "%(message)s")
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the supervisor says when (SIGTERM)
    faulthandler.register(STACK_DUMP_SIGNAL, all_threads=True)  # before a hung one's kill
    try:
        asyncio.run(_serve_beating(config, serving, beat))
    except BaseException as err:
        if failure is not None and serving is not None and not serving.is_set():
            failure.value = f"{type(err).__name__}: {err}".encode()[:_FAILURE_BYTES - 1]
        raise


def _check_before_spawning(config: RelayConfig, count: int) -> None:
    """Build what every worker builds before it serves, to fail once, clearly.

    Raises:
        ConfigError: ``view`` with more than one worker, or what the relay itself refuses
            (no credentials, an unreadable token file, TLS certificate or NATS CA file, a
            bad view address).
    """
    from relay_server.server import RelayServer
    from shared.view import parse_view_address

    if config.view.strip():
        if count > 1:
            raise ConfigError(f"relay.view ({config.view}) needs a single relay process, not "
                              f"{count} workers (relay.workers, --workers; one per core by "
                              "default with --nats): each would bind the view's address; "
                              "set --workers 1 or turn the view off")
        parse_view_address(config.view)
    RelayServer(config)  # the token authority (credentials, token file), the TLS context
    config.check_nats_ca_file()


class _Progress:
    """A worker's progress as its supervisor sees it: when its beat last moved.

    Args:
        beat: the worker's shared counter.
        serving: its event, set once its ports are bound.
        now_s: the spawn time (the supervisor's monotonic clock).
        timeout_s: a beat that stands still this long means a stuck worker (once it serves;
            until then :data:`START_ALLOWANCE_S` if that is longer: a starting worker's loop
            may block a while on imports, TLS set-up and a full garbage collection); None:
            never stuck.
    """

    def __init__(self, beat: Any, serving: Any, now_s: float, timeout_s: float | None
                 ) -> None:
        self.beat = beat
        self.serving = serving
        self._seen = beat.value
        self._since = now_s
        self._timeout_s = timeout_s

    def excuse(self, now_s: float) -> None:
        """A fresh timeout from ``now_s`` (the supervisor was not running before)."""
        self._since = now_s

    def stuck(self, now_s: float) -> str | None:
        """Why the worker counts as stuck (None: it does not)."""
        value = self.beat.value
        if value != self._seen:
            self._seen, self._since = value, now_s
            return None
        if self._timeout_s is None:
            return None
        still_s = now_s - self._since
        if self.serving.is_set():
            if still_s <= self._timeout_s:
                return None
            return (f"made no progress for {still_s:.1f} s (its event loop is stuck, and it "
                    f"did not end itself; limit {self._timeout_s:g} s)")
        limit = max(self._timeout_s, START_ALLOWANCE_S)
        if still_s <= limit:
            return None
        return (f"made no progress for {still_s:.1f} s while starting (its event loop is "
                f"stuck; {limit:g} s allowed before it serves)")


def _kill_stuck(procs: list[mp.process.BaseProcess]) -> list[mp.process.BaseProcess]:
    """Have stuck workers write their stacks (:data:`STACK_DUMP_SIGNAL`, then SIGCONT: a
    stopped worker takes the signal once woken; one wait for all), then kill them. Returns
    those not yet reaped (for later rounds: a process in an uninterruptible wait dies only
    when that wait ends, and the supervisor does not wait)."""
    for proc in procs:
        if proc.pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, STACK_DUMP_SIGNAL)
                os.kill(proc.pid, signal.SIGCONT)
    time.sleep(_DUMP_WAIT_S)
    for proc in procs:
        proc.kill()
        log.warning("relay worker %s killed (the stacks it wrote, if it had started, are "
                    "above)", proc.pid)
    return [proc for proc in procs if not _reaped(proc)]


def _reaped(proc: mp.process.BaseProcess) -> bool:
    proc.join(_REAP_WAIT_S)
    return not proc.is_alive()


def run_workers(config: RelayConfig, count: int) -> None:
    """Run ``count`` relay workers on this host (one process each, SO_REUSEPORT) until
    SIGINT or SIGTERM; restart a worker that dies or hangs (see the module's docstring).

    Raises:
        ConfigError: no ``nats_url``, or port 0 (the workers must share fixed ports); a
            setting every worker would refuse at its start (see
            :func:`_check_before_spawning`); a worker that died before it ever served
            (its error in the message).
    """
    if not config.nats_url:
        raise ConfigError("--workers needs --nats nats://HOST:PORT")
    if config.port == 0 or config.resolved_tcp_port == 0:
        raise ConfigError("--workers needs fixed ports (not 0): the workers share them")
    _check_before_spawning(config, count)
    worker_config = dataclasses.replace(config, reuse_port=True)
    # systemd hears this process alone (its variables were taken out of the environment at
    # start: the workers do not inherit them), ready once every worker serves
    notifier = process_notifier()
    ctx = mp.get_context("spawn")
    level = logging.getLogger().getEffectiveLevel()
    procs: list[mp.process.BaseProcess] = []
    serving: list[Any] = []  # per worker, an event it sets once its ports are bound
    progress: list[_Progress] = []
    failures: list[Any] = []  # per worker, its start error (a shared byte array)
    born: list[float] = [time.monotonic()] * count  # per worker, when it was started
    served = [False] * count  # per slot: a worker in it has served
    quick = [0] * count  # per slot: deaths since one of its workers ran _STEADY_S
    due: dict[int, float] = {}  # slots of dead workers -> when to start another
    dying: list[mp.process.BaseProcess] = []  # killed, not yet reaped
    stopping = False

    def stop(*_: object) -> None:
        nonlocal stopping
        stopping = True

    old = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}

    limit_s = (config.hang_timeout_s + SELF_EXIT_MARGIN_S) if config.hang_timeout_s else None

    def spawn() -> tuple[mp.process.BaseProcess, Any, _Progress, Any]:
        ready = ctx.Event()
        beat = ctx.Value("Q", 0, lock=False)
        failure = ctx.Array("c", _FAILURE_BYTES, lock=False)
        proc = ctx.Process(target=_worker_main, args=(worker_config, level, wall_anchor_ns(),
                                                      ready, beat, failure),
                           name="teletouch-relay-worker")
        proc.start()
        return proc, ready, _Progress(beat, ready, time.monotonic(), limit_s), failure

    def restart(i: int) -> None:
        procs[i], serving[i], progress[i], failures[i] = spawn()
        born[i] = time.monotonic()

    try:
        for _ in range(count):
            proc, ready, watch, failure = spawn()
            procs.append(proc)
            serving.append(ready)
            progress.append(watch)
            failures.append(failure)
        log.info("relay: %d workers on ports %d/%d joined by %s", count, config.port,
                 config.resolved_tcp_port, redact_url(config.nats_url))
        said_ready = False
        period = notifier.watchdog_period_s
        round_s = _ROUND_S if period is None else min(_ROUND_S, period / 2)
        gap_s = min(_SUPERVISOR_GAP_S, config.hang_timeout_s / 2) if config.hang_timeout_s \
            else _SUPERVISOR_GAP_S
        pinged = last_round = time.monotonic()
        while not stopping:
            time.sleep(round_s)
            now = time.monotonic()
            if now - last_round > round_s + gap_s:
                log.warning("relay supervisor did not run for %.1f s: every worker gets a "
                            "fresh hang timeout", now - last_round)
                for watch in progress:
                    watch.excuse(now)
            if not said_ready and all(ready.is_set() for ready in serving):
                said_ready = True
                notifier.notify("READY=1", f"STATUS=relay supervisor: {count} workers on "
                                f"ports {config.port}/{config.resolved_tcp_port}",
                                wait_s=SAY_WAIT_S)
            if period is not None and now - pinged >= period:
                notifier.notify("WATCHDOG=1")  # this loop's liveness (it restarts workers)
                pinged = now
            stuck = []
            for i, proc in enumerate(procs):
                if i in due:
                    continue  # dead, another starts later
                alive = proc.is_alive()
                served[i] = served[i] or serving[i].is_set()  # after: set, then died: served
                if not alive:
                    if stopping:  # a stop's SIGTERM to the process group ended it: expected
                        break
                    if not served[i]:  # it could not start: nor would the next one
                        why = failures[i].value.decode(errors="replace") or "no error told"
                        raise ConfigError(f"relay worker {proc.pid} ended before it served "
                                          f"(exit code {proc.exitcode}): {why}")
                    if now - born[i] >= _STEADY_S:
                        quick[i] = 0
                    delay_s = min(_RESTART_MAX_S, _RESTART_MIN_S * 2 ** quick[i])
                    quick[i] = min(quick[i] + 1, 16)
                    due[i] = now + delay_s
                    log.warning("relay worker %s exited (code %s%s); starting another in %g s",
                                proc.pid, proc.exitcode, "; if its own watchdog ended it, "
                                "its stacks are above" if proc.exitcode == 1 else "", delay_s)
                elif (why := progress[i].stuck(now)) is not None:
                    log.error("relay worker %s %s: killing it and starting another; its "
                              "threads' stacks follow in its log", proc.pid, why)
                    stuck.append(i)
            if stuck:
                dying += _kill_stuck([procs[i] for i in stuck])
            dying = [proc for proc in dying if proc.is_alive()]  # is_alive reaps
            for i in stuck + [i for i, at in due.items() if at <= now]:
                if stopping:
                    break
                due.pop(i, None)
                restart(i)
            last_round = time.monotonic()  # a round's own work is not a gap
    finally:
        notifier.notify("STOPPING=1", wait_s=SAY_WAIT_S)
        for proc in procs:
            if proc.is_alive() and proc.pid is not None:
                os.kill(proc.pid, signal.SIGTERM)
        for proc in procs + dying:
            proc.join(10.0)
            if proc.is_alive():
                proc.kill()
                proc.join(10.0)
        for sig, handler in old.items():
            signal.signal(sig, handler)
