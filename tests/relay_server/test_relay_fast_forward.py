"""The relay forwards a data message's own bytes with its stamps spliced in (real sockets):
the payload is byte-identical but for ``hops``, the stamps are the relay's, and a message
with a bad header still gets its documented error and is not forwarded."""

from __future__ import annotations

import asyncio

import msgpack
import numpy as np
import pytest

from shared.protocol import (
    LengthPrefixDecoder,
    PlatformState,
    TactileFrame,
    decode,
    encode,
    frame,
)
from shared.protocol.codec import decode_map
from shared.protocol.forward import locate_hops
from shared.protocol.messages import Hop
from shared.timebase import now_us
from tests.relay_server.relay_clients import Client, clients, running_relay
from tests.relay_server.test_relay_forwarding import join_pair
from tests.support import scaled

_DATA_TYPES = frozenset({"platform_state", "tactile_frame", "arm_state", "arm_command",
                         "error"})


async def _send_bytes(client: Client, payload: bytes) -> None:
    await client.send_raw(payload if client.ws is not None else frame(payload))


async def _next_raw(client: Client, decoder: LengthPrefixDecoder, pending: list[bytes],
                    timeout_s: float = 2.0) -> bytes:
    """The next data or error message's raw bytes (clock pings, stats skipped)."""
    async with asyncio.timeout(scaled(timeout_s)):
        while True:
            while pending:
                raw = pending.pop(0)
                if msgpack.unpackb(raw).get("type") in _DATA_TYPES:
                    return raw
            if client.ws is not None:
                pending.append(await client.ws.recv(decode=False))
            else:
                assert client.reader is not None
                pending.extend(decoder.feed(await client.reader.read(2**20)))


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_a_forwarded_frame_is_the_senders_bytes_with_the_relay_stamps(kind: str) -> None:
    async with running_relay() as relay, clients((kind, 0), (kind, 0)) as (local, remote):
        await join_pair(relay, f"fast-{kind}", local, remote)
        rng = np.random.default_rng(1)
        layers = {"height_mm": rng.uniform(-2, 2, (49, 49)).astype(np.float32),
                  "stiffness_k": rng.uniform(0.5, 1, (49, 49)).astype(np.float32)}
        msg = TactileFrame(seq=5, ts_us=remote.now(), layers=layers, contact=True,
                           hops=(Hop("remote", "sensor_frame", remote.now()),))
        # a key this relay does not know (a newer station's) is the receiver's to ignore: it
        # passes too (the relay used to re-encode the message and drop it)
        sent = msgpack.packb({**msgpack.unpackb(encode(msg)), "x_note": "newer"})
        before = now_us()
        await _send_bytes(remote, sent)
        got = await _next_raw(local, LengthPrefixDecoder(2**24), [])
        after = now_us()
        wire = locate_hops(sent, decode_map(sent))
        assert wire is not None
        assert got[:wire.hops_start] == sent[:wire.hops_start]
        assert got.endswith(sent[wire.hops_end:])  # the 19 kB of layers, untouched
        fwd = decode(got)
        assert isinstance(fwd, TactileFrame)
        assert fwd.hops[0] == msg.hops[0]
        (_, s_in, t_in), (_, s_out, t_out) = fwd.hops[1:]
        # and nothing else was added: the two stamps are the only new bytes
        assert len(got) == len(sent) + sum(len(msgpack.packb(list(h))) for h in fwd.hops[1:])
        assert (s_in, s_out) == ("relay_in", "relay_out")
        assert before <= t_in <= t_out <= after  # same host: the relay's clock is ours
        np.testing.assert_array_equal(fwd.layers["height_mm"], layers["height_mm"])


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_bad_headers_get_their_error_and_are_not_forwarded(kind: str) -> None:
    good = PlatformState(seq=3, ts_us=1, position_mm=(1.0, 2.0, 3.0))
    body = msgpack.unpackb(encode(good))
    bad = [({**body, "hops": [["moon", "x", 1]]}, "bad_field"),
           ({**body, "seq": -1}, "bad_field"),
           ({**body, "hops": "later"}, "bad_field"),
           ({**body, "position_mm": [float("nan"), 0.0, 0.0]}, "non_finite")]
    async with running_relay() as relay, clients((kind, 0), (kind, 0)) as (local, remote):
        await join_pair(relay, f"bad-{kind}", local, remote)
        dec, pending = LengthPrefixDecoder(2**24), list[bytes]()
        for obj, code in bad:
            await _send_bytes(local, msgpack.packb(obj))
            err = decode(await _next_raw(local, dec, pending))
            assert (err.TYPE, err.code, err.fatal) == ("error", code, False)  # type: ignore[attr-defined]
        await _send_bytes(local, encode(good))
        first = decode(await _next_raw(remote, LengthPrefixDecoder(2**24), []))
        assert isinstance(first, PlatformState) and first.seq == 3  # nothing bad got through
        assert [h.stage for h in first.hops] == ["relay_in", "relay_out"]
