"""Closing a StationLink leaves no unread task error behind (asyncio would log it)."""

from __future__ import annotations

import asyncio
import gc
import logging

import pytest

from relay_server.config import RelayConfig
from relay_server.server import RelayServer
from shared.client import StationLink
from tests.support import scaled


async def test_close_logs_no_lost_task_exception(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.ERROR, logger="asyncio")
    config = RelayConfig(host="127.0.0.1", port=0, tcp_port=0, allow_any_token=True)
    async with RelayServer(config) as relay:
        link = StationLink(f"ws://127.0.0.1:{relay.ws_port}/", session="s", role="local",
                           token="x")
        async with link:
            await link.wait_connected(scaled(5.0))
            await asyncio.sleep(scaled(0.1))
    await asyncio.sleep(scaled(0.05))
    gc.collect()
    await asyncio.sleep(0)
    lost = [r for r in caplog.records if "never retrieved" in r.getMessage()]
    assert lost == []
