"""Forwarding a data message as its sender encoded it, with hop stamps spliced in.

A relay must stamp every data message it forwards (``relay_in``, ``relay_out``: see
``docs/protocol.md`` §2.1), and nothing else of it changes. Rather than encode the decoded
message again for every receiver (a 19 kB tactile frame is packed anew, its arrays copied),
the relay keeps the bytes it received and validated, notes where their ``hops`` array lies
(:func:`locate_hops`, once per received message) and builds each receiver's copy as those
bytes with a longer ``hops`` array (:func:`with_hops`): every other byte is the sender's.

The received message is still decoded and validated in full first (a bad one gets its
error and is never forwarded); :func:`locate_hops` declines (None) whenever the bytes are not
a plain case (no ``hops`` key; a top-level key given twice, which the decoder refuses
anyway), and the caller then encodes the decoded message as before. A message encoded anew
loses the sender's unknown keys (``docs/protocol.md`` §2).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import msgpack

from shared.protocol.messages import MAX_HOPS

__all__ = ["WireMessage", "locate_hops", "with_hops"]

_FIXARRAY, _ARRAY16, _ARRAY32 = 0x90, 0xDC, 0xDD


@dataclass(frozen=True, slots=True)
class WireMessage:
    """A received data message's bytes and where its ``hops`` array lies in them.

    Attributes:
        data: the message as received (msgpack, without the TCP length prefix).
        hops_start: offset of the ``hops`` array's header.
        items_start: offset of its first stamp (after the header).
        hops_end: offset just past its last stamp.
        count: stamps in it.
    """

    data: bytes
    hops_start: int
    items_start: int
    hops_end: int
    count: int


def locate_hops(data: bytes, obj: Mapping[str, Any]) -> WireMessage | None:
    """Find the ``hops`` array of a decoded, validated data message in its bytes.

    Args:
        data: the bytes ``obj`` was decoded from (one msgpack map).
        obj: the decoded top-level map (its ``hops`` already validated).

    Returns:
        The location, or None when the message must be encoded anew to add stamps: no
        ``hops`` key, or a top-level key present twice (the decoded map kept the last).
    """
    hops = obj.get("hops")
    if not isinstance(hops, list | tuple):
        return None
    unpacker = msgpack.Unpacker(raw=False)
    unpacker.feed(data)
    try:
        if unpacker.read_map_header() != len(obj):
            return None  # a duplicated key: which one a reader keeps is not ours to guess
        for _ in range(len(obj)):
            if unpacker.unpack() == "hops":
                start = unpacker.tell()
                unpacker.skip()
                end = unpacker.tell()
                break
            unpacker.skip()
        else:
            return None
    except (ValueError, msgpack.UnpackException):  # not reached for a decoded message
        return None
    first = data[start]
    if _FIXARRAY <= first <= _FIXARRAY | 0x0F:
        header = 1
    elif first == _ARRAY16:
        header = 3
    elif first == _ARRAY32:
        header = 5
    else:
        return None
    return WireMessage(data, start, start + header, end, len(hops))


def _array_header(n: int) -> bytes:
    return bytes((_FIXARRAY | n,)) if n <= 0x0F else bytes((_ARRAY16,)) + n.to_bytes(2, "big")


def with_hops(wire: WireMessage, extra_hops: Sequence[tuple[str, str, int]]) -> bytes | None:
    """The message's bytes with ``extra_hops`` appended to its ``hops`` array.

    Args:
        wire: from :func:`locate_hops`.
        extra_hops: stamps ``(clock, stage, t_us)`` to append (the caller's own, not
            validated).

    Returns:
        The new bytes, or None when the stamps would exceed ``MAX_HOPS`` (the caller then
        encodes the message, keeping the newest ``MAX_HOPS``).
    """
    n = wire.count + len(extra_hops)
    if n > MAX_HOPS:
        return None
    view = memoryview(wire.data)
    return b"".join((view[:wire.hops_start], _array_header(n),
                     view[wire.items_start:wire.hops_end],
                     *[msgpack.packb(hop) for hop in extra_hops],
                     view[wire.hops_end:]))
