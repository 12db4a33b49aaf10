"""Serial framing of the ArrayTac payloads: COBS, zero-delimited (docs/arraytac_can.md, §Serial).

One link frame is ``COBS(arb_id u16 LE | payload) 00``. The payload is the very same byte
string as the CAN FD frame's data field (so it carries its own CRC); the 16-bit arbitration
ID tells the receiver which frame it is. COBS removes every 0x00 from the body, so a
receiver that joins mid-stream or sees line noise resynchronises at the next 0x00.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from shared.errors import MalformedMessageError

__all__ = ["LinkDecoderStats", "LinkFrameDecoder", "cobs_decode", "cobs_encode",
           "encode_link_frame"]

_ARB = struct.Struct("<H")
#: longest body accepted (ID + 64-byte payload); anything longer is noise
MAX_BODY_BYTES = 2 + 64


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: ``data`` without any 0x00 (no delimiter added).

    Each run of non-zero bytes (split at the zeros) becomes a code byte (its length + 1) and
    the run; a run of 254 bytes or more is cut into 254-byte blocks under code 255, which
    imply no zero. The bytes equal the textbook byte-by-byte encoder's (a property test
    checks it); per frame it costs a split and one append per run, not a Python step per
    byte (the drive board's commands go out at 1 kHz).
    """
    out = bytearray()
    for run in data.split(b"\x00"):
        while len(run) >= 254:
            out.append(255)
            out += run[:254]
            run = run[254:]
        out.append(len(run) + 1)
        out += run
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`.

    Raises:
        MalformedMessageError: a zero byte inside, or a code pointing past the end.
    """
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise MalformedMessageError("COBS: zero byte inside a frame")
        end = i + code
        if end > n:
            raise MalformedMessageError("COBS: block runs past the end of the frame")
        block = data[i + 1:end]
        if 0 in block:
            raise MalformedMessageError("COBS: zero byte inside a frame")
        out += block
        i = end
        if code < 255 and i < n:
            out.append(0)
    return bytes(out)


def encode_link_frame(arb_id: int, payload: bytes) -> bytes:
    """One serial link frame: COBS of (ID, payload), then the 0x00 delimiter."""
    return cobs_encode(_ARB.pack(arb_id & 0xFFFF) + payload) + b"\x00"


@dataclass(slots=True)
class LinkDecoderStats:
    """Counters of the serial stream."""

    bytes_in: int = 0
    frames_ok: int = 0
    bad_frames: int = 0
    garbage_bytes: int = 0


class LinkFrameDecoder:
    """Incremental decoder: bytes in, ``(arb_id, payload)`` pairs out; bad frames counted."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.stats = LinkDecoderStats()

    def feed(self, data: bytes | bytearray | memoryview) -> list[tuple[int, bytes]]:
        """Add received bytes; return every complete, well-formed frame, in order."""
        self.stats.bytes_in += len(data)
        self._buffer += data
        out: list[tuple[int, bytes]] = []
        while True:
            end = self._buffer.find(0)
            if end < 0:
                if len(self._buffer) > MAX_BODY_BYTES + 2:  # no delimiter in sight: noise
                    self.stats.garbage_bytes += len(self._buffer)
                    self._buffer.clear()
                return out
            chunk = bytes(self._buffer[:end])
            del self._buffer[:end + 1]
            if not chunk:
                continue  # idle delimiters are legal
            try:
                body = cobs_decode(chunk)
            except MalformedMessageError:
                body = b""
            if len(body) < _ARB.size or len(body) > MAX_BODY_BYTES:
                self.stats.bad_frames += 1
                self.stats.garbage_bytes += len(chunk) + 1
                continue
            (arb_id,) = _ARB.unpack_from(body)
            out.append((arb_id, body[_ARB.size:]))
            self.stats.frames_ok += 1
