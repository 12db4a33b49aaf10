"""msgpack codec for Tele-Touch messages: bytes <-> validated message objects.

One message is one msgpack map with ``v`` (protocol version) and ``type``. Decoding
checks, in order: size, msgpack well-formedness, map shape, version, type, then the
fields of that type. Each failure raises its own
:class:`~shared.errors.RemoteProtocolError` subclass. Encoding validates by default and
raises :class:`~shared.errors.LocalProtocolError`: we never put an invalid message on
the wire.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NoReturn

import msgpack

from shared.errors import (
    FieldError,
    LocalProtocolError,
    MalformedMessageError,
    NonFiniteError,
    OversizeError,
    UnknownMessageTypeError,
    VersionError,
)
from shared.protocol.fields import describe
from shared.protocol.messages import MAX_HOPS, MESSAGE_TYPES, Message

__all__ = [
    "DEFAULT_MAX_MESSAGE_BYTES",
    "PROTOCOL_VERSION",
    "SUPPORTED_VERSIONS",
    "decode",
    "decode_map",
    "encode",
    "message_from_map",
]

#: the newest version; a message carries the first version defining its type
#: (``MIN_VERSION``: 1 for every type but ``tactile_compact``, 2), so a version-1 peer
#: still reads everything else
PROTOCOL_VERSION = 2
SUPPORTED_VERSIONS = frozenset({1, 2})
#: default size limit of one encoded message (a 320 x 240 float32 layer is 300 KiB)
DEFAULT_MAX_MESSAGE_BYTES = 4 * 1024 * 1024


class _NonFinite(ValueError):
    """Raised by the unpack hooks at a NaN or infinity; caught in :func:`decode_map`."""


_isfinite = math.isfinite


def _map_of(pairs: list[tuple[Any, Any]]) -> dict[Any, Any]:
    # every map, nested ones too: str keys only (msgpack's strict_map_key still lets bin
    # keys through) and no key twice (which copy a reader keeps is not defined: the relay
    # forwards the bytes it validated, so another reader could take a copy it never checked)
    for key, _ in pairs:
        if key.__class__ is not str:
            raise ValueError(f"map keys must be strings, got a {type(key).__name__} key")
    return _once(pairs)


def _once(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj = dict(pairs)
    if len(obj) != len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise ValueError(f"map key {key[:40]!r} given twice")
            seen.add(key)
    return obj


def _checked_map(pairs: list[tuple[Any, Any]]) -> dict[Any, Any]:
    """:func:`_map_of`, and finite numbers only (one pass: this runs for every map)."""
    for key, value in pairs:
        if key.__class__ is not str:
            raise ValueError(f"map keys must be strings, got a {type(key).__name__} key")
        if value.__class__ is float and not _isfinite(value):
            raise _NonFinite(f"key {key[:40]!r} is {value}")
    return _once(pairs)


def _checked_list(items: list[Any]) -> list[Any]:
    for value in items:
        if value.__class__ is float and not _isfinite(value):
            raise _NonFinite(f"an array element is {value}")
    return items


def decode_map(data: bytes | bytearray | memoryview, *,
               max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> dict[str, Any]:
    """Unpack bytes into the raw message map, checking size, form, numbers and version.

    Raises:
        OversizeError: more than ``max_message_bytes`` bytes.
        MalformedMessageError: not exactly one msgpack map with string keys, each given
            once (every map, nested ones too: an int, float or bin key anywhere, or a key
            twice, is malformed).
        VersionError: ``v`` is missing or unsupported.
        UnknownMessageTypeError, FieldError: a number anywhere is NaN or infinite, and the
            envelope (``v``, ``type``) or a field is wrong too (the errors in the order of
            :func:`message_from_map`).
        NonFiniteError: a number anywhere is NaN or infinite, unknown keys too.
    """
    if len(data) > max_message_bytes:
        raise OversizeError(f"message of {len(data)} bytes exceeds the limit of "
                            f"{max_message_bytes}")
    try:
        obj = _unpack(data, finite=True)
    except _NonFinite as err:
        _refuse_non_finite(data, err)
    return _check_envelope(obj)


def _unpack(data: bytes | bytearray | memoryview, *, finite: bool) -> Any:
    try:
        if finite:
            return msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True,
                                   object_pairs_hook=_checked_map, list_hook=_checked_list)
        return msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True,
                               object_pairs_hook=_map_of)
    except _NonFinite:
        raise
    except msgpack.ExtraData as err:
        raise MalformedMessageError("trailing bytes after the msgpack map") from err
    except (ValueError, TypeError, msgpack.UnpackException) as err:
        if "map key" in str(err) or "keys must be strings" in str(err):
            raise MalformedMessageError(f"map keys must be strings, each once: {err}") from err
        raise MalformedMessageError(f"not valid msgpack: {err}") from err


def _check_envelope(obj: Any) -> dict[str, Any]:
    if not isinstance(obj, dict):
        raise MalformedMessageError(f"a message must be a msgpack map, got {type(obj).__name__}")
    version = obj.get("v")
    if isinstance(version, bool) or not isinstance(version, int):
        raise VersionError("field v (protocol version) is missing or not an integer")
    if version not in SUPPORTED_VERSIONS:
        raise VersionError(f"protocol version {version} is not supported "
                           f"(supported: {sorted(SUPPORTED_VERSIONS)})")
    return obj


def _refuse_non_finite(data: bytes | bytearray | memoryview, err: _NonFinite) -> NoReturn:
    """A well-formed message with a NaN or infinity somewhere (the unpack stopped at it):
    raise the error the checks would in order (envelope, type, the field's own), else a
    NonFiniteError naming where it is (an unknown key: §2 refuses them everywhere)."""
    obj = _check_envelope(_unpack(data, finite=False))  # the rest of it: a bad key after
    message_from_map(obj)  # raises a field's own error (NonFiniteError naming the field)
    raise NonFiniteError(f"a number must be finite: {err}") from None


def message_from_map(obj: dict[str, Any]) -> Message:
    """Validate a raw message map (from :func:`decode_map`) into a message object.

    Raises:
        UnknownMessageTypeError: ``type`` is missing or unknown.
        FieldError: a field is missing, of the wrong type or out of range.
    """
    msg_type = obj.get("type")
    cls = MESSAGE_TYPES.get(msg_type) if isinstance(msg_type, str) else None
    if cls is None:
        raise UnknownMessageTypeError(f"unknown message type {describe(msg_type)}; known: "
                                      f"{sorted(MESSAGE_TYPES)}")
    if obj.get("v", 1) < cls.MIN_VERSION:
        raise VersionError(f"{msg_type} needs protocol version {cls.MIN_VERSION}, the message "
                           f"says {obj.get('v')}")
    return cls.from_wire(obj)


def decode(data: bytes | bytearray | memoryview, *,
           max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> Message:
    """Decode and validate one message.

    Raises:
        RemoteProtocolError: a subclass naming what is wrong (see module docstring).
    """
    return message_from_map(decode_map(data, max_message_bytes=max_message_bytes))


def encode(message: Message, *, validate: bool = True,
           max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
           extra_hops: Sequence[tuple[str, str, int]] = ()) -> bytes:
    """Encode a message to msgpack bytes.

    Args:
        message: the message.
        validate: re-check every field as a receiver would (default). Forwarders that
            only re-encode a message they already decoded may pass False.
        max_message_bytes: refuse to produce a longer message.
        extra_hops: hop stamps ``(clock, stage, t_us)`` (a :class:`Hop` or a plain tuple)
            appended to a data message's ``hops`` while encoding (the relay's
            ``relay_in``/``relay_out``), keeping the last ``MAX_HOPS``; this saves forwarders
            a copy of the message per hop. Not validated: the caller's own stamps.

    Raises:
        LocalProtocolError: the message would be rejected by a receiver.
    """
    body = message.to_wire()
    if extra_hops:
        hops = body["hops"]
        hops.extend(extra_hops)  # tuples pack as msgpack arrays, like the lists of to_wire
        if len(hops) > MAX_HOPS:
            body["hops"] = hops[-MAX_HOPS:]
    wire = {"v": message.MIN_VERSION, "type": message.TYPE, **body}
    if validate:
        try:
            type(message).from_wire(wire)
        except FieldError as err:
            raise LocalProtocolError(f"refusing to send an invalid {message.TYPE}: {err}",
                                     code=err.code) from err
    data = msgpack.packb(wire, use_bin_type=True)
    if len(data) > max_message_bytes:
        raise LocalProtocolError(f"{message.TYPE} of {len(data)} bytes exceeds the limit of "
                                 f"{max_message_bytes}", code="oversize")
    return data
