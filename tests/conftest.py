"""Suite-wide fixtures: fail any test that leaks a task, a thread, a socket or a CAN bus;
keep the stations' process-ending watchdog out of the test runner.

* ``_no_loop_watchdog_in_the_test_runner``: a station run in this process starts a watch
  (:mod:`shared.loop_watchdog`) that would end the whole test run when a test blocks its
  loop; here its ending of the process and faulthandler's timer do nothing (subprocesses keep
  theirs: ``tests/shared/test_loop_watchdog.py``, ``test_station_watchdogs.py`` and the
  relay's in ``tests/relay_server/test_relay_health.py`` test it there);
* ``_no_leaked_tasks``: asyncio tasks still running on the test's event loop;
* ``_no_leaked_resources``: threads, socket file descriptors of this process and python-can
  ``virtual`` bus channels that a test opened and did not close. Threads and sockets that
  are on their way out get a short grace period (``scaled(LEAK_GRACE_S)``).

The hypothesis profile comes from ``HYPOTHESIS_PROFILE`` (:data:`HYPOTHESIS_PROFILES`):
``ci`` (``.ci/run``) draws the same examples on every run of the same test code, so a
commit's CI result does not depend on a lucky draw; ``explore`` draws new examples on every
run with no example database (give ``--hypothesis-seed`` to repeat one); ``dev``, the
default, is hypothesis's own (new draws, and the local database replays past failures).

Library threads that live for the whole session by design are not leaks (see
``_LONG_LIVED_THREAD_PREFIXES``). A test that must leave something behind says so with
``@pytest.mark.allow_leaks("thread", "socket", "can_bus")`` and a comment saying why.
"""

from __future__ import annotations

import asyncio
import faulthandler
import os
import threading
import time
from collections.abc import AsyncIterator, Iterator

import pytest
from hypothesis import settings

from shared import loop_watchdog
from tests.support import scaled

LEAK_KINDS = ("thread", "socket", "can_bus")
LEAK_GRACE_S = 1.0

#: name prefixes of library threads that outlive a test on purpose. None found so far:
#: numba's parallel pools (workqueue/omp/tbb) are native threads that ``threading`` does
#: not list, and pytest-asyncio joins the event loop's default executor when it closes
#: the loop (before this check). Add a prefix here, with its owner, if a library needs it.
_LONG_LIVED_THREAD_PREFIXES: tuple[str, ...] = ()


#: the hypothesis profiles, chosen by ``HYPOTHESIS_PROFILE`` (see the module docstring).
#: None has a deadline: how long an example takes is the benchmarks' business, and on a
#: loaded machine any wall-clock bound fails at random (an example of
#: ``test_pin_ages_agree_with_a_brute_force_reference`` took 409 ms beside two CPU burners,
#: against hypothesis's default 200 ms deadline, and 0.5 ms when replayed)
#: Each starts from hypothesis's own ``default`` profile, not from whatever is loaded: where
#: the environment has ``CI`` set, hypothesis loads its built-in ``ci`` profile at import
#: (derandomized, no database), and ``dev`` would silently inherit it.
_BASE = settings.get_profile("default")
HYPOTHESIS_PROFILES = {
    "dev": settings(_BASE, deadline=None, print_blob=True),
    "ci": settings(_BASE, deadline=None, derandomize=True, database=None, print_blob=True),
    "explore": settings(_BASE, deadline=None, derandomize=False, database=None,
                        print_blob=True),
}
for _name, _profile in HYPOTHESIS_PROFILES.items():
    settings.register_profile(_name, _profile)


def _load_hypothesis_profile() -> None:
    name = os.environ.get("HYPOTHESIS_PROFILE", "dev")
    if name not in HYPOTHESIS_PROFILES:
        raise pytest.UsageError(f"HYPOTHESIS_PROFILE={name!r}: expected one of "
                                f"{', '.join(HYPOTHESIS_PROFILES)}")
    settings.load_profile(name)


_load_hypothesis_profile()


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "allow_leaks(*kinds): the test may leave threads/sockets/can_bus behind "
        f"(kinds: {', '.join(LEAK_KINDS)}); say why beside the marker")


def _threads() -> set[threading.Thread]:
    return {t for t in threading.enumerate()
            if t.is_alive() and not t.name.startswith(_LONG_LIVED_THREAD_PREFIXES)}


