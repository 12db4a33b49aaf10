"""Sans-I/O codec of the XYZ encoder-board serial protocol (see docs/platform_protocol.md).

Board -> host only. Every frame is::

    A5 5A | len u8 | type u8 | payload (len bytes) | crc u16 LE

``crc`` is CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)
over ``len``, ``type`` and the payload. All multi-byte fields are little-endian.

:class:`EncoderFrameDecoder` takes bytes in chunks of any size and gives decoded frames
out; it resynchronises on garbage (hunts for the next sync pair) and counts what it
skipped, so a noisy line costs samples, never a crash.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass

from shared.errors import MalformedMessageError

__all__ = [
    "INFO_STRUCT",
    "MAX_PAYLOAD_BYTES",
    "PROTOCOL_VERSION",
    "SAMPLE_STRUCT",
    "SYNC",
    "TYPE_INFO",
    "TYPE_SAMPLE",
    "BoardInfo",
    "DecoderStats",
    "EncoderFrameDecoder",
    "EncoderSample",
    "crc16_ccitt",
    "decode_frame",
    "encode_info_frame",
    "encode_sample_frame",
]

SYNC = b"\xa5\x5a"
TYPE_SAMPLE = 0x01
TYPE_INFO = 0x02
MAX_PAYLOAD_BYTES = 64
#: seq u32, board time u32 (us), counts x/y/z int32
SAMPLE_STRUCT = struct.Struct("<IIiii")
#: protocol version u8, axes u8, pulses per revolution u16, decoding u8, sample rate u16 (Hz),
#: firmware version u16
INFO_STRUCT = struct.Struct("<BBHBHH")
_HEADER = struct.Struct("<2sBB")
_CRC = struct.Struct("<H")
PROTOCOL_VERSION = 1


def crc16_ccitt(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (check value of b"123456789" is 0x29B1)."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True, slots=True)
class EncoderSample:
    """One sample frame: raw counter values as the board latched them.

    Attributes:
        seq: board sample counter (uint32, wraps).
        board_t_us: board clock at the latch instant, microseconds (uint32, wraps ~71.6 min).
        counts: raw signed 32-bit quadrature counters (x, y, z); they wrap at +-2^31.
    """

    seq: int
    board_t_us: int
    counts: tuple[int, int, int]


@dataclass(frozen=True, slots=True)
class BoardInfo:
    """The board's self-description, sent at start-up and then once a second."""

    protocol_version: int
    axes: int
    pulses_per_rev: int
    decoding: int
    sample_rate_hz: int
    firmware_version: int


@dataclass(slots=True)
class DecoderStats:
    """Counters of the byte stream: what arrived, what was good, what was skipped."""

    bytes_in: int = 0
    frames_ok: int = 0
    crc_errors: int = 0
    garbage_bytes: int = 0
    unknown_types: int = 0


def _frame(frame_type: int, payload: bytes) -> bytes:
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    body = bytes((len(payload), frame_type)) + payload
    return SYNC + body + _CRC.pack(crc16_ccitt(body))


def encode_sample_frame(seq: int, board_t_us: int, counts: tuple[int, int, int]) -> bytes:
    """Encode one sample frame (26 bytes).

    Args:
        seq: sample counter, reduced modulo 2^32.
        board_t_us: board clock in microseconds, reduced modulo 2^32.
        counts: the three counters; reduced to signed 32 bits (two's complement wrap).

    Returns:
        The frame bytes, sync to CRC.
    """
    wrapped = tuple(((int(c) + 2**31) % 2**32) - 2**31 for c in counts)
    payload = SAMPLE_STRUCT.pack(seq % 2**32, board_t_us % 2**32, *wrapped)
    return _frame(TYPE_SAMPLE, payload)


def encode_info_frame(info: BoardInfo) -> bytes:
    """Encode the board self-description frame (15 bytes)."""
    payload = INFO_STRUCT.pack(info.protocol_version, info.axes, info.pulses_per_rev,
                               info.decoding, info.sample_rate_hz, info.firmware_version)
    return _frame(TYPE_INFO, payload)


