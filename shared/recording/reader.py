"""Read a Tele-Touch MCAP recording, also one cut short, and refuse anything else clearly.

:func:`read_mcap` reads the file front to back (no index needed, so a file whose station
was killed reads up to its last complete chunk; ``complete`` says whether the footer was
reached). A chunk that fails its checksum or does not decompress (a flipped bit on disk) is
skipped and counted (``skipped_chunks``, ``skipped_reason``): the chunks after it are read
(their records are framed on their own). Wire channels decode into protocol messages with
the protocol's own validation.

Errors (:class:`RecordingFormatError`, an :class:`~shared.errors.InputDataError`) name what
is wrong: not an MCAP file, an MCAP file that is not a Tele-Touch recording, a file cut
before its start metadata, a wire message that does not decode.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import InvalidMagic
from mcap.records import Channel, Chunk, Footer, Header, McapRecord, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk

from shared.errors import InputDataError, RemoteProtocolError
from shared.protocol import Message
from shared.protocol.codec import decode
from shared.recording.schemas import (
    META_END,
    META_START,
    PROFILE,
    WIRE_ENCODING,
    parse_wire_topic,
)

__all__ = ["McapRecording", "RecordedMessage", "RecordingFormatError", "read_mcap"]

#: the largest record accepted (a corrupt length must not allocate gigabytes)
_RECORD_LIMIT = 256 << 20


class RecordingFormatError(InputDataError):
    """The file is not a readable Tele-Touch recording (the message says why)."""

    code = "bad_recording"


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    """One message of a recording, in file order.

    Attributes:
        topic: the channel's topic.
        t_us: log time (wall clock, microseconds).
        encoding: ``msgpack`` (wire) or ``json`` (derived).
        data: the payload bytes.
    """

    topic: str
    t_us: int
    encoding: str
    data: bytes

    @property
    def wire(self) -> tuple[str, str, str] | None:
        """(station, direction, type) for a wire message, else None."""
        return parse_wire_topic(self.topic) if self.encoding == WIRE_ENCODING else None

    def decode(self) -> Message:
        """The protocol message of a wire channel.

        Raises:
            RecordingFormatError: not a wire channel, or the payload does not decode.
        """
        if self.wire is None:
            raise RecordingFormatError(f"{self.topic} is not a wire channel")
        try:
            return decode(self.data, max_message_bytes=1 << 30)
        except RemoteProtocolError as err:
            raise RecordingFormatError(f"a message on {self.topic} does not decode: {err}"
                                       ) from err

    def json(self) -> dict[str, Any]:
        """The object of a JSON channel.

        Raises:
            RecordingFormatError: not JSON.
        """
        try:
            obj = json.loads(self.data)
        except (ValueError, UnicodeDecodeError) as err:
            raise RecordingFormatError(f"a message on {self.topic} is not JSON: {err}") from err
        except RecursionError as err:  # nested deeper than the parser goes (a crafted file)
            raise RecordingFormatError(f"a message on {self.topic} is nested too deep to "
                                       "read") from err
        if not isinstance(obj, dict):
            raise RecordingFormatError(f"a message on {self.topic} is not a JSON object")
        return obj


@dataclass
class McapRecording:
    """A recording read into memory.

    Attributes:
        path: the file.
        station: the station that wrote it (``local``, ``remote``).
        meta: the settings the station recorded when it started.
        end: the end metadata (counts, summary) of a clean stop; empty when cut short.
        complete: True when the file ends with its MCAP footer (closed cleanly).
        stop_reason: why reading stopped early (None when complete).
        messages: every message, in file order.
        schemas: schema name -> JSON Schema (derived channels).
        skipped_chunks: corrupt chunks skipped (their messages are missing).
        skipped_reason: why the first of them was skipped (None: none skipped).
        unreadable_messages: messages of the chunks after a skipped one whose channel was
            defined only in a skipped chunk (and not repeated in the file's summary).
    """

    path: Path
    station: str
    meta: dict[str, Any]
    end: dict[str, Any] = field(default_factory=dict)
    complete: bool = False
    stop_reason: str | None = None
    messages: list[RecordedMessage] = field(default_factory=list)
    schemas: dict[str, dict[str, Any]] = field(default_factory=dict)
    skipped_chunks: int = 0
    skipped_reason: str | None = None
    unreadable_messages: int = 0

    def topics(self) -> dict[str, int]:
        """Topic -> message count."""
        out: dict[str, int] = {}
        for m in self.messages:
            out[m.topic] = out.get(m.topic, 0) + 1
        return out

    def on(self, topic: str) -> Iterator[RecordedMessage]:
        """The messages of one topic, in order."""
        return (m for m in self.messages if m.topic == topic)

    def wire_messages(self, direction: str | None = None,
                      msg_type: str | None = None) -> Iterator[tuple[RecordedMessage, Message]]:
        """Decoded wire messages (optionally of one direction / type), in order.

        Raises:
            RecordingFormatError: a wire payload does not decode.
        """
        for m in self.messages:
            w = m.wire
            if w is None or (direction is not None and w[1] != direction) or \
                    (msg_type is not None and w[2] != msg_type):
                continue
            yield m, m.decode()


def _meta_json(record: Metadata, key: str, path: Path) -> dict[str, Any]:
    try:
        obj = json.loads(record.metadata.get(key, "{}"))
    except ValueError as err:
        raise RecordingFormatError(f"{path}: metadata {record.name}.{key} is not JSON") from err
    return obj if isinstance(obj, dict) else {"value": obj}


def read_mcap(path: str | os.PathLike[str]) -> McapRecording:
    """Read a Tele-Touch recording (see the module docstring).

    Raises:
        RecordingFormatError: not an MCAP file; an MCAP file of another program; a file cut
            before the station's start metadata (nothing to read).
    """
    p = Path(path)
    try:
        fh = open(p, "rb")  # noqa: SIM115 - closed below
    except OSError as err:
        raise RecordingFormatError(f"cannot open the recording {p}: {err}") from err
    header: Header | None = None
    rec: McapRecording | None = None
    channels: dict[int, Channel] = {}
    # (channel id, log time, data) of every message, in order: resolved at the end, when
    # the channels the file's summary repeats are known too (a skipped chunk may have held
    # a channel's only definition in the data section)
    raw: list[tuple[int, int, bytes]] = []
    stop_reason: str | None = None
    complete = False
    skipped = 0
    skipped_reason: str | None = None

    def take(record: McapRecord) -> None:
        nonlocal header, rec, complete
        if isinstance(record, Header):
            header = record
            if record.profile != PROFILE:
                raise RecordingFormatError(
                    f"{p} is an MCAP file but not a Tele-Touch recording (profile "
                    f"{record.profile!r}, written by {record.library!r}; expected "
                    f"profile {PROFILE!r})")
        elif isinstance(record, Metadata):
            if record.name == META_START and rec is None:
                rec = McapRecording(path=p, station=record.metadata.get("station", "?"),
                                    meta=_meta_json(record, "meta_json", p))
            elif record.name == META_END and rec is not None:
                rec.end = {"counts": _meta_json(record, "counts_json", p),
                           "meta": _meta_json(record, "meta_json", p)}
        elif isinstance(record, Schema):
            if rec is not None and record.encoding == "jsonschema":
                try:
                    rec.schemas[record.name] = json.loads(record.data)
                except ValueError as err:
                    raise RecordingFormatError(f"{p}: schema {record.name} is not JSON"
                                               ) from err
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, McapMessage):
            if rec is None:
                raise RecordingFormatError(f"{p}: a message before the recording's "
                                           f"{META_START!r} metadata")
            raw.append((record.channel_id, record.log_time // 1000, bytes(record.data)))
        elif isinstance(record, Footer):
            complete = True

    try:
        reader = StreamReader(fh, validate_crcs=True, record_size_limit=_RECORD_LIMIT,
                              emit_chunks=True)
        for record in reader.records:
            if not isinstance(record, Chunk):
                take(record)
                continue
            try:  # a whole chunk was read: its framing is its own, the next one's is intact
                if record.uncompressed_size > _RECORD_LIMIT:
                    raise ValueError(f"uncompressed size {record.uncompressed_size} bytes")
                inner = breakup_chunk(record, validate_crc=True)
            except Exception as err:  # a CRC mismatch, the decompressor's error, a torn record
                skipped += 1
                skipped_reason = skipped_reason or (
                    f"chunk at {record.message_start_time // 1000} us: "
                    f"{type(err).__name__}: {err}")
                continue
            for r in inner:
                take(r)
    except InvalidMagic as err:
        if header is None:
            raise RecordingFormatError(f"{p} is not an MCAP file (it does not start with the "
                                       "MCAP magic bytes)") from err
        stop_reason = f"bad magic at the end: {err}"
    except RecordingFormatError:
        raise
    except Exception as err:
        # the end of a cut file: EndOfFile, a short struct, a CRC mismatch, or the
        # decompressor's error (zstandard.ZstdError) on a chunk cut in the middle
        stop_reason = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
    finally:
        fh.close()
    if header is None:
        raise RecordingFormatError(f"{p} is not an MCAP file or is truncated before its "
                                   f"header ({stop_reason})")
    if rec is None:
        raise RecordingFormatError(
            f"{p} is an MCAP file (profile {header.profile!r}) without the Tele-Touch start "
            f"metadata {META_START!r}: not a Tele-Touch recording, or cut before it started"
            + (f" ({stop_reason})" if stop_reason else ""))
    for cid, t_us, data in raw:
        ch = channels.get(cid)
        if ch is None:
            if not skipped:
                raise RecordingFormatError(f"{p}: a message on unknown channel {cid}")
            rec.unreadable_messages += 1  # defined in a skipped chunk only
            continue
        rec.messages.append(RecordedMessage(ch.topic, t_us, ch.message_encoding, data))
    rec.skipped_chunks, rec.skipped_reason = skipped, skipped_reason
    rec.complete = complete and stop_reason is None
    rec.stop_reason = None if rec.complete else (stop_reason or "no footer")
    return rec