def _socket_fds() -> dict[int, str]:
    """This process's open socket descriptors: fd -> ``socket:[inode]``."""
    found: dict[int, str] = {}
    try:
        names = os.listdir("/proc/self/fd")
    except OSError:  # not Linux: no check
        return found
    for name in names:
        try:
            target = os.readlink(f"/proc/self/fd/{name}")
        except OSError:  # closed while listing
            continue
        if target.startswith("socket:"):
            found[int(name)] = target
    return found


def _can_channels() -> dict[object, int]:
    """Open python-can virtual buses: channel -> number of buses on it."""
    try:
        from can.interfaces import virtual
    except ImportError:
        return {}
    return {channel: len(queues) for channel, queues in list(virtual.channels.items())}


def _leaks(threads_before: set[threading.Thread], sockets_before: dict[int, str],
           can_before: dict[object, int]) -> dict[str, list[str]]:
    threads = [t for t in _threads() - threads_before if t is not threading.current_thread()]
    sockets = {fd: target for fd, target in _socket_fds().items()
               if sockets_before.get(fd) != target}
    can_now = _can_channels()
    buses = [f"{channel!r} ({n - can_before.get(channel, 0)} bus(es))"
             for channel, n in can_now.items() if n > can_before.get(channel, 0)]
    return {"thread": [repr(t) for t in threads],
            "socket": [f"fd {fd} -> {target}" for fd, target in sorted(sockets.items())],
            "can_bus": buses}


def _inert_dump_traceback_later(timeout: float, repeat: bool = False, file: object = None,
                                exit: bool = False) -> None:
    """``faulthandler.dump_traceback_later`` in the test runner's process: arms nothing."""


def _inert_cancel_dump_traceback_later() -> None:
    """``faulthandler.cancel_dump_traceback_later`` there: leaves pytest's own timer alone
    (``faulthandler_timeout``, when set)."""


def _inert_end_process(report: str) -> None:
    """``shared.loop_watchdog.end_process`` there: ends nothing (the watch's thread stops)."""


@pytest.fixture(autouse=True)
def _no_loop_watchdog_in_the_test_runner(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(faulthandler, "dump_traceback_later", _inert_dump_traceback_later)
    monkeypatch.setattr(faulthandler, "cancel_dump_traceback_later",
                        _inert_cancel_dump_traceback_later)
    monkeypatch.setattr(loop_watchdog, "end_process", _inert_end_process)


@pytest.fixture(autouse=True)
def _no_leaked_resources(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail a test that leaves a thread, a socket or a virtual CAN bus open."""
    marker = request.node.get_closest_marker("allow_leaks")
    allowed = set(marker.args) if marker is not None else set()
    unknown = allowed - set(LEAK_KINDS)
    if unknown:
        pytest.fail(f"allow_leaks: unknown kind(s) {sorted(unknown)}; use {LEAK_KINDS}")
    threads_before = _threads()
    sockets_before = _socket_fds()
    can_before = _can_channels()
    yield
    deadline = time.monotonic() + scaled(LEAK_GRACE_S)
    while True:
        leaks = {kind: items for kind, items in
                 _leaks(threads_before, sockets_before, can_before).items()
                 if items and kind not in allowed}
        if not leaks or time.monotonic() > deadline:
            break
        time.sleep(0.01)  # threads finishing, sockets being closed by their owners
    if leaks:
        details = "; ".join(f"{len(items)} {kind}(s): {items}" for kind, items in leaks.items())
        pytest.fail(f"test leaked {details}", pytrace=False)


@pytest.fixture(autouse=True)
async def _no_leaked_tasks() -> AsyncIterator[None]:
    """Fail an async test that leaves tasks running on its event loop."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:  # sync test: nothing to check
        yield
        return
    before = asyncio.all_tasks()
    yield
    current = asyncio.current_task()
    leaked = [t for t in asyncio.all_tasks() - before if t is not current and not t.done()]
    if leaked:
        for t in leaked:
            t.cancel()
        await asyncio.gather(*leaked, return_exceptions=True)
        pytest.fail(f"test leaked {len(leaked)} asyncio task(s): "
                    f"{[t.get_coro() for t in leaked]}")
