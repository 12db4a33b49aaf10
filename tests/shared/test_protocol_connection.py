"""Sans-I/O connection tests: stream chunks in, events out, with no event loop."""

from __future__ import annotations

import itertools

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.errors import MalformedMessageError, OversizeError, UnknownMessageTypeError
from shared.protocol import (
    ConnectionFailed,
    LengthPrefixDecoder,
    MessageReceived,
    MessageRejected,
    PlatformState,
    ProtocolConnection,
    frame,
)


def states(n: int) -> list[PlatformState]:
    return [PlatformState(seq=i, ts_us=1000 + i, position_mm=(i, 0.0, 1.0)) for i in range(n)]


@settings(max_examples=100, deadline=None)
@given(cuts=st.lists(st.integers(0, 2000), max_size=30))
def test_tcp_stream_split_anywhere(cuts: list[int]) -> None:
    """However the byte stream is chunked, the same messages come out in order."""
    sender = ProtocolConnection("tcp")
    sent = states(10)
    for m in sent:
        sender.send(m)
    stream = b"".join(sender.data_to_send())
    receiver = ProtocolConnection("tcp")
    points = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    for a, b in itertools.pairwise(points):
        receiver.receive_data(stream[a:b])
    events = receiver.events_received()
    assert [e.message for e in events if isinstance(e, MessageReceived)] == sent
    assert receiver.events_received() == []


def test_bad_message_between_good_ones_is_rejected_and_stream_continues() -> None:
    good = ProtocolConnection("tcp")
    good.send(states(1)[0])
    bad = frame(msgpack.packb({"v": 1, "type": "teleport"}))
    stream = good.data_to_send()[0] + bad + good.encode(states(2)[1])
    conn = ProtocolConnection("tcp")
    conn.receive_data(stream)
    kinds = [type(e) for e in conn.events_received()]
    assert kinds == [MessageReceived, MessageRejected, MessageReceived]


def test_rejected_event_carries_the_typed_error() -> None:
    conn = ProtocolConnection("ws")
    conn.receive_data(msgpack.packb({"v": 1, "type": "teleport"}))
    (event,) = conn.events_received()
    assert isinstance(event, MessageRejected)
    assert isinstance(event.error, UnknownMessageTypeError)


def test_oversize_header_fails_the_connection() -> None:
    conn = ProtocolConnection("tcp", max_message_bytes=64)
    conn.receive_data(b"\x00\x00\x01\x00" + b"x" * 10)
    (event,) = conn.events_received()
    assert isinstance(event, ConnectionFailed)
    assert isinstance(event.error, OversizeError)
    assert conn.failed
    conn.receive_data(frame(b"anything"))  # ignored after failure
    assert conn.events_received() == []


def test_zero_length_frame_fails_the_connection() -> None:
    conn = ProtocolConnection("tcp")
    conn.receive_data(b"\x00\x00\x00\x00")
    (event,) = conn.events_received()
    assert isinstance(event, ConnectionFailed)
    assert isinstance(event.error, MalformedMessageError)


def test_ws_oversize_message_is_rejected_not_fatal() -> None:
    conn = ProtocolConnection("ws", max_message_bytes=20)
    conn.receive_data(b"x" * 21)
    conn.receive_data(ProtocolConnection("ws").encode(PlatformState()))
    events = conn.events_received()
    assert isinstance(events[0], MessageRejected)
    assert isinstance(events[0].error, OversizeError)
    # a platform_state is longer than 20 bytes too: also rejected, connection still alive
    assert not conn.failed


def test_ws_framing_is_bare_msgpack() -> None:
    conn = ProtocolConnection("ws")
    conn.send(PlatformState(seq=5))
    (data,) = conn.data_to_send()
    assert msgpack.unpackb(data)["seq"] == 5


def test_decoder_buffers_partial_header() -> None:
    dec = LengthPrefixDecoder(100)
    assert dec.feed(b"\x00\x00") == []
    assert dec.feed(b"\x00\x02a") == []
    assert dec.buffered == 1
    assert dec.feed(b"b") == [b"ab"]
    assert dec.buffered == 0


def test_unknown_framing_refused() -> None:
    with pytest.raises(ValueError):
        ProtocolConnection("udp")  # type: ignore[arg-type]
