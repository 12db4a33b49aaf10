"""Relay limits (issue 11 item 4), with real sockets: connections per address and in total,
the pre-hello size bound, the per-connection message rate. Each refusal has its own code,
is logged once, and the relay keeps serving."""

from __future__ import annotations

import logging
import math
import struct

import msgpack
import pytest

from relay_server.server import RelayServer
from shared.protocol import ArmCommand, ClockPing
from tests.relay_server.relay_clients import Client, clients, running_relay
from tests.support import async_wait_until, scaled


def framed(payload: bytes, kind: str) -> bytes:
    return payload if kind == "ws" else struct.pack(">I", len(payload)) + payload


async def pair_works(relay: RelayServer, session: str) -> None:
    async with clients(("tcp", 0), ("ws", 0)) as (local, remote):
        await local.connect(relay)
        await remote.connect(relay)
        await local.hello("local", session)
        await remote.hello("remote", session)
        await local.send(ArmCommand(seq=1, ts_us=local.now(), action="stop"))
        assert (await remote.expect("arm_command")).seq == 1


async def send_many(c: Client, payload: bytes, n: int) -> None:
    """``n`` copies of one framed message, as fast as the transport takes them."""
    if c.kind == "ws":
        for _ in range(n):
            await c.send_raw(payload)
    else:
        await c.send_raw(payload * n)


async def expect_refused(c: Client, code: str, close_code: int) -> None:
    err = await c.expect("error")
    assert (err.code, err.fatal) == (code, True), err
    got = await c.expect_closed()
    if c.kind == "ws":
        assert got == close_code


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_connections_per_address_are_capped(kind: str,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    async with running_relay(max_connections_per_ip=3) as relay, clients(
            *[(kind, 0)] * 4) as conns:
        for c in conns[:3]:
            await c.connect(relay)
        await async_wait_until(lambda: len(relay._connections) == 3, scaled(2.0))
        caplog.clear()
        await conns[3].connect(relay)
        await expect_refused(conns[3], "too_many_connections", 1013)
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and "too_many_connections" in warnings[0], warnings
        assert relay.counters["refused_connections"] == 1
        await conns[0].close()  # a slot frees up: the relay serves again
        await async_wait_until(lambda: len(relay._connections) == 2, scaled(2.0))
        await conns[1].hello("local", "cap")


async def test_connections_in_total_are_capped() -> None:
    async with running_relay(max_connections=2) as relay, clients(
            ("tcp", 0), ("ws", 0), ("ws", 0)) as (a, b, c):
        await a.connect(relay)
        await b.connect(relay)
        await async_wait_until(lambda: len(relay._connections) == 2, scaled(2.0))
        await c.connect(relay)
        await expect_refused(c, "too_many_connections", 1013)
        await a.hello("local", "tot")
        await b.hello("remote", "tot")


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_before_hello_a_connection_buffers_at_most_max_hello_bytes(kind: str) -> None:
    async with running_relay(max_hello_bytes=4096) as relay, clients((kind, 0)) as (c,):
        await c.connect(relay)
        big = msgpack.packb({"v": 1, "type": "hello", "role": "local", "session": "h",
                             "token": "t", "pad": b"x" * 6000})
        # TCP: the header alone is refused, the relay does not wait for (or buffer) the body
        await c.send_raw(framed(big, kind)[:100] if kind == "tcp" else big)
        await expect_refused(c, "oversize", 1009)
        await pair_works(relay, "h")


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_after_hello_the_full_size_applies(kind: str) -> None:
    async with running_relay(max_hello_bytes=4096) as relay, clients((kind, 0)) as (c,):
        await c.connect(relay)
        await c.hello("local", "full")
        ping = msgpack.packb({"v": 1, "type": "clock_ping", "ping_id": 7, "t0_us": 1,
                              "pad": b"x" * 100_000})
        await c.send_raw(framed(ping, kind))
        pong = await c.expect("clock_pong")
        assert pong.ping_id == 7


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_message_rate_limit_warns_then_closes_when_sustained(
        kind: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    async with running_relay(rate_limit_per_s=50.0, rate_limit_burst=100) as relay, clients(
            (kind, 0)) as (c,):
        await c.connect(relay)
        await c.hello("local", "rate")
        ping = c.conn.encode(ClockPing(ping_id=1, t0_us=1))
        caplog.clear()
        await send_many(c, ping, 130)  # 100 granted, ~30 over: a warning, not a close
        err = await c.expect("error", skip=("clock_ping", "stats", "clock_pong"))
        assert (err.code, err.fatal) == ("rate_limited", False), err
        assert relay.counters["rate_limited"] >= 1
        await send_many(c, ping, 300)  # sustained: more than a burst refused -> closed
        while True:
            err = await c.expect("error", skip=("clock_ping", "stats", "clock_pong"))
            if err.fatal:
                break
        assert err.code == "rate_limited"
        got = await c.expect_closed()
        if kind == "ws":
            assert got == 1008
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 2 and all("rate_limited" in w for w in warnings), warnings
        await pair_works(relay, "rate2")


async def test_the_rate_limit_does_not_touch_a_1khz_stream() -> None:
    async with running_relay() as relay, clients(("tcp", 0)) as (c,):
        await c.connect(relay)
        await c.hello("local", "fast")
        batch = b"".join(c.conn.encode(ArmCommand(seq=i, ts_us=1, action="stop"))
                         for i in range(2000))  # a 2 s backlog of a 1 kHz stream at once
        await c.send_raw(batch)
        errs = [await c.expect("error", skip=("clock_ping", "stats")) for _ in range(5)]
        assert all(e.code == "no_peer" for e in errs)
        assert relay.counters["rate_limited"] == 0


@pytest.mark.parametrize("bad", ["yes", 1, None])
def test_lock_memory_must_be_a_boolean(bad: object) -> None:
    from relay_server.config import RelayConfig
    from shared.errors import ConfigError

    with pytest.raises(ConfigError, match=r"relay\.lock_memory must be true or false"):
        RelayConfig(lock_memory=bad)  # type: ignore[arg-type]
    assert RelayConfig().lock_memory is True


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf])
def test_the_nats_connect_timeout_must_be_finite_and_positive(bad: float) -> None:
    from relay_server.config import RelayConfig
    from shared.errors import ConfigError

    with pytest.raises(ConfigError, match=r"relay\.nats_connect_timeout_s must be a finite"):
        RelayConfig(nats_connect_timeout_s=bad)
    assert RelayConfig().nats_connect_timeout_s == 10.0


@pytest.mark.parametrize("bad", [0.99, 0.1, -1.0, -0.0 - 1e-9, math.nan, math.inf])
def test_the_hang_timeout_is_off_or_at_least_a_second(bad: float) -> None:
    from relay_server.config import RelayConfig
    from shared.errors import ConfigError

    with pytest.raises(ConfigError, match=r"relay\.hang_timeout_s must be 0 \(no watchdog\) or "
                                          r"a finite number of seconds >= 1, got "):
        RelayConfig(hang_timeout_s=bad)
    assert RelayConfig().hang_timeout_s == 10.0
    assert RelayConfig(hang_timeout_s=0).hang_timeout_s == 0
    assert RelayConfig(hang_timeout_s=1.0).hang_timeout_s == 1.0
