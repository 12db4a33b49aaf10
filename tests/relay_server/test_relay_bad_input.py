"""Every bad-input class gets its error code and close code; the relay keeps serving others."""

from __future__ import annotations

import logging
import math
import struct

import msgpack
import numpy as np
import pytest

from relay_server.server import RelayServer
from shared.protocol import ArmCommand, Hello, PlatformState, TactileFrame, encode
from tests.relay_server.relay_clients import SECRET, Client, clients, running_relay
from tests.support import scaled


def raw(**fields: object) -> bytes:
    return msgpack.packb({"v": 1, **fields}, use_bin_type=True)


def good_platform(seq: int) -> PlatformState:
    return PlatformState(seq=seq, ts_us=1, position_mm=(0.0, 0.0, 0.0),
                         velocity_mm_s=(0.0, 0.0, 0.0))


async def assert_pair_still_works(relay: RelayServer, local: Client, remote: Client,
                                  seq: int) -> None:
    await local.send(ArmCommand(seq=seq, ts_us=local.now(), action="stop"))
    assert (await remote.expect("arm_command")).seq == seq


def framed(payload: bytes, kind: str) -> bytes:
    return payload if kind == "ws" else struct.pack(">I", len(payload)) + payload


FATAL_BEFORE_HELLO = [
    ("malformed", b"\xc1\xc1 not msgpack", 1007),
    ("version", raw(type="hello", role="local", session="x", token="t") .replace(
        b"\xa1v\x01", b"\xa1v\x07"), 1002),
    ("hello_expected", encode(good_platform(1)), 1002),
    ("unknown_type", raw(type="teleport"), 1003),
    ("bad_field", raw(type="hello", role="pilot", session="x", token="t"), 1007),
]


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_fatal_errors_before_hello(kind: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    async with running_relay() as relay, clients(("ws", 0), ("tcp", 0)) as (local, remote):
        await local.connect(relay)
        await remote.connect(relay)
        await local.hello("local", "good")
        await remote.hello("remote", "good")
        for i, (code, payload, close_code) in enumerate(FATAL_BEFORE_HELLO):
            caplog.clear()
            bad = Client(kind)
            await bad.connect(relay)
            try:
                await bad.send_raw(framed(payload, kind))
                err = await bad.expect("error")
                assert (err.code, err.fatal) == (code, True), err
                got_close = await bad.expect_closed()
                if kind == "ws":
                    assert got_close == close_code
            finally:
                await bad.close()
            warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
            assert len(warnings) == 1, [r.getMessage() for r in warnings]
            assert warnings[0].exc_info is None and code in warnings[0].getMessage()
            await assert_pair_still_works(relay, local, remote, i)


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_auth_role_taken_and_hello_timeout(kind: str) -> None:
    async with running_relay(hello_timeout_s=scaled(0.3)) as relay, clients(
            ("ws", 0), ("tcp", 0), (kind, 0), (kind, 0), (kind, 0), (kind, 0)) as (
            local, remote, wrong, missing, second, silent):
        for c in (local, remote, wrong, missing, second, silent):
            await c.connect(relay)
        await local.hello("local", "s")
        await remote.hello("remote", "s")
        cases = [(wrong, "auth", 4001, "0" * 64), (missing, "auth", 4001, ""),
                 (second, "role_taken", 4002, None)]
        for client, code, close_code, token in cases:
            from relay_server.auth import derive_token
            tok = derive_token(SECRET, "s") if token is None else token
            await client.send(Hello(role="local", session="s", token=tok))
            err = await client.expect("error")
            assert (err.code, err.fatal) == (code, True)
            got = await client.expect_closed()
            if kind == "ws":
                assert got == close_code
        err = await silent.expect("error", timeout_s=3.0)
        assert err.code == "hello_timeout" and err.fatal
        got = await silent.expect_closed()
        if kind == "ws":
            assert got == 4003
        await assert_pair_still_works(relay, local, remote, 1)


def nan_tactile() -> bytes:
    layer = np.zeros((4, 4), np.float32)
    layer[1, 2] = math.nan
    return encode(TactileFrame(seq=1, ts_us=1, layers={"height_mm": layer}), validate=False)


PER_MESSAGE = [
    ("malformed", b"\x92\x01"),  # a msgpack array, not a map
    ("unknown_type", raw(type="teleport")),
    ("bad_field", raw(type="arm_state", seq="one", ts=1, position_mm=[0, 0, 0], force_n=0.0,
                      status="ok")),
    ("non_finite", raw(type="arm_state", seq=1, ts=1, position_mm=[0, math.inf, 0],
                       force_n=0.0, status="ok")),
    ("non_finite", nan_tactile()),
    ("wrong_direction", encode(good_platform(3))),  # the remote may not send platform_state
    ("already_joined", encode(Hello(role="remote", session="s", token="x"))),
]


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_per_message_errors_keep_the_connection_until_the_budget(
        kind: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    async with running_relay(bad_message_budget=len(PER_MESSAGE) + 1) as relay, clients(
            ("ws", 0), (kind, 0)) as (local, remote):
        await local.connect(relay)
        await remote.connect(relay)
        await local.hello("local", "s")
        await remote.hello("remote", "s")
        for code, payload in PER_MESSAGE:
            await remote.send_raw(framed(payload, kind))
            err = await remote.expect("error")
            assert (err.code, err.fatal) == (code, False), err
        # still joined and forwarding in both directions
        await assert_pair_still_works(relay, local, remote, 1)
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and warnings[0].exc_info is None
        for _ in range(2):
            await remote.send_raw(framed(b"\xc1", kind))
        codes = []
        while True:
            msg = await remote.expect("error")
            codes.append(msg.code)
            if msg.fatal:
                break
        assert codes[-1] == "too_many_errors"
        got = await remote.expect_closed()
        if kind == "ws":
            assert got == 1008
        assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 2
        # local still fine: it reconnects a new remote
        fresh = Client("tcp")
        try:
            await fresh.connect(relay)
            await fresh.hello("remote", "s")
            await assert_pair_still_works(relay, local, fresh, 2)
        finally:
            await fresh.close()


async def test_oversize_is_fatal_ws_and_tcp() -> None:
    async with running_relay(max_message_bytes=2048) as relay, clients(
            ("ws", 0), ("tcp", 0)) as (ws, tcp):
        await ws.connect(relay)
        await tcp.connect(relay)
        await ws.hello("local", "big")
        await tcp.hello("remote", "big")
        big = raw(type="arm_state", pad=b"x" * 3000)
        await ws.send_raw(big)
        err = await ws.expect("error")
        assert (err.code, err.fatal) == ("oversize", True)
        assert await ws.expect_closed() == 1009
        await tcp.send_raw(struct.pack(">I", 10**6))  # header alone is enough
        err = await tcp.expect("error")
        assert (err.code, err.fatal) == ("oversize", True)
        await tcp.expect_closed()
        assert relay.sessions == {} or "big" not in relay.sessions


async def test_version_after_hello_is_fatal() -> None:
    async with running_relay() as relay, clients(("ws", 0)) as (c,):
        await c.connect(relay)
        await c.hello("local", "v")
        payload = bytearray(encode(good_platform(1)))
        payload = payload.replace(b"\xa1v\x01", b"\xa1v\x09")
        await c.send_raw(bytes(payload))
        err = await c.expect("error")
        assert (err.code, err.fatal) == ("version", True)
        assert await c.expect_closed() == 1002
