"""Fuzz targets of the decoder and the TCP framing, and the helpers every target shares.

A target is a function ``bytes -> None``. It returns when the input was handled as the doc
says; it raises :class:`Finding` when an oracle disagrees, and any other exception that
escapes it is a crash of the code under test (the harness catches nothing but the errors the
doc promises). The session targets are in :mod:`lab.fuzz.sessions`; all of them are
listed in :mod:`lab.fuzz.registry`.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack

from lab.fuzz.docspec import Fatality, error_table
from shared.errors import MalformedMessageError, OversizeError, RemoteProtocolError
from shared.protocol import MESSAGE_TYPES, DataMessage, LengthPrefixDecoder, Message, decode, encode
from shared.protocol.messages import MAX_HOPS

__all__ = ["DECODER_LIMIT", "Finding", "check", "check_error", "decoder", "framing",
           "reference_deframe", "reference_envelope", "same_message"]

#: size limit of the decoder target (small, so that ``oversize`` is reachable)
DECODER_LIMIT = 8192


class Finding(AssertionError):
    """An input made the code under test break a promise of the doc or an invariant."""


def check(condition: object, what: str) -> None:
    """Raise :class:`Finding` with ``what`` unless ``condition`` holds."""
    if not condition:
        raise Finding(what)


def check_error(err: RemoteProtocolError, *, fatal: bool | None = None) -> None:
    """An error raised for received bytes is one of the doc's codes, with its close code."""
    rules = error_table()
    rule = rules.get(err.code)
    check(rule is not None, f"error code {err.code!r} is not in docs/protocol.md §6 ({err})")
    assert rule is not None
    if rule.close_code is not None:
        check(err.close_code == rule.close_code,
              f"{err.code}: close code {err.close_code}, the doc says {rule.close_code}")
    if fatal is not None and not fatal:
        check(rule.fatality is not Fatality.ALWAYS, f"{err.code} is always fatal per the doc")
    check(str(err), f"{err.code} without a message")


class _Pairs(list[tuple[Any, Any]]):
    """A msgpack map kept as its (key, value) pairs (so no key type is lost)."""


def _keys_are_str_once(obj: Any) -> bool:
    """Every map key in ``obj``, at any depth, is a str given once (iterative: msgpack nests
    1024 deep)."""
    stack = [obj]
    while stack:
        node = stack.pop()
        if isinstance(node, _Pairs):
            keys = [k for k, _ in node]
            if not all(isinstance(k, str) for k in keys) or len(set(keys)) != len(keys):
                return False
            stack.extend(v for _, v in node)
        elif isinstance(node, list):
            stack.extend(node)
    return True


def _all_finite(obj: Any) -> bool:
    """No float anywhere in ``obj`` is NaN or infinite (§2: "rejected everywhere")."""
    stack = [obj]
    while stack:
        node = stack.pop()
        if isinstance(node, float) and not math.isfinite(node):
            return False
        if isinstance(node, _Pairs):
            stack.extend(v for _, v in node)
        elif isinstance(node, list):
            stack.extend(node)
    return True


def reference_envelope(data: bytes, limit: int) -> str | None:
    """What ``docs/protocol.md`` §1-§2 say of a message's envelope, written from the doc
    (not from the codec): the error code, or None when the envelope is fine and the fields
    decide. Order: size, msgpack, one map with string keys everywhere, each once, ``v``,
    ``type``."""
    if len(data) > limit:
        return "oversize"
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=False, use_list=True,
                              object_pairs_hook=_Pairs)
    except Exception:  # any unpack failure: not msgpack, trailing bytes, bad UTF-8, depth
        return "malformed"
    if not isinstance(obj, _Pairs) or not _keys_are_str_once(obj):
        return "malformed"
    top = dict(obj)
    v = top.get("v")
    if type(v) is not int or v not in (1, 2):  # §2: versions 1 and 2
        return "version"
    t = top.get("type")
    if type(t) is not str or t not in MESSAGE_TYPES:
        return "unknown_type"
    if t == "tactile_compact" and v < 2:  # §4.1: a version-2 message
        return "version"
    return None


def same_message(a: Message, b: Message) -> bool:
    """Equal as the wire sees them (numpy layers compared by bytes)."""
    return type(a) is type(b) and encode(a, validate=False, max_message_bytes=2**31) == encode(
        b, validate=False, max_message_bytes=2**31)


