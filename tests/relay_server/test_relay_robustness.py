"""A client's wild figures or a relay bug while writing cost one connection at most, and the
observers' view shows only what the relay accepted."""

from __future__ import annotations

from typing import Any

from relay_server.config import RelayConfig
from relay_server.server import RelayServer, _Connection
from shared.protocol import ArmState, PlatformState, Stats
from tests.relay_server.relay_clients import SECRET, clients, running_relay
from tests.support import async_wait_until


async def test_a_wild_station_clock_is_not_sampled_and_costs_no_connection() -> None:
    """A station whose pongs say t1 = t2 = 2**63 - 1 got an offset of ~9e18 us; its next
    message's delay overflowed the uplink ledger and the relay aborted it without a word."""
    async with running_relay(ping_burst=1) as relay, \
            clients(("tcp", 0), ("tcp", 0)) as (local, remote):
        await (await remote.connect(relay)).hello("remote", "wild")
        local.now = lambda: 2**63 - 1  # type: ignore[method-assign]
        await (await local.connect(relay)).hello("local", "wild")
        await local.expect("clock_ping")  # answered with the wild clock
        session = relay.sessions["wild"]
        peer = session.stations["local"]
        await async_wait_until(lambda: relay.counters["stray_pong"] or len(peer.clock), 2.0,
                               "the pong handled")
        await local.send(PlatformState(seq=1, ts_us=0))
        assert (await remote.expect("platform_state")).seq == 1
        assert peer.clock.offset_us is None and relay.counters["stray_pong"] >= 1
        assert session.directions["local_to_remote"].unsynced == 1


class _FakeWire:
    framing = "tcp"

    def __init__(self) -> None:
        self.written: list[bytes] = []
        self.closed: tuple[int, str] | None = None

    def ready(self) -> bool:
        return True

    def write_nowait(self, frames: list[bytes]) -> None:
        self.written += frames

    async def close(self, code: int = 1000, reason: str = "") -> None:
        self.closed = (code, reason)


async def test_a_failure_while_encoding_closes_that_peer_and_the_others_are_written() -> None:
    """``flush_now`` encoded the outbox outside its ``try``: an exception there (a ledger
    overflow in a forward's accounting) escaped ``RelayServer.flush``, and the peers after
    it in the same flush were not written."""
    relay = RelayServer(RelayConfig(host="127.0.0.1", port=0, tcp_port=0, secret=SECRET))
    bad, good = _Connection(relay, _FakeWire()), _Connection(relay, _FakeWire())  # type: ignore[arg-type]

    def broken(clock: Any) -> list[bytes]:
        raise OverflowError("Python int too large to convert to C long")

    bad.protocol.data_to_send = broken  # type: ignore[method-assign]
    for conn in (bad, good):
        conn.protocol.outbox.put_ordered(Stats(scope="relay", time_us=1, metrics={}))
    assert list(relay._to_flush) == [bad, good]
    relay.flush()
    assert len(good.transport.written) == 1  # type: ignore[attr-defined]
    assert bad.protocol.outbox.closed
    await async_wait_until(lambda: bad.transport.closed == (1011, "write failed"), 1.0,  # type: ignore[attr-defined]
                           "the failed peer closed")


async def test_the_view_shows_no_data_the_relay_refused() -> None:
    """A local station's forged ``arm_state`` got ``wrong_direction`` but was shown to the
    observers as the arm's state."""
    async with running_relay(view="127.0.0.1:0") as relay, \
            clients(("tcp", 0), ("tcp", 0)) as (local, remote):
        await (await local.connect(relay)).hello("local", "v")
        await (await remote.connect(relay)).hello("remote", "v")
        assert relay.view_hub is not None
        await local.send(ArmState(seq=1, ts_us=local.now(), position_mm=(123.0, 45.0, 6.0),
                                  force_n=9.0, status="fault"))
        err = await local.expect("error")
        assert err.code == "wrong_direction"
        probe = relay.view_hub.source("v").live()["probe"]
        assert probe["end_effector_mm"] is None and probe["arm_status"] is None
        await remote.send(ArmState(seq=1, ts_us=remote.now(), position_mm=(1.0, 2.0, 3.0)))
        await local.expect("arm_state")
        assert relay.view_hub.source("v").live()["probe"]["end_effector_mm"] == [1.0, 2.0, 3.0]
