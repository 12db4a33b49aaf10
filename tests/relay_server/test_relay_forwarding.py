"""Relay integration over real sockets: forwarding, hops, observers, clock offsets, stats."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from relay_server.server import RelayServer
from shared.protocol import ArmCommand, ArmState, PlatformState, TactileFrame, Welcome
from shared.timebase import now_us
from tests.relay_server.relay_clients import Client, clients, running_relay
from tests.support import MachineStalls, scaled


def platform(seq: int, clock_us: int) -> PlatformState:
    return PlatformState(seq=seq, ts_us=clock_us, position_mm=(1.0, 2.0, float(seq)),
                         velocity_mm_s=(0.0, 0.0, 0.0))


async def join_pair(relay: RelayServer, session: str, local: Client, remote: Client) -> None:
    await local.connect(relay)
    await remote.connect(relay)
    welcome_local = await local.hello("local", session)
    welcome_remote = await remote.hello("remote", session)
    assert isinstance(welcome_local, Welcome) and isinstance(welcome_remote, Welcome)
    assert welcome_local.role == "local"
    assert welcome_remote.role == "remote"


async def test_two_sessions_both_directions_ws_and_tcp() -> None:
    async with running_relay() as relay, clients(("ws", 0), ("tcp", 0), ("tcp", 0),
                                                 ("ws", 0)) as (l1, r1, l2, r2):
        await join_pair(relay, "s1", l1, r1)
        await join_pair(relay, "s2", l2, r2)
        await l1.send(ArmCommand(seq=1, ts_us=l1.now(), action="move",
                                 target_mm=(1.0, 2.0, 3.0)))
        cmd = await r1.expect("arm_command")
        assert cmd.target_mm == (1.0, 2.0, 3.0)
        stages = [(h.clock, h.stage) for h in cmd.hops]
        assert stages == [("relay", "relay_in"), ("relay", "relay_out")]
        assert cmd.hops[0].t_us <= cmd.hops[1].t_us
        layers = {"height_mm": np.zeros((4, 4), np.float32)}
        await r2.send(TactileFrame(seq=7, ts_us=r2.now(), layers=layers, contact=True))
        frame = await l2.expect("tactile_frame")
        assert frame.seq == 7 and frame.contact
        np.testing.assert_array_equal(frame.layers["height_mm"], layers["height_mm"])
        await r1.send(ArmState(seq=3, ts_us=r1.now(), position_mm=(0.0, 0.0, 1.0)))
        assert (await l1.expect("arm_state")).seq == 3
        await l2.send(platform(11, l2.now()))
        assert (await r2.expect("platform_state")).seq == 11
        # nothing crossed sessions
        assert not [m for m in r2.inbox + l1.inbox if isinstance(m, ArmCommand | ArmState)
                    and m.seq in (1, 3)]


async def test_observer_gets_both_directions_and_is_read_only() -> None:
    async with running_relay() as relay, clients(("ws", 0), ("tcp", 0), ("ws", 0)) as (
            local, remote, obs):
        await join_pair(relay, "obs", local, remote)
        await obs.connect(relay)
        await obs.hello("observer", "obs")
        await local.send(ArmCommand(seq=1, ts_us=local.now(), action="stop"))
        await remote.send(ArmState(seq=2, ts_us=remote.now(), position_mm=(0.0, 0.0, 0.0)))
        got = {(await obs.expect(t)).TYPE for t in ("arm_command", "arm_state")}
        assert got == {"arm_command", "arm_state"}
        await obs.send(ArmCommand(seq=5, ts_us=now_us(), action="stop"))
        err = await obs.expect("error")
        assert err.code == "read_only" and not err.fatal
        await remote.expect("arm_command")  # the local's command only
        await asyncio.sleep(scaled(0.05))
        assert not [m for m in remote.inbox if m.TYPE == "arm_command"]


async def test_clock_offsets_and_stats_push() -> None:
    offset_local, offset_remote = 250_000, -1_300_000
    async with running_relay() as relay, clients(("ws", offset_local), ("tcp", offset_remote)
                                                 ) as (local, remote):
        await join_pair(relay, "clk", local, remote)
        stats = None
        with MachineStalls() as stalls:  # a stall lengthens the first round trips
            for _ in range(20):  # pings are answered while waiting
                stats = await local.expect("stats", skip=("clock_ping",))
                await remote.expect("stats", skip=("clock_ping",))
                off = stats.metrics["clock_offset_us"]
                if off["local"] is not None and off["remote"] is not None:
                    break
        assert stats is not None
        off = stats.metrics["clock_offset_us"]
        # loopback round trips are well under 20 ms even on a loaded machine
        bound_us = scaled(20_000) + stalls.total_s * 1e6
        assert abs(off["local"] - offset_local) < bound_us, (off, stalls.stalls_s)
        assert abs(off["remote"] - offset_remote) < bound_us, (off, stalls.stalls_s)
        for seq in range(30):
            await local.send(platform(seq, local.now()))
            await asyncio.sleep(0.002)
        for _ in range(30):
            stats = await remote.expect("stats", skip=("clock_ping", "platform_state"))
            if stats.metrics["forwarded"]["local_to_remote"] >= 1 and \
                    stats.metrics["delay_us"]["local_to_remote"]["station_to_relay"]["p50"] \
                    is not None:
                break
        m = stats.metrics
        assert m["role"] == "remote" and m["session"] == "clk"
        up = m["delay_us"]["local_to_remote"]["station_to_relay"]
        # offset-corrected one-way delay on loopback: small, not ~250 ms (scaled: queueing on
        # a loaded machine adds tens of ms)
        assert -scaled(20_000) < up["p50"] < scaled(20_000)
        assert m["delay_us"]["local_to_remote"]["relay"]["p99"] >= 0
        assert set(m["drops"]["local_to_remote"]) == {"lost", "latest_wins", "queue_full",
                                                      "no_peer"}
        assert set(m["queue_depth"]) == {"local", "remote"}


class _ForeignTransport:
    """A stream transport of another event loop: asyncio's interface, not its class (as
    uvloop's transports are)."""

    def __init__(self, inner: asyncio.BaseTransport) -> None:
        self._inner = inner

    def __getattr__(self, name: str) -> object:
        return getattr(self._inner, name)


async def test_transports_need_asyncios_interface_not_its_class(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # the relay's connections are protocols of any event loop whose transports implement
    # asyncio.Transport's methods: an isinstance check refused uvloop's
    from relay_server import wire

    made = wire.Wire.connection_made
    foreign: list[object] = []

    def connection_made(self: wire.Wire, transport: asyncio.BaseTransport) -> None:
        proxy = _ForeignTransport(transport)
        assert not isinstance(proxy, asyncio.Transport)
        foreign.append(proxy)
        made(self, proxy)  # type: ignore[arg-type]

    monkeypatch.setattr(wire.Wire, "connection_made", connection_made)
    async with running_relay() as relay, clients(("ws", 0), ("tcp", 0)) as (local, remote):
        await join_pair(relay, "s1", local, remote)
        await local.send(platform(5, local.now()))
        assert (await remote.expect("platform_state")).seq == 5
    assert len(foreign) == 2
