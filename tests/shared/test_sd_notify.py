"""The systemd notifications (shared.sd_notify) against a real AF_UNIX datagram socket, as
systemd listens: readiness, watchdog pings from the event loop, stopping."""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from shared.sd_notify import Notifier, service
from tests.support import scaled


@pytest.fixture(params=["path", "abstract"])
def manager(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[str, socket.socket]]:
    """A socket listening as systemd's does: its ``NOTIFY_SOCKET`` value and the socket."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    if request.param == "path":
        name = str(tmp_path / "notify")
        sock.bind(name)
    else:
        name = f"@teletouch-test-{uuid.uuid4().hex}"
        sock.bind("\0" + name[1:])
    sock.settimeout(scaled(5.0))
    with sock:
        yield name, sock


def _messages(sock: socket.socket, count: int) -> list[str]:
    return [sock.recv(4096).decode() for _ in range(count)]


async def test_ready_watchdog_and_stopping_reach_the_manager(
        manager: tuple[str, socket.socket]) -> None:
    name, sock = manager
    env = {"NOTIFY_SOCKET": name, "WATCHDOG_USEC": "40000", "WATCHDOG_PID": str(os.getpid()),
           "OTHER": "kept"}
    notifier = Notifier(env)
    assert env == {"OTHER": "kept"}  # taken out: the service's children do not speak for it
    assert notifier.active and notifier.watchdog_period_s == 0.02
    async with service("relay serving on :8765", notifier):
        ready = await asyncio.to_thread(_messages, sock, 1)
        assert ready == ["READY=1\nSTATUS=relay serving on :8765"]
        pings = await asyncio.to_thread(_messages, sock, 3)  # every 20 ms, from this loop
        assert pings == ["WATCHDOG=1"] * 3
    rest = await asyncio.to_thread(_drain_until_stopping, sock)
    assert set(rest[:-1]) <= {"WATCHDOG=1"} and rest[-1] == "STOPPING=1"


def _drain_until_stopping(sock: socket.socket) -> list[str]:
    out: list[str] = []
    while not out or out[-1] != "STOPPING=1":
        out += _messages(sock, 1)
    return out


async def test_a_stuck_event_loop_stops_the_pings(manager: tuple[str, socket.socket]) -> None:
    """What the watchdog is for: while the loop is blocked no ping goes out."""
    import time

    name, sock = manager
    async with service("x", Notifier({"NOTIFY_SOCKET": name, "WATCHDOG_USEC": "20000"})):
        assert await asyncio.to_thread(_messages, sock, 2) == ["READY=1\nSTATUS=x",
                                                               "WATCHDOG=1"]
        assert set(_queued(sock)) <= {"WATCHDOG=1"}  # sent while this task awaited
        time.sleep(0.2)  # the loop blocked (deliberately, in this test) for 20 periods
        assert _queued(sock) == []
        assert await asyncio.to_thread(_messages, sock, 1) == ["WATCHDOG=1"]  # runs again


def _queued(sock: socket.socket) -> list[str]:
    """What waits in the socket now (without waiting)."""
    out = []
    sock.settimeout(0.0)
    try:
        while True:
            out.append(sock.recv(4096).decode())
    except BlockingIOError:
        return out
    finally:
        sock.settimeout(scaled(5.0))


@pytest.mark.parametrize("env", [{}, {"WATCHDOG_USEC": "40000"}, {"NOTIFY_SOCKET": ""}])
async def test_without_a_manager_nothing_is_sent(env: dict[str, str]) -> None:
    notifier = Notifier(dict(env))
    assert not notifier.active and notifier.watchdog_period_s is None
    async with service("x", notifier):
        assert not notifier.notify("STATUS=y")


@pytest.mark.parametrize(("usec", "pid"), [("0", None), ("abc", None), ("40000", "other")])
def test_no_watchdog_unless_it_is_this_process_s(usec: str, pid: str | None,
                                                 manager: tuple[str, socket.socket]) -> None:
    env = {"NOTIFY_SOCKET": manager[0], "WATCHDOG_USEC": usec}
    if pid is not None:
        env["WATCHDOG_PID"] = str(os.getpid() + 1)  # another process's watchdog
    notifier = Notifier(env)
    assert notifier.active and notifier.watchdog_period_s is None


def test_a_manager_that_went_away_is_warned_of_once(tmp_path: Path,
                                                    caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="shared.sd_notify")
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone")})
    assert not notifier.notify("READY=1") and not notifier.notify("WATCHDOG=1")
    assert len(caplog.records) == 1 and "cannot notify" in caplog.records[0].getMessage()
    relative = Notifier({"NOTIFY_SOCKET": "not/a/socket"})
    assert not relative.active


def test_a_manager_that_does_not_read_never_blocks_the_sender(
        manager: tuple[str, socket.socket], caplog: pytest.LogCaptureFixture) -> None:
    """A unix datagram queue holds few messages (``net.unix.max_dgram_qlen``, 10 here): a
    blocking send would stall the event loop once the manager stops reading. Past that the
    messages are dropped, counted and said once."""
    caplog.set_level(logging.WARNING, logger="shared.sd_notify")
    import threading

    notifier = Notifier({"NOTIFY_SOCKET": manager[0]})
    sent: list[bool] = []  # more than the queue holds
    queue = int(Path("/proc/sys/net/unix/max_dgram_qlen").read_text())
    sender = threading.Thread(  # a blocked send must fail this test, not hang it
        target=lambda: sent.extend(notifier.notify("WATCHDOG=1") for _ in range(queue + 50)),
        daemon=True)
    sender.start()
    sender.join(scaled(10.0))
    assert not sender.is_alive(), f"blocked after {len(sent)} messages"
    assert sent[0] and not sent[-1] and notifier.dropped == sent.count(False) > 0
    assert len(caplog.records) == 1 and "queue is full" in caplog.records[0].getMessage()


def test_ready_waits_for_room_in_the_managers_queue(manager: tuple[str, socket.socket]) -> None:
    """A ping finding the manager's queue full is dropped, but ``READY=1`` (said once; lost,
    the unit would stay starting until systemd kills it) waits for room, up to its limit."""
    import threading

    name, sock = manager
    notifier = Notifier({"NOTIFY_SOCKET": name})
    queue = int(Path("/proc/sys/net/unix/max_dgram_qlen").read_text())
    for _ in range(queue + 50):
        if not notifier.notify("WATCHDOG=1"):
            break
    assert notifier.dropped == 1  # full now
    reader = threading.Timer(0.2, sock.recv, (4096,))  # the manager reads again, later
    reader.start()
    try:
        assert notifier.notify("READY=1", "STATUS=x", wait_s=scaled(5.0))
    finally:
        reader.join()
    assert notifier.dropped == 1
