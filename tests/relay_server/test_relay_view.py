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

from relay_server.auth import make_token
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


@pytest.mark.parametrize("case", ["wrong_token", "local_token", "other_session", "no_hello"])
async def test_the_relay_view_needs_an_observer_token_of_the_session(case: str) -> None:
    now = int(time.time())
    hello = {
        "wrong_token": {"session": "s1", "token": make_token("other", "s1", "observer",
                                                             now + 60)},
        "local_token": {"session": "s1", "token": make_token(SECRET, "s1", "local", now + 60)},
        "other_session": {"session": "s1",
                          "token": make_token(SECRET, "s2", "observer", now + 60)},
        "no_hello": None}[case]
    async with running_relay(view="127.0.0.1:0") as relay:
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
