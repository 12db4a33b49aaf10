"""A WebSocket opening handshake that never completes (a silent socket, a request sent a
byte at a time and never finished) is cut after the relay's open timeout, and meanwhile the
relay serves everyone else."""

from __future__ import annotations

import asyncio
import time

import pytest

from relay_server import server as relay_module
from tests.relay_server.relay_clients import running_relay
from tests.relay_server.test_relay_isolation_and_status import http_get
from tests.support import scaled


async def _closed_after(reader: asyncio.StreamReader, timeout_s: float) -> float:
    """Seconds until the relay closed the socket (EOF or reset)."""
    t0 = time.monotonic()
    async with asyncio.timeout(timeout_s):
        try:
            while await reader.read(4096):
                pass
        except ConnectionError:
            pass
    return time.monotonic() - t0


@pytest.mark.parametrize("sends", [b"", b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgr"])
async def test_an_unfinished_opening_handshake_is_cut_and_others_are_served(
        monkeypatch: pytest.MonkeyPatch, sends: bytes) -> None:
    open_timeout_s = scaled(0.5)
    monkeypatch.setattr(relay_module, "_OPEN_TIMEOUT_S", open_timeout_s)
    async with running_relay() as relay:
        reader, writer = await asyncio.open_connection("127.0.0.1", relay.ws_port)
        try:
            writer.write(sends)
            await writer.drain()
            code, _, _ = await http_get(relay.ws_port, "/status")  # not held up meanwhile
            assert code == 200
            elapsed = await _closed_after(reader, open_timeout_s + scaled(5.0))
        finally:
            writer.close()
        assert elapsed <= open_timeout_s + scaled(2.0)
