"""Inputs the fuzzers found that broke a promise, each fixed in the product code.

Each test fails on the code before its fix (the commit that adds it names the finding).
"""

from __future__ import annotations

from collections import Counter

import msgpack
import pytest

from lab.fuzz.seeds import hello_for
from shared.errors import FieldError
from shared.protocol import Error, Welcome, decode, encode
from shared.protocol.peer_session import PeerSession, PeerSettings


def _platform_state(**over: object) -> bytes:
    body = {"v": 1, "type": "platform_state", "seq": 1, "ts": 2, "hops": [],
            "position_mm": [0, 0, 0], "velocity_mm_s": [0, 0, 0]}
    body.update(over)
    return msgpack.packb(body, use_bin_type=True)


@pytest.mark.parametrize("clock", [[1], {"a": 1}, ["local"]])
def test_a_hop_whose_clock_is_a_list_or_map_is_a_bad_field(clock: object) -> None:
    """Found by both fuzzers (decoder target): ``hops: [[[...], "capture", 1]]`` raised
    ``TypeError: unhashable type`` out of the decoder (the clock was looked up in a set)."""
    with pytest.raises(FieldError, match=r"hops\[0\]"):
        decode(_platform_state(hops=[[clock, "capture", 1]]))


def test_the_relay_answers_such_a_hop_with_a_per_message_error() -> None:
    """The same input after the hello: a non-fatal ``bad_field``, the connection kept (it
    was an exception out of ``PeerSession.receive_data``, ending the relay's handler)."""
    ps = PeerSession("ws", PeerSettings(), 0, Counter())
    ps.receive_data(encode(hello_for("local")), 0)
    ps.events_received()
    ps.accept(Welcome(session="s1", role="local", max_message_bytes=1 << 20), 0)
    ps.receive_data(_platform_state(hops=[[[1], "capture", 1]]), 1)
    assert not ps.closing
    written = [decode(b) for b in ps.data_to_send(lambda: 2)]
    errors = [e for e in written if isinstance(e, Error)]
    assert [(e.code, e.fatal) for e in errors] == [("bad_field", False)]


@pytest.mark.parametrize("expiry", ["²³", "٣٣٣٣٣٣٣٣٣٣", "1²", "4000000000\u0663"])
def test_a_v2_token_with_non_ascii_digits_is_auth(expiry: str) -> None:
    """Found by the relay target (its mutator's dictionary holds such tokens): a v2 token whose
    expiry is ``str.isdigit()`` but not ASCII (``"²³"``) raised ``ValueError`` out of the
    token check, past the relay's handler, instead of ``auth``/4001."""
    from relay_server.auth import TokenAuthority
    from shared.errors import AuthError

    auth = TokenAuthority({}, "secret")
    with pytest.raises(AuthError):
        auth.check("s1", f"v2.local.{expiry}.AAAA", "local")


def test_relay_full_and_shutdown_are_documented_with_their_close_code() -> None:
    """Found by the relay target (max_sessions = 1): the relay answered ``relay_full`` (and,
    by reading ``_join``, ``shutdown``), close 4000, codes docs/protocol.md §6 did not list."""
    from lab.fuzz.docspec import Fatality, error_table
    from lab.fuzz.registry import TARGETS
    from lab.fuzz.script import Kind, Op, dump

    for code in ("relay_full", "shutdown"):
        rule = error_table()[code]
        assert (rule.close_code, rule.fatality) == (4000, Fatality.ALWAYS)
    script = dump(32, [Op(Kind.MSG, 0, encode(hello_for("local", "s1"))),
                       Op(Kind.MSG, 1, encode(hello_for("local", "s2"))),
                       Op(Kind.FLUSH, 1)])
    TARGETS["relay"](script)  # checks the answer against the doc's table


def _nested(depth: int) -> bytes:
    return b"\x91" * depth + b"\x01"  # [[[...[1]...]]]


@pytest.mark.parametrize("where", ["type", "dtype", "shape"])
def test_a_deeply_nested_value_in_an_error_message_is_not_repr_d(where: str) -> None:
    """Found by a depth probe of the decoder target (msgpack nests up to 1024 levels): the
    error message quoted the received ``type`` (or ``dtype``/``shape``) with ``repr``, which
    raised ``RecursionError`` out of ``decode`` for 1,000 nested arrays."""
    from shared.errors import RemoteProtocolError

    if where == "type":
        data = b"\x82\xa1v\x01\xa4type" + _nested(1000)
    else:
        layer = {"dtype": "<f4", "shape": [1, 1], "data": b"\0" * 4}
        body = msgpack.packb({"v": 1, "type": "tactile_frame", "seq": 1, "ts": 1,
                              "center_mm": [0, 0], "pitch_mm": 1.0, "contact": False,
                              "force_n": 0, "indentation_mm": 0,
                              "layers": {"height_mm": {**layer, where: 0}}})
        marker = msgpack.packb(where) + b"\x00"
        data = body.replace(marker, msgpack.packb(where) + _nested(1000))
        assert data != body
    with pytest.raises(RemoteProtocolError) as info:
        decode(data)
    assert "a list" in str(info.value)


@pytest.mark.parametrize("bad_header", [b"\xff\xff\xff\xff", b"\x00\x00\x00\x00"])
def test_messages_before_a_broken_tcp_header_in_the_same_chunk_are_handled(
        bad_header: bytes) -> None:
    """Found by atheris (peer target): a TCP chunk holding complete frames and then a broken
    length prefix lost those frames (the decoder raised with them unreturned), so the relay
    neither answered nor forwarded them; the doc has each message handled, then the fatal
    framing error."""
    from shared.protocol import ArmCommand, ProtocolConnection, frame
    from shared.protocol.connection import ConnectionFailed, MessageReceived, MessageRejected

    conn = ProtocolConnection("tcp", 4096)
    good = encode(ArmCommand(seq=5, ts_us=1, action="stop"))
    conn.receive_data(frame(good) + frame(b"\xc1") + bad_header)
    events = conn.events_received()
    assert [type(e) for e in events] == [MessageReceived, MessageRejected, ConnectionFailed]
    assert events[0].message.seq == 5  # type: ignore[union-attr]

    ps = PeerSession("tcp", PeerSettings(), 0, Counter())
    ps.receive_data(frame(encode(hello_for("local"))), 0)
    ps.events_received()
    ps.accept(Welcome(session="s1", role="local", max_message_bytes=1 << 20), 0)
    ps.receive_data(frame(b"\xc1") + bad_header, 1)
    written = ProtocolConnection("tcp", 1 << 20)
    written.receive_data(b"".join(ps.data_to_send(lambda: 2)))
    errors = [(e.message.code, e.message.fatal) for e in written.events_received()  # type: ignore[union-attr]
              if isinstance(e.message, Error)]  # type: ignore[union-attr]
    assert errors == [("malformed", False), ("oversize" if bad_header[0] else "malformed", True)]
