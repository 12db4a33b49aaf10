"""Length-prefix framing for raw TCP: ``uint32 big-endian length`` + that many bytes.

WebSocket needs no framing of ours (one binary WebSocket message = one Tele-Touch
message). Over TCP, :class:`LengthPrefixDecoder` turns a byte stream, in chunks of any
size, back into whole payloads. A length over the limit or of zero cannot be
resynchronised, so it is fatal for the connection.
"""

from __future__ import annotations

import struct

from shared.errors import MalformedMessageError, OversizeError

__all__ = ["HEADER", "LengthPrefixDecoder", "frame"]

HEADER = struct.Struct(">I")


def frame(payload: bytes) -> bytes:
    """Prefix ``payload`` with its length (4 bytes, big-endian)."""
    return HEADER.pack(len(payload)) + payload


class LengthPrefixDecoder:
    """Incremental decoder of length-prefixed frames.

    Args:
        max_message_bytes: longest payload accepted.
    """

    def __init__(self, max_message_bytes: int) -> None:
        self.max_message_bytes = max_message_bytes
        self._buffer = bytearray()
        self._need: int | None = None  # payload length once the header is read

    @property
    def buffered(self) -> int:
        """Bytes received but not yet returned as a payload."""
        return len(self._buffer)

    def feed(self, data: bytes | bytearray | memoryview) -> list[bytes]:
        """Add received bytes; return every payload now complete, in order.

        A broken header right behind complete payloads does not take them with it: they are
        returned, and the header raises at the next call (``feed(b"")`` will do).

        Raises:
            OversizeError: a header announces more than ``max_message_bytes``.
            MalformedMessageError: a header announces an empty payload.
        """
        self._buffer += data
        out: list[bytes] = []
        while True:
            if self._need is None:
                if len(self._buffer) < HEADER.size:
                    return out
                (length,) = HEADER.unpack_from(self._buffer)
                if out and (length > self.max_message_bytes or length == 0):
                    return out  # deliver what came before it; the header raises next call
                if length > self.max_message_bytes:
                    raise OversizeError(f"frame announces {length} bytes, limit is "
                                        f"{self.max_message_bytes}")
                if length == 0:
                    raise MalformedMessageError("frame of length 0")
                del self._buffer[:HEADER.size]
                self._need = length
            if len(self._buffer) < self._need:
                return out
            out.append(bytes(self._buffer[:self._need]))
            del self._buffer[:self._need]
            self._need = None
