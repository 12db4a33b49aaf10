"""The suite's leak checks (tests/conftest.py) see a thread, a socket and a CAN bus."""

from __future__ import annotations

import socket
import threading

import can

from tests.conftest import _can_channels, _leaks, _socket_fds, _threads


def _snapshot() -> tuple[set[threading.Thread], dict[int, str], dict[object, int]]:
    return _threads(), _socket_fds(), _can_channels()


def test_a_running_thread_is_a_leak_until_it_ends() -> None:
    before = _snapshot()
    stop = threading.Event()
    thread = threading.Thread(target=stop.wait, name="leaky-test-thread")
    thread.start()
    try:
        assert any("leaky-test-thread" in t for t in _leaks(*before)["thread"])
    finally:
        stop.set()
        thread.join()
    assert _leaks(*before)["thread"] == []


def test_an_open_socket_is_a_leak_until_closed() -> None:
    before = _snapshot()
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        assert any(f"fd {sock.fileno()} ->" in s for s in _leaks(*before)["socket"])
    finally:
        sock.close()
    assert _leaks(*before)["socket"] == []


def test_an_open_virtual_can_bus_is_a_leak_until_shut_down() -> None:
    before = _snapshot()
    bus = can.Bus(interface="virtual", channel="leak-fixture-test")
    try:
        assert any("leak-fixture-test" in b for b in _leaks(*before)["can_bus"])
    finally:
        bus.shutdown()
    assert _leaks(*before)["can_bus"] == []
