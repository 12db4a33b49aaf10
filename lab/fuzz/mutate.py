"""Mutations of fuzz inputs: byte-level (as libFuzzer's) and msgpack-structure-aware.

The structure mutator unpacks a message, changes one node (a value of another type or an
extreme one, a key removed, added or made non-string, a string of strange characters) and
packs it again, so a mutant gets past msgpack and reaches the field checks and the sessions.
Script inputs (:mod:`lab.fuzz.script`) are mutated per operation. Pure functions of a
``random.Random``: a run is reproducible from its seed.
"""

from __future__ import annotations

import math
import random
from typing import Any

import msgpack

from lab.fuzz.script import Kind, Op, dump, parse
from shared.protocol import MESSAGE_TYPES

__all__ = ["mutate_bytes", "mutate_input", "mutate_message", "mutate_script"]

_INTERESTING_INTS = (0, 1, -1, 2, 31, 32, 33, 127, 128, 255, 256, 1023, 1024, 1025, 4096,
                     4097, 8192, 65535, 65536, 2**20, 2**20 + 1, 2**31 - 1, 2**31, 2**32 - 1,
                     2**32, 2**53 + 1, 2**63 - 1, 2**63, 2**64 - 1, -2**31, -2**63)
_INTERESTING_FLOATS = (0.0, -0.0, 0.5, 1.0, 1e-4, 99.99, 100.0, 1000.0, 1000.0001, 1e4,
                       1e5, 1e308, -1e308, 5e-324, math.nan, math.inf, -math.inf)
_WORDS = (*MESSAGE_TYPES, "local", "remote", "observer", "relay", "move", "stop", "home",
          "set_force_limit", "ok", "halted", "height_mm", "stiffness_k", "friction",
          "stiffness_n_per_mm", "<f4", "<f8", "|u1", ">f4", "<i8", "capture", "relay_in",
          "v2", "v2.local.²³.x", "v2.remote.4000000000.", "s1", "s2", "", "\u0000", "é",
          "\U0001f600", "²", "٣", "a" * 65, "b" * 300, "c" * 1100)
_KEYS = ("v", "type", "seq", "ts", "hops", "role", "session", "token", "name", "ping_id",
         "t0_us", "t1_us", "t2_us", "scope", "time_us", "metrics", "code", "message", "fatal",
         "stream", "reason", "position_mm", "velocity_mm_s", "action", "target_mm",
         "force_limit_n", "force_n", "status", "source_seq", "source_ts", "center_mm",
         "pitch_mm", "layers", "contact", "indentation_mm", "dtype", "shape", "data")
_BYTES = (0x00, 0x01, 0x7F, 0x80, 0xC0, 0xC1, 0xC4, 0xC7, 0xCB, 0xCF, 0xD3, 0xD9, 0xDB,
          0xDC, 0xDD, 0xDE, 0xDF, 0xFF, 0x90, 0x93, 0x81, 0xA0, 0xA1)


def _value(rng: random.Random, depth: int = 0) -> Any:
    pick = rng.randrange(12)
    if pick < 3:
        return rng.choice(_INTERESTING_INTS)
    if pick < 5:
        return rng.choice(_INTERESTING_FLOATS)
    if pick < 7:
        return rng.choice(_WORDS)
    if pick == 7:
        return rng.choice((None, True, False))
    if pick == 8:
        return bytes(rng.randrange(256) for _ in range(rng.choice((0, 1, 4, 8, 16, 24))))
    if pick == 9 and depth < 3:
        return [_value(rng, depth + 1) for _ in range(rng.choice((0, 1, 2, 3, 33)))]
    if pick == 10 and depth < 3:
        return {rng.choice(_KEYS): _value(rng, depth + 1) for _ in range(rng.randrange(4))}
    if rng.random() < 0.3:
        return msgpack.Timestamp(rng.randrange(2**34), rng.randrange(10**9))
    return msgpack.ExtType(rng.randrange(5), b"\0" * rng.choice((0, 4, 8, 12)))