def decode_frame(frame: bytes) -> EncoderSample | BoardInfo:
    """Decode exactly one whole frame (sync to CRC).

    Raises:
        MalformedMessageError: wrong sync, length, CRC, type or payload size.
    """
    if len(frame) < _HEADER.size + _CRC.size or frame[:2] != SYNC:
        raise MalformedMessageError("encoder frame: missing sync bytes A5 5A or too short")
    length = frame[2]
    if len(frame) != _HEADER.size + length + _CRC.size:
        raise MalformedMessageError(f"encoder frame: length byte says {length}, "
                                    f"frame holds {len(frame) - 6} payload bytes")
    (crc_rx,) = _CRC.unpack_from(frame, len(frame) - 2)
    if crc16_ccitt(frame[2:-2]) != crc_rx:
        raise MalformedMessageError("encoder frame: CRC mismatch")
    return _decode_payload(frame[3], frame[4:-2])


def _decode_payload(frame_type: int, payload: bytes) -> EncoderSample | BoardInfo:
    if frame_type == TYPE_SAMPLE:
        if len(payload) != SAMPLE_STRUCT.size:
            raise MalformedMessageError(f"sample frame payload of {len(payload)} bytes, "
                                        f"expected {SAMPLE_STRUCT.size}")
        seq, t_us, cx, cy, cz = SAMPLE_STRUCT.unpack(payload)
        return EncoderSample(seq=seq, board_t_us=t_us, counts=(cx, cy, cz))
    if frame_type == TYPE_INFO:
        if len(payload) != INFO_STRUCT.size:
            raise MalformedMessageError(f"info frame payload of {len(payload)} bytes, "
                                        f"expected {INFO_STRUCT.size}")
        return BoardInfo(*INFO_STRUCT.unpack(payload))
    raise MalformedMessageError(f"encoder frame: unknown type 0x{frame_type:02x}")


class EncoderFrameDecoder:
    """Incremental, resynchronising decoder of the encoder-board byte stream.

    Bytes before a sync pair, and the first byte of a candidate frame that fails its CRC,
    are counted as garbage and skipped; decoding continues from the next sync pair, so a
    corrupted frame never swallows the good frame behind it.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.stats = DecoderStats()

    def feed(self, data: bytes | bytearray | memoryview) -> list[EncoderSample | BoardInfo]:
        """Add received bytes; return every frame now complete and valid, in order."""
        self.stats.bytes_in += len(data)
        buf = self._buffer
        buf += data
        out: list[EncoderSample | BoardInfo] = []
        while True:
            start = buf.find(SYNC)
            if start < 0:
                # keep a trailing 0xA5: it may be the first half of a sync pair
                keep = 1 if buf[-1:] == SYNC[:1] else 0
                self.stats.garbage_bytes += len(buf) - keep
                del buf[:len(buf) - keep]
                return out
            if start:
                self.stats.garbage_bytes += start
                del buf[:start]
            if len(buf) < 3:
                return out
            length = buf[2]
            if length > MAX_PAYLOAD_BYTES:
                self.stats.garbage_bytes += 1
                del buf[:1]
                continue
            total = _HEADER.size + length + _CRC.size
            if len(buf) < total:
                return out
            (crc_rx,) = _CRC.unpack_from(buf, total - 2)
            if crc16_ccitt(buf[2:total - 2]) != crc_rx:
                self.stats.crc_errors += 1
                self.stats.garbage_bytes += 1
                del buf[:1]
                continue
            frame_type = buf[3]
            payload = bytes(buf[4:total - 2])
            del buf[:total]
            try:
                out.append(_decode_payload(frame_type, payload))
            except MalformedMessageError:
                self.stats.unknown_types += 1
                continue
            self.stats.frames_ok += 1
