"""The relay says what docs/protocol.md says (issue 11, item 5: an independent client found
six disagreements; each has a test here that fails on the old relay)."""

from __future__ import annotations

import asyncio
import struct

import msgpack
import pytest

from shared.protocol import ArmCommand, Error, decode, encode
from tests.relay_server.relay_clients import clients, running_relay
from tests.support import scaled


def framed(payload: bytes, kind: str) -> bytes:
    return payload if kind == "ws" else struct.pack(">I", len(payload)) + payload


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_a_hello_without_a_token_field_is_auth_4001(kind: str) -> None:
    """Doc §6: a missing token is ``auth``/4001 (was ``bad_field``/1007)."""
    async with running_relay() as relay, clients((kind, 0)) as (c,):
        await c.connect(relay)
        body = msgpack.packb({"v": 1, "type": "hello", "role": "local", "session": "s"})
        await c.send_raw(framed(body, kind))
        err = await c.expect("error")
        assert (err.code, err.fatal) == ("auth", True)
        got = await c.expect_closed()
        if kind == "ws":
            assert got == 4001


@pytest.mark.parametrize("key", [b"bin", 7, 1.5])
@pytest.mark.parametrize("where", ["top", "nested"])
def test_non_string_map_keys_are_malformed_anywhere(key: object, where: str) -> None:
    """Doc §2: a message is a map with string keys; any other key is ``malformed``."""
    from shared.errors import MalformedMessageError

    body: dict[object, object] = {"v": 1, "type": "stats", "scope": "local", "time_us": 1,
                                  "metrics": {"a": 1}}
    if where == "top":
        body[key] = 1
    else:
        body["metrics"] = {key: 1}
    with pytest.raises(MalformedMessageError, match="string"):
        decode(msgpack.packb(body, use_bin_type=True))


async def test_non_string_key_after_hello_is_a_per_message_malformed() -> None:
    async with running_relay() as relay, clients(("tcp", 0)) as (c,):
        await c.connect(relay)
        await c.hello("local", "k")
        await c.send_raw(framed(msgpack.packb({"v": 1, "type": "bye", b"x": 1},
                                              use_bin_type=True), "tcp"))
        err = await c.expect("error")
        assert (err.code, err.fatal) == ("malformed", False)


async def test_unexpected_type_is_documented_and_not_fatal() -> None:
    """A client sending a relay-only type (``welcome``) gets the documented code."""
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "protocol.md").read_text()
    assert "`unexpected_type`" in doc
    async with running_relay() as relay, clients(("ws", 0)) as (c,):
        await c.connect(relay)
        await c.hello("local", "u")
        await c.send_raw(msgpack.packb({"v": 1, "type": "welcome", "session": "u",
                                        "role": "local", "server_time_us": 1,
                                        "ping_interval_s": 1, "max_message_bytes": 10}))
        err = await c.expect("error")
        assert (err.code, err.fatal) == ("unexpected_type", False)


async def test_oversize_error_reaches_the_tcp_client_before_the_close() -> None:
    """The relay flushes the fatal ``oversize`` error and lingers for the rest of the
    client's bytes, so the close is not a reset that destroys the error (was lost in 10
    of 20 tries)."""
    payload = b"\x00" * 256 * 1024
    async with running_relay(max_message_bytes=2048) as relay:
        for attempt in range(20):
            reader, writer = await asyncio.open_connection("127.0.0.1", relay.tcp_port)
            try:
                writer.write(struct.pack(">I", len(payload)) + payload)
                await writer.drain()
                data = b""
                async with asyncio.timeout(scaled(5.0)):
                    while chunk := await reader.read(65536):
                        data += chunk
                (length,) = struct.unpack(">I", data[:4])
                err = decode(data[4:4 + length])
                assert isinstance(err, Error), (attempt, err)
                assert (err.code, err.fatal) == ("oversize", True), attempt
            finally:
                writer.close()
                await writer.wait_closed()


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_queue_full_and_no_peer_name_the_seq_in_fields(kind: str) -> None:
    """Doc §4 ``error``: ``stream`` and ``seq`` name the refused message."""
    async with running_relay(ordered_queue_len=1) as relay, clients((kind, 0)) as (local,):
        await local.connect(relay)
        await local.hello("local", "q")
        await local.send(ArmCommand(seq=41, ts_us=local.now(), action="stop"))
        err = await local.expect("error")
        assert (err.code, err.stream, err.seq, err.fatal) == ("no_peer", "arm_command", 41,
                                                              False)
        body = msgpack.unpackb(encode(err))
        assert body["seq"] == 41 and body["stream"] == "arm_command"