def _nodes(obj: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [path]
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _nodes(v, (*path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += _nodes(v, (*path, i))
    return out


def _mutate_obj(rng: random.Random, obj: Any) -> Any:
    paths = _nodes(obj)
    path = rng.choice(paths)
    parent, last = None, None
    node = obj
    for step in path:
        parent, last, node = node, step, node[step]
    op = rng.randrange(7)
    if op == 0 or (parent is None and not isinstance(node, dict | list)):
        new = _value(rng)
    elif op == 1 and isinstance(node, dict) and node:
        node.pop(rng.choice(list(node)))
        return obj
    elif op == 2 and isinstance(node, dict):
        key: Any = rng.choice((rng.choice(_KEYS), 7, 1.5, b"bin", None, True))
        node[key] = _value(rng)
        return obj
    elif op == 3 and isinstance(node, list):
        if node and rng.random() < 0.5:
            node.pop(rng.randrange(len(node)))
        else:
            node.insert(rng.randrange(len(node) + 1), _value(rng))
        return obj
    elif op == 4 and isinstance(node, str):
        new = rng.choice((node[: rng.randrange(len(node) + 1)], node + rng.choice(_WORDS),
                          rng.choice(_WORDS), node.encode()))
    elif op == 5 and isinstance(node, int | float) and not isinstance(node, bool):
        new = rng.choice((node + 1, node - 1, -node, node * 2**20, float(node), node + 0.5))
    elif op == 6 and isinstance(node, bytes):
        new = node[: rng.randrange(len(node) + 1)] + bytes(rng.randrange(256)
                                                         for _ in range(rng.randrange(3)))
    else:
        new = _value(rng)
    if parent is None:
        return new
    parent[last] = new
    return obj


def mutate_message(rng: random.Random, data: bytes) -> bytes:
    """Mutate one msgpack value structurally (byte-level if it does not unpack)."""
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception:
        return mutate_bytes(rng, data)
    try:
        for _ in range(1 + rng.randrange(2)):
            obj = _mutate_obj(rng, obj)
        return msgpack.packb(obj, use_bin_type=True)
    except Exception:  # an int that no longer fits, nesting too deep: mutate the bytes
        return mutate_bytes(rng, data)


def mutate_bytes(rng: random.Random, data: bytes, max_size: int = 65536) -> bytes:
    """One libFuzzer-like byte mutation."""
    b = bytearray(data)
    op = rng.randrange(9)
    if op == 8:  # deep nesting: msgpack allows 1024 levels, Python's repr() fewer
        pos = rng.randrange(len(b) + 1)
        b[pos:pos] = rng.choice((b"\x91", b"\x81\xa1a")) * rng.choice((100, 600, 1000, 1100))
    elif not b or op == 0:
        pos = rng.randrange(len(b) + 1)
        b[pos:pos] = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 9)))
    elif op == 1:
        pos = rng.randrange(len(b))
        b[pos] ^= 1 << rng.randrange(8)
    elif op == 2:
        b[rng.randrange(len(b))] = rng.choice(_BYTES)
    elif op == 3:
        start = rng.randrange(len(b))
        del b[start:start + rng.randrange(1, 17)]
    elif op == 4:
        start = rng.randrange(len(b))
        chunk = b[start:start + rng.randrange(1, 33)]
        pos = rng.randrange(len(b) + 1)
        b[pos:pos] = chunk
    elif op == 5 and len(b) >= 4:
        pos = rng.randrange(len(b) - 3)
        value = rng.choice(_INTERESTING_INTS) & 0xFFFFFFFF
        b[pos:pos + 4] = value.to_bytes(4, "big")
    elif op == 6:
        del b[rng.randrange(len(b) + 1):]
    else:
        pos = rng.randrange(len(b))
        b[pos] = (b[pos] + rng.choice((1, -1, 16, -16))) & 0xFF
    return bytes(b[:max_size])


def mutate_script(rng: random.Random, data: bytes, corpus: list[bytes] | None = None) -> bytes:
    """Mutate a session script: one operation's payload, or the operation list itself."""
    script = parse(data)
    ops = list(script.ops)
    options = script.options
    pick = rng.randrange(10)
    payload_ops = [i for i, o in enumerate(ops) if o.kind in (Kind.MSG, Kind.RAW, Kind.TEXT)]
    if pick < 5 and payload_ops:
        i = rng.choice(payload_ops)
        o = ops[i]
        new = (mutate_message(rng, o.payload) if rng.random() < 0.7
               else mutate_bytes(rng, o.payload))
        ops[i] = Op(o.kind, o.peer, new)
    elif pick == 5:
        options ^= 1 << rng.randrange(8)
    elif pick == 6 and ops:
        i = rng.randrange(len(ops))
        o = ops[i]
        if rng.random() < 0.5:
            ops[i] = Op(Kind(rng.randrange(8)), o.peer, o.payload, o.value)
        else:
            ops[i] = Op(o.kind, rng.randrange(4), o.payload, o.value)
    elif pick == 7:
        kind = rng.choice((Kind.TIME, Kind.STEP, Kind.TICK, Kind.FLUSH, Kind.CLOSE))
        value = rng.choice((1, 20_000, 1_000_000, 4_999_999, 5_000_000, 60_000_000,
                            -1_000_000, -2**31))
        ops.insert(rng.randrange(len(ops) + 1), Op(kind, rng.randrange(4), value=value))
    elif pick == 8 and ops:
        i = rng.randrange(len(ops))
        if rng.random() < 0.5:
            del ops[i]
        else:
            ops.insert(rng.randrange(len(ops) + 1), ops[i])
    elif corpus:  # splice: operations of another input
        other = parse(rng.choice(corpus)).ops
        if other:
            start = rng.randrange(len(other))
            ops[rng.randrange(len(ops) + 1):0] = other[start:start + rng.randrange(1, 6)]
    return dump(options, ops[:256])


def mutate_input(rng: random.Random, target: str, data: bytes,
                 corpus: list[bytes] | None = None) -> bytes:
    """Mutate an input of ``target`` with the mutator that fits it."""
    if target == "decoder":
        return mutate_message(rng, data) if rng.random() < 0.6 else mutate_bytes(rng, data)
    if target == "framing":
        return mutate_bytes(rng, data)
    return mutate_script(rng, data, corpus)
