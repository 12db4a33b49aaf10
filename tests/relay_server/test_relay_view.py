"""The relay's live view for observers: observer token required, built from routed messages."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

import numpy as np
import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from relay_server.auth import derive_token, make_token
from shared.errors import ConfigError
from shared.protocol import ArmState, Hop, PlatformState, TactileFrame
from tests.relay_server.relay_clients import SECRET, clients, running_relay
from tests.support import async_wait_until, scaled


async def _snapshot(ws: ClientConnection, predicate: Any, what: str,
                    timeout_s: float = 5.0, trail: list[Any] | None = None) -> dict[str, Any]:
    """The first snapshot that satisfies ``predicate`` (trail points of all go to ``trail``)."""
    try:
        async with asyncio.timeout(scaled(timeout_s)):
            while True:
                msg = json.loads(await ws.recv())
                if trail is not None:
                    trail += msg["trail"]["points"]
                if predicate(msg):
                    return dict(msg)
    except TimeoutError as err:
        raise AssertionError(f"no snapshot with {what} within {scaled(timeout_s):.1f} s") \
            from err


async def test_observer_sees_patch_trajectory_arm_and_stages_of_its_session() -> None:
    async with running_relay(view="127.0.0.1:0") as relay, \
            clients(("ws", 0), ("ws", 0)) as (local, remote):
        assert relay.view_server is not None and relay.view_server.port
        await (await local.connect(relay)).hello("local", "s1")
        await (await remote.connect(relay)).hello("remote", "s1")
        token = make_token(SECRET, "s1", "observer", int(time.time()) + 600)
        async with connect(f"ws://127.0.0.1:{relay.view_server.port}/ws") as ws:
            await ws.send(json.dumps({"type": "hello", "session": "s1", "token": token}))
            for i in range(3):
                await local.send(PlatformState(
                    seq=i + 1, ts_us=local.now(), hops=(Hop("local", "capture", local.now()),),
                    position_mm=(30.0 + i, 30.0, 40.0)))
                await remote.expect("platform_state")
                await asyncio.sleep(0.03)  # trajectory points are at least 25 ms apart
            height = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
            await remote.send(TactileFrame(
                seq=1, ts_us=remote.now(), hops=(Hop("remote", "tactile_ready", remote.now()),),
                layers={"height_mm": height}, contact=True, force_n=2.5))
            await remote.send(ArmState(seq=1, ts_us=remote.now(), position_mm=(1.0, 2.0, -3.0),
                                       force_n=2.5))
            await local.expect("tactile_frame")
            trail: list[list[float]] = []
            msg = await _snapshot(ws, lambda m: m["live"]["patch"] is not None
                                  and m["live"]["probe"]["end_effector_mm"] is not None,
                                  "patch and arm", trail=trail)
            live = msg["live"]
            assert live["station"] == "relay" and live["session"] == "s1"
            assert live["link"] == {"state": "up", "stations": ["local", "remote"]}
            assert live["pins"] is None and live["safe"]["known"] is False
            assert (live["patch"]["w"], live["patch"]["h"]) == (4, 3)
            assert live["patch"]["contact"] is True and live["patch"]["force_n"] == 2.5
            assert live["probe"]["end_effector_mm"] == [1.0, 2.0, -3.0]
            assert live["probe"]["platform_mm"] == [32.0, 30.0, 40.0]
            async with asyncio.timeout(scaled(5)):
                while len(trail) < 3:
                    trail += json.loads(await ws.recv())["trail"]["points"]
            assert [p[0] for p in trail] == [0.0, 1.0, 2.0]  # phantom x (default workspace)
            assert "stages_ms" in live["latency"]


@pytest.mark.parametrize("case", ["wrong_token", "local_token", "other_session", "no_hello",
                                  "legacy_token", "table_token", "expired"])
async def test_the_relay_view_needs_an_observer_token_of_the_session(case: str) -> None:
    now = int(time.time())
    hello = {
        "wrong_token": {"session": "s1", "token": make_token("other", "s1", "observer",
                                                             now + 60)},
        "local_token": {"session": "s1", "token": make_token(SECRET, "s1", "local", now + 60)},
        "other_session": {"session": "s1",
                          "token": make_token(SECRET, "s2", "observer", now + 60)},
        # a legacy token names no role: a station's opens every role of the relay, but not
        # the observers' view (docs/security.md: only a v2 observer token reads the view)
        "legacy_token": {"session": "s1", "token": derive_token(SECRET, "s1")},
        "table_token": {"session": "s1", "token": "table-token-of-s1"},
        "expired": {"session": "s1", "token": make_token(SECRET, "s1", "observer", now - 1)},
        "no_hello": None}[case]
    table = {"s1": "table-token-of-s1"} if case == "table_token" else {}
    async with running_relay(view="127.0.0.1:0", tokens=table) as relay:
        assert relay.view_server is not None
        relay.view_server.config = type(relay.view_server.config)(hello_timeout_s=0.3)
        async with connect(f"ws://127.0.0.1:{relay.view_server.port}/ws") as ws:
            if hello is not None:
                await ws.send(json.dumps({"type": "hello", **hello}))
            with pytest.raises(ConnectionClosed) as err:
                await ws.recv()
            assert err.value.rcvd is not None and err.value.rcvd.code == 4001
        await async_wait_until(lambda: relay.view_server is not None
                               and relay.view_server.counters["clients_unauthorized"] == 1,
                               2, "the refusal counted")


async def test_the_relay_view_off_by_default_and_a_busy_port_is_a_config_error() -> None:
    async with running_relay() as relay:
        assert relay.view_server is None and relay.view_hub is None
        with pytest.raises(ConfigError, match="cannot listen"):
            async with running_relay(view=f"127.0.0.1:{relay.ws_port}"):
                pass


async def test_an_open_view_is_closed_when_its_token_expires() -> None:
    async with running_relay(view="127.0.0.1:0") as relay:
        assert relay.view_server is not None
        expiry = int(time.time()) + 2
        token = make_token(SECRET, "s1", "observer", expiry)
        async with connect(f"ws://127.0.0.1:{relay.view_server.port}/ws") as ws:
            await ws.send(json.dumps({"type": "hello", "session": "s1", "token": token}))
            assert json.loads(await ws.recv())["type"] == "snapshot"
            with pytest.raises(ConnectionClosed) as err:
                async with asyncio.timeout(2 + scaled(5)):
                    while True:
                        await ws.recv()
            assert err.value.rcvd is not None and err.value.rcvd.code == 4001
            assert time.time() >= expiry
        assert relay.view_server.counters["clients_expired"] == 1


async def _upgrade(port: int, host: str, origin: str) -> int:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(f"GET /ws HTTP/1.1\r\nHost: {host}\r\nOrigin: {origin}\r\n"
                     "Connection: Upgrade\r\nUpgrade: websocket\r\n"
                     "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                     "Sec-WebSocket-Version: 13\r\n\r\n".encode())
        await writer.drain()
        async with asyncio.timeout(scaled(5)):
            status = await reader.readline()
    finally:
        writer.close()
    return int(status.split()[1])


async def test_the_relay_view_answers_its_public_name_but_not_another_sites_page() -> None:
    async with running_relay(view="127.0.0.1:0") as relay:
        assert relay.view_server is not None and relay.view_server.port
        port = relay.view_server.port
        public = f"relay.example.org:{port}"  # its DNS name, or a TLS proxy keeping the Host
        assert await _upgrade(port, public, f"http://{public}") == 101
        assert await _upgrade(port, "relay.example.org", "https://relay.example.org") == 101
        assert await _upgrade(port, public, "https://evil.example") == 403
        assert relay.view_server.counters["ws_forbidden_origin"] == 1


def test_the_trail_is_stored_compactly_and_read_back_exactly() -> None:
    import tracemalloc

    from relay_server.view import SessionViewSource
    from shared.workspace import WorkspaceMap

    src = SessionViewSource("s1", WorkspaceMap())
    n = 5000
    msgs = [PlatformState(seq=i + 1, ts_us=i, position_mm=(30.0 + i * 0.01, 30.25, 40.0))
            for i in range(n)]
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for i, msg in enumerate(msgs):
            src.observe(msg, 1_000_000 + i * 25_000)  # one trajectory point each
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grown < 40 * n, f"{grown / n:.0f} bytes per trajectory point"
    def expected(i: int) -> list[float]:
        ph = src.workspace.forward(np.asarray(msgs[i].position_mm, dtype=np.float64))
        return [round(float(v), 2) for v in ph] + [0.0]

    first, points = src.trail_since(0, 10)
    assert first == 0 and points == [expected(i) for i in range(10)]
    first, points = src.trail_since(n - 2, 10)
    assert first == n - 2 and points == [expected(n - 2), expected(n - 1)]