def decoder(data: bytes) -> None:
    """Target: ``decode`` of one message.

    Promises checked: only the doc's errors, with the doc's close codes; the envelope verdict
    matches :func:`reference_envelope`; a message that decodes has no NaN or infinity
    anywhere (unknown keys too), can be encoded again (validated) and decodes to the same
    bytes; a data message forwarded with the relay's two hop stamps decodes with exactly
    those stamps appended (at most 32 kept).
    """
    expected = reference_envelope(data, DECODER_LIMIT)
    try:
        msg = decode(data, max_message_bytes=DECODER_LIMIT)
    except RemoteProtocolError as err:
        check_error(err)
        if expected is not None:
            check(err.code == expected, f"decoder says {err.code}, the doc says {expected}: {err}")
        else:
            check(err.code in ("bad_field", "non_finite"),
                  f"a well-formed envelope refused as {err.code}: {err}")
        return
    check(expected is None, f"decoded a message the doc refuses as {expected}: {msg!r}")
    check(_all_finite(msgpack.unpackb(data, raw=False, strict_map_key=False, use_list=True,
                                      object_pairs_hook=_Pairs)),
          f"decoded a message with a NaN or infinity in it: {msg!r}")
    wire = encode(msg)  # raises LocalProtocolError if a received message cannot be sent on
    check(encode(decode(wire)) == wire, f"re-encoding {msg.TYPE} is not stable")
    if isinstance(msg, DataMessage):
        stamps = (("relay", "relay_in", 5), ("relay", "relay_out", 9))
        fwd = decode(encode(msg, validate=False, max_message_bytes=2**31, extra_hops=stamps),
                     max_message_bytes=2**31)
        assert isinstance(fwd, DataMessage)
        want = [tuple(h) for h in msg.hops] + list(stamps)
        check([tuple(h) for h in fwd.hops] == want[-MAX_HOPS:],
              f"forwarded hops {fwd.hops} != {want[-MAX_HOPS:]}")


def reference_deframe(stream: bytes, limit: int) -> tuple[list[bytes], str | None, int]:
    """The doc's TCP framing over a whole stream: the payloads, the error code that ends it
    (``oversize``/``malformed``) or None, and the bytes left over (an incomplete frame)."""
    out: list[bytes] = []
    pos = 0
    while len(stream) - pos >= 4:
        length = int.from_bytes(stream[pos:pos + 4], "big")
        if length > limit:
            return out, "oversize", 0
        if length == 0:
            return out, "malformed", 0
        if len(stream) - pos - 4 < length:
            break
        out.append(stream[pos + 4:pos + 4 + length])
        pos += 4 + length
    return out, None, len(stream) - pos


def framing(data: bytes) -> None:
    """Target: the incremental TCP length-prefix decoder, fed in chunks of any size.

    Byte 0 picks the limit (16..1024), byte 1 the chunk sizes; the rest is the stream.
    Promises: the same payloads as :func:`reference_deframe` over the whole stream (those
    ahead of a broken header too), the same ending error, and never more than
    ``max(limit, 4)`` bytes buffered.
    """
    if len(data) < 2:
        return
    limit, pattern, stream = (data[0] % 64 + 1) * 16, data[1], data[2:]
    want, want_err, _ = reference_deframe(stream, limit)
    dec = LengthPrefixDecoder(limit)
    got: list[bytes] = []
    err_code = None
    pos, i = 0, 0
    while pos < len(stream):
        size = 1 + ((pattern >> (i % 5)) * 7 + i) % 61
        i += 1
        try:
            got += dec.feed(stream[pos:pos + size])
        except (OversizeError, MalformedMessageError) as err:
            check_error(err)
            err_code = err.code
            break
        pos += size
        check(dec.buffered < max(limit, 4) or err_code is not None,
              f"{dec.buffered} bytes buffered, limit {limit}")
    if err_code is None:
        try:  # a broken header behind the last payloads raises at the next call
            got += dec.feed(b"")
        except (OversizeError, MalformedMessageError) as err:
            check_error(err)
            err_code = err.code
    check(got == want, f"payloads {len(got)} != reference {len(want)} (the frames ahead of "
          "a broken header count)")
    check(err_code == want_err, f"framing ended with {err_code}, the reference with {want_err}")
