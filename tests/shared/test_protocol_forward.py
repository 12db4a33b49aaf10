"""Forwarding a data message as received, hops spliced in (shared.protocol.forward), checked
against the independent path: decode, append the stamps, encode again."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.errors import MalformedMessageError
from shared.protocol import ArmCommand, ArmState, PlatformState, TactileFrame, decode, encode
from shared.protocol.codec import decode_map
from shared.protocol.forward import WireMessage, locate_hops, with_hops
from shared.protocol.messages import MAX_HOPS, DataMessage, Hop
from shared.protocol.peer_session import PeerSession, PeerSettings

_hop = st.builds(Hop, st.sampled_from(["local", "remote", "relay"]),
                 st.from_regex(r"[a-z][a-z0-9_]{0,31}", fullmatch=True),
                 st.integers(0, 2**63 - 1))
_hops = st.lists(_hop, max_size=MAX_HOPS).map(tuple)
_extra = st.lists(st.tuples(st.just("relay"), st.sampled_from(["relay_in", "nats_out",
                                                               "relay_out"]),
                            st.integers(0, 2**63 - 1)), min_size=1, max_size=4)


@st.composite
def data_messages(draw: st.DrawFn) -> DataMessage:
    seq, ts, hops = draw(st.integers(0, 2**63 - 1)), draw(st.integers(0, 2**63 - 1)), draw(_hops)
    kind = draw(st.sampled_from(["platform", "arm_state", "arm_command", "tactile"]))
    if kind == "platform":
        return PlatformState(seq=seq, ts_us=ts, hops=hops, position_mm=(1.0, -2.0, 3.5))
    if kind == "arm_state":
        return ArmState(seq=seq, ts_us=ts, hops=hops, force_n=1.25, source_seq=seq)
    if kind == "arm_command":
        return ArmCommand(seq=seq, ts_us=ts, hops=hops, action="move", target_mm=(1.0, 2, 3))
    rows = draw(st.integers(1, 6))
    height = np.arange(rows * 3, dtype=np.float32).reshape(rows, 3) / 10
    return TactileFrame(seq=seq, ts_us=ts, hops=hops, layers={"height_mm": height},
                        contact=True)


def _decoded(data: bytes) -> DataMessage:
    msg = decode(data)
    assert isinstance(msg, DataMessage)
    return msg


def _located(data: bytes) -> WireMessage:
    wire = locate_hops(data, decode_map(data))
    assert wire is not None
    return wire


@settings(max_examples=200, deadline=None)
@given(data_messages(), _extra)
def test_spliced_bytes_decode_like_a_re_encoded_message(msg: DataMessage,
                                                        extra: list[tuple[str, str, int]]
                                                        ) -> None:
    data = encode(msg)
    wire = _located(data)
    assert wire.count == len(msg.hops)
    out = with_hops(wire, extra)
    if len(msg.hops) + len(extra) > MAX_HOPS:
        assert out is None  # the caller encodes, keeping the newest MAX_HOPS
        return
    assert out is not None
    reference = _decoded(encode(msg, validate=False, extra_hops=extra))
    got = _decoded(out)
    assert got.to_wire().keys() == reference.to_wire().keys()
    assert got.hops == reference.hops == (*msg.hops, *(Hop(*h) for h in extra))
    assert msgpack.unpackb(out) == {**msgpack.unpackb(data),
                                    "hops": [list(h) for h in got.hops]}
    # every byte but the hops array is the sender's
    assert out[:wire.hops_start] == data[:wire.hops_start]
    assert out.endswith(data[wire.hops_end:])


def test_a_sixteen_bit_hops_header_and_unknown_keys_pass_through() -> None:
    body = {"v": 1, "type": "platform_state", "seq": 4, "ts": 9,
            "position_mm": [0.0, 0.0, 0.0], "velocity_mm_s": [0.0, 0.0, 0.0],
            "x_future": {"a": b"\x00\x01"}}
    # hops as array16 (0xdc) with 2 stamps: legal msgpack, not the shortest form
    hops = b"\xdc\x00\x02" + msgpack.packb(["local", "send", 5]) + msgpack.packb(
        ["local", "tx", 6])
    head = msgpack.packb(body)
    data = bytes([head[0] + 1]) + head[1:] + msgpack.packb("hops") + hops  # fixmap +1 key
    wire = _located(data)
    assert (wire.items_start - wire.hops_start, wire.count) == (3, 2)
    out = with_hops(wire, [("relay", "relay_in", 7), ("relay", "relay_out", 8)])
    assert out is not None
    obj = msgpack.unpackb(out)
    assert obj["hops"] == [["local", "send", 5], ["local", "tx", 6], ["relay", "relay_in", 7],
                           ["relay", "relay_out", 8]]
    assert obj["x_future"] == {"a": b"\x00\x01"}  # unknown keys are the receiver's to ignore
    assert _decoded(out).hops[-1] == Hop("relay", "relay_out", 8)


def test_no_hops_key_or_a_duplicated_key_is_left_to_the_encoder() -> None:
    no_hops = msgpack.packb({"v": 1, "type": "platform_state", "seq": 1, "ts": 2,
                             "position_mm": [0, 0, 0], "velocity_mm_s": [0, 0, 0]})
    assert locate_hops(no_hops, decode_map(no_hops)) is None
    # "hops" twice: a reader keeps one of them, which one is not ours to guess
    pairs = [("v", 1), ("type", "platform_state"), ("seq", 1), ("ts", 2), ("hops", []),
             ("position_mm", [0, 0, 0]), ("velocity_mm_s", [0, 0, 0]),
             ("hops", [["local", "x", 1]])]
    dup = bytes([0x80 | len(pairs)]) + b"".join(msgpack.packb(k) + msgpack.packb(v)
                                                for k, v in pairs)
    with pytest.raises(MalformedMessageError, match="given twice"):
        decode_map(dup)  # refused on receipt; locate_hops still declines one on its own
    assert locate_hops(dup, dict(pairs)) is None


def test_the_relay_session_splices_and_falls_back_past_max_hops() -> None:
    """PeerSession.data_to_send: a forwarded message with its bytes is spliced; one whose
    stamps would exceed MAX_HOPS is encoded with the newest MAX_HOPS, as before."""
    ps = PeerSession("ws", PeerSettings(), 0)
    for n_hops in (1, MAX_HOPS - 1):
        msg = PlatformState(seq=n_hops, ts_us=1,
                            hops=tuple(Hop("local", f"s{i}", i) for i in range(n_hops)))
        data = encode(msg)
        ps.outbox.put_latest("p", msg, 100, wire=_located(data))
        (out,) = ps.data_to_send(lambda: 200)
        got = _decoded(out)
        assert got.hops[-2:] == (Hop("relay", "relay_in", 100), Hop("relay", "relay_out", 200))
        assert len(got.hops) == min(n_hops + 2, MAX_HOPS)
        if n_hops + 2 <= MAX_HOPS:
            assert out.endswith(data[_located(data).hops_end:])
        else:
            assert got.hops[0] == Hop("local", "s1", 1)  # the oldest dropped
