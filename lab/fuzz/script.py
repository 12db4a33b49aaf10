"""The byte format of a fuzz input that drives a session: a header, then operations.

A coverage-guided fuzzer mutates bytes, so a session scenario is written as bytes that any
mutation keeps readable (a truncated or garbled input is still a valid, shorter script)::

    header: 1 byte of options (target-specific: framing, queue sizes, ...)
    op:     1 byte = (peer << 4) | kind, then, for kinds with a payload, a 2-byte big-endian
            length and that many bytes (fewer if the input ends first)

Kinds: ``MSG`` one message (WebSocket: one binary message; TCP: framed by the harness),
``RAW`` bytes as they are (TCP: any chunk, may break the framing), ``TEXT`` a WebSocket text
message, ``TIME`` the clock moves forward by a 4-byte amount of microseconds, ``STEP`` the
clock jumps by a signed 4-byte amount (wall-clock steps, also backwards), ``TICK`` timers
run, ``FLUSH`` the output is written, ``CLOSE`` the connection drops.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from enum import IntEnum

__all__ = ["Kind", "Op", "Script", "dump", "parse"]


class Kind(IntEnum):
    """What one operation does (the low 3 bits of its first byte)."""

    MSG = 0
    RAW = 1
    TEXT = 2
    TIME = 3
    STEP = 4
    TICK = 5
    FLUSH = 6
    CLOSE = 7


_PAYLOAD_KINDS = frozenset({Kind.MSG, Kind.RAW, Kind.TEXT})
_U16 = struct.Struct(">H")
_U32 = struct.Struct(">I")
_I32 = struct.Struct(">i")


@dataclass(frozen=True, slots=True)
class Op:
    """One operation: ``peer`` (0-15) it applies to, ``kind``, and its ``payload`` (bytes
    for MSG/RAW/TEXT) or ``value`` (microseconds for TIME/STEP)."""

    kind: Kind
    peer: int = 0
    payload: bytes = b""
    value: int = 0


@dataclass(frozen=True, slots=True)
class Script:
    """A parsed input: the option byte and the operations."""

    options: int
    ops: tuple[Op, ...]


def parse(data: bytes, max_ops: int = 256) -> Script:
    """Read a script; any bytes are a valid script (missing bytes read as zero, a truncated
    payload is shorter). At most ``max_ops`` operations are read (bounded work per input)."""
    if not data:
        return Script(0, ())
    options, pos, n = data[0], 1, len(data)
    ops: list[Op] = []
    while pos < n and len(ops) < max_ops:
        head = data[pos]
        pos += 1
        kind, peer = Kind(head & 7), head >> 4
        if kind in _PAYLOAD_KINDS:
            raw_len = data[pos:pos + 2].ljust(2, b"\0")
            length = _U16.unpack(raw_len)[0]
            pos += 2
            ops.append(Op(kind, peer, data[pos:pos + length]))
            pos += length
        elif kind in (Kind.TIME, Kind.STEP):
            raw = data[pos:pos + 4].ljust(4, b"\0")
            pos += 4
            value = (_U32 if kind is Kind.TIME else _I32).unpack(raw)[0]
            ops.append(Op(kind, peer, value=value))
        else:
            ops.append(Op(kind, peer))
    return Script(options, tuple(ops))


def _dump_op(op: Op) -> Iterator[bytes]:
    yield bytes([((op.peer & 15) << 4) | int(op.kind)])
    if op.kind in _PAYLOAD_KINDS:
        payload = op.payload[:0xFFFF]
        yield _U16.pack(len(payload))
        yield payload
    elif op.kind is Kind.TIME:
        yield _U32.pack(op.value & 0xFFFFFFFF)
    elif op.kind is Kind.STEP:
        yield _I32.pack(max(-2**31, min(2**31 - 1, op.value)))


def dump(options: int, ops: Iterable[Op]) -> bytes:
    """Write a script (the inverse of :func:`parse` for well-formed operations)."""
    return bytes([options & 0xFF]) + b"".join(part for op in ops for part in _dump_op(op))
