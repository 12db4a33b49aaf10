"""Sans-I/O codec of the ArrayTac drive-board frames (bit-exact spec: docs/arraytac_can.md).

Three frames, all little-endian, each ending in CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF)
over every byte before it:

- ``COMMAND`` (host -> board, arbitration ID 0x100, 64 bytes): a whole 16-pin update:
  height 12 bit (1.25 um per LSB, 0..4000 = 0..5 mm), stiffness k 8 bit (0.002 per LSB,
  0..250 = 0.5..1.0), friction f 8 bit (0.004 per LSB, 0..250 = 0..1), sequence number,
  flags (keepalive, watchdog safe-state mode, resume after a watchdog trip) and the
  link-loss watchdog timeout.
- ``FEEDBACK`` (board -> host, 0x180, 64 bytes): measured pin positions (12 bit, 1.25 um),
  saturation bitmask, drive voltages (12 bit, 0.05 V), status flags, echo of the last applied
  command sequence, board clock, error counters.
- ``SAFE_STATE`` (host -> board, 0x080, 8 bytes, highest priority): go flat or hold now.

The same payloads travel over serial framed by :mod:`local_site.display.serial_framing`.
Decoders raise :class:`~shared.errors.MalformedMessageError` (a remote protocol error) and
nothing else on bad bytes.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from shared.errors import MalformedMessageError

__all__ = [
    "ARB_ID_COMMAND",
    "ARB_ID_FEEDBACK",
    "ARB_ID_SAFE_STATE",
    "COMMAND_FRAME_BYTES",
    "FEEDBACK_FRAME_BYTES",
    "FLAG_KEEPALIVE",
    "FLAG_RESUME",
    "FLAG_WATCHDOG_HOLD",
    "F_LSB",
    "HEIGHT_LSB_MM",
    "HEIGHT_MAX_CODE",
    "K_LSB",
    "K_MAX_CODE",
    "N_PINS",
    "SAFE_FLAT",
    "SAFE_HOLD",
    "SAFE_STATE_FRAME_BYTES",
    "STATUS_COMMAND_REJECTED",
    "STATUS_FAULT",
    "STATUS_SAFE_HOLD",
    "STATUS_SAFE_STATE",
    "STATUS_WATCHDOG_TRIPPED",
    "VOLTAGE_LSB_V",
    "CommandFrame",
    "FeedbackFrame",
    "SafeStateFrame",
    "decode_command",
    "decode_feedback",
    "decode_safe_state",
    "encode_command",
    "encode_feedback",
    "encode_safe_state",
    "frame_crc",
    "pack12",
    "unpack12",
]

N_PINS = 16
ARB_ID_SAFE_STATE = 0x080
ARB_ID_COMMAND = 0x100
ARB_ID_FEEDBACK = 0x180

COMMAND_FRAME_BYTES = 64
FEEDBACK_FRAME_BYTES = 64
SAFE_STATE_FRAME_BYTES = 8

TYPE_COMMAND = 0x11
TYPE_FEEDBACK = 0x21
TYPE_SAFE_STATE = 0x31

HEIGHT_LSB_MM = 0.00125
HEIGHT_MAX_CODE = 4000  # 5.000 mm
POSITION_MAX_CODE = 0xFFF  # feedback may read a little beyond 5 mm
K_LSB = 0.002
K_MIN = 0.5
K_MAX_CODE = 250  # k = 1.0
F_LSB = 0.004
F_MAX_CODE = 250  # f = 1.0
VOLTAGE_LSB_V = 0.05

FLAG_KEEPALIVE = 0x01
FLAG_WATCHDOG_HOLD = 0x02
#: the host has seen the board's watchdog trip and this command is fresh: leave the latch
FLAG_RESUME = 0x04

SAFE_FLAT = 0
SAFE_HOLD = 1

STATUS_SAFE_STATE = 0x01
STATUS_WATCHDOG_TRIPPED = 0x02
STATUS_SAFE_HOLD = 0x04
STATUS_COMMAND_REJECTED = 0x08
STATUS_FAULT = 0x10

_CMD_HEAD = struct.Struct("<BBH")          # type, flags, seq
_CMD_TAIL = struct.Struct("<HH")           # watchdog_ms, crc
_FB_HEAD = struct.Struct("<BBHI")          # type, status, seq_echo, board_t_us
_FB_MID = struct.Struct("<HHH")            # saturated mask, rejected, watchdog trips
_SAFE = struct.Struct("<BBHHH")            # type, mode, seq, reserved, crc
_CRC = struct.Struct("<H")
_PIN_BITS = np.arange(N_PINS)


def frame_crc(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE (check value of b"123456789" is 0x29B1)."""
    return binascii.crc_hqx(data, 0xFFFF)


def pack12(codes: np.ndarray) -> bytes:
    """Pack 16 unsigned 12-bit codes into 24 bytes, two codes per three bytes.

    For a pair (a, b): byte0 = a[7:0], byte1 = a[11:8] | b[3:0] << 4, byte2 = b[11:4]. So
    the bytes, read as one little-endian integer, hold code i at bits 12 i .. 12 i + 11:
    packed with Python integers (a few us; the numpy version's ten array operations on 16
    values cost 3x more, at 1,500-3,000 calls/s in the display path).

    Raises:
        ValueError: an odd number of codes.
    """
    values = np.asarray(codes, dtype=np.uint16).ravel().tolist()
    if len(values) % 2:
        raise ValueError(f"pack12 needs an even number of codes, got {len(values)}")
    word = 0
    for i, code in enumerate(values):
        word |= (code & 0xFFF) << (12 * i)
    return word.to_bytes(len(values) * 3 // 2, "little")


def unpack12(data: bytes | bytearray | memoryview) -> np.ndarray:
    """Inverse of :func:`pack12`: 24 bytes -> 16 codes (uint16).

    Raises:
        ValueError: a length that is not a multiple of 3.
    """
    if len(data) % 3:
        raise ValueError(f"unpack12 needs a multiple of 3 bytes, got {len(data)}")
    word = int.from_bytes(data, "little")
    return np.array([(word >> shift) & 0xFFF for shift in range(0, len(data) * 8, 12)],
                    dtype=np.uint16)


def _check_codes(name: str, codes: np.ndarray, max_code: int) -> np.ndarray:
    arr = np.asarray(codes)
    if arr.shape != (N_PINS,) or arr.dtype.kind not in "iu" \
            or (arr.dtype.kind == "i" and arr.min() < 0) or arr.max() > max_code:
        raise ValueError(f"{name} must be {N_PINS} integer codes in [0, {max_code}]")
    return arr


@dataclass(frozen=True, slots=True, eq=False)
class CommandFrame:
    """A decoded ``COMMAND`` frame, as integer codes (the exact wire content).

    Attributes:
        seq: sequence number (uint16, wraps).
        flags: ``FLAG_*`` bits.
        height_codes: 16 codes, 1.25 um each (0..4000).
        k_codes: 16 codes, k = 0.5 + 0.002 * code (0..250).
        f_codes: 16 codes, f = 0.004 * code (0..250).
        watchdog_ms: link-loss timeout the board must apply (0: the board's default).
    """

    seq: int
    flags: int
    height_codes: np.ndarray
    k_codes: np.ndarray
    f_codes: np.ndarray
    watchdog_ms: int = 0

    @property
    def height_mm(self) -> np.ndarray:
        """Heights in mm, shape (16,)."""
        return self.height_codes.astype(float) * HEIGHT_LSB_MM

    @property
    def stiffness_k(self) -> np.ndarray:
        """Stiffness k in [0.5, 1], shape (16,)."""
        return K_MIN + self.k_codes.astype(float) * K_LSB

    @property
    def friction(self) -> np.ndarray:
        """Friction f in [0, 1], shape (16,)."""
        return self.f_codes.astype(float) * F_LSB


def encode_command(frame: CommandFrame) -> bytes:
    """Encode a ``COMMAND`` frame: exactly 64 bytes.

    Raises:
        ValueError: a code out of range (a bug of the caller: quantise first).
    """
    h, k, f = frame.height_codes, frame.k_codes, frame.f_codes
    if not (type(h) is np.ndarray and type(k) is np.ndarray and type(f) is np.ndarray
            and h.dtype == _U16 and k.dtype == _U16 and f.dtype == _U16
            and h.shape == k.shape == f.shape == (N_PINS,) and h.flags.c_contiguous
            and k.flags.c_contiguous and f.flags.c_contiguous):
        # other integer types or layouts: checked, then as the display's own codes are
        h, k, f = (np.ascontiguousarray(_check_codes(name, codes, top), dtype=np.uint16)
                   for name, codes, top in (("height_codes", h, HEIGHT_MAX_CODE),
                                            ("k_codes", k, K_MAX_CODE),
                                            ("f_codes", f, F_MAX_CODE)))
    packed = np.empty(COMMAND_FRAME_BYTES - 2, np.uint8)
    if not _command_body_kernel(h, k, f, frame.flags & 0xFF, frame.seq & 0xFFFF,
                                frame.watchdog_ms & 0xFFFF, packed):
        for name, codes, top in (("height_codes", h, HEIGHT_MAX_CODE),
                                 ("k_codes", k, K_MAX_CODE), ("f_codes", f, F_MAX_CODE)):
            _check_codes(name, codes, top)  # raises, naming the layer
    data = packed.tobytes()
    return data + _CRC.pack(frame_crc(data))


_U16 = np.dtype(np.uint16)


@njit(cache=True, nogil=True)
def _command_body_kernel(h: NDArray[np.uint16], k: NDArray[np.uint16], f: NDArray[np.uint16],
                         flags: int, seq: int, watchdog_ms: int,
                         out: NDArray[np.uint8]) -> bool:  # pragma: no cover - compiled
    """A ``COMMAND`` frame's 62 bytes before the CRC into ``out`` (docs/arraytac_can.md: head,
    the heights packed as :func:`pack12` packs them, k and f bytes, watchdog); False when a
    code is out of range (then ``out`` is garbage and the caller raises)."""
    out[0] = TYPE_COMMAND
    out[1] = flags & 0xFF
    out[2] = seq & 0xFF
    out[3] = (seq >> 8) & 0xFF
    for pair in range(N_PINS // 2):
        a, b = h[2 * pair], h[2 * pair + 1]
        if a > HEIGHT_MAX_CODE or b > HEIGHT_MAX_CODE:
            return False
        out[4 + 3 * pair] = a & 0xFF
        out[5 + 3 * pair] = ((a >> 8) & 0x0F) | ((b & 0x0F) << 4)
        out[6 + 3 * pair] = (b >> 4) & 0xFF
    for i in range(N_PINS):
        if k[i] > K_MAX_CODE or f[i] > F_MAX_CODE:
            return False
        out[28 + i] = k[i]
        out[44 + i] = f[i]
    out[60] = watchdog_ms & 0xFF
    out[61] = (watchdog_ms >> 8) & 0xFF
    return True


def _check_frame(data: bytes, size: int, type_byte: int, what: str) -> None:
    if len(data) != size:
        raise MalformedMessageError(f"{what} frame of {len(data)} bytes, expected {size}")
    if data[0] != type_byte:
        raise MalformedMessageError(f"{what} frame: type byte 0x{data[0]:02x}, "
                                    f"expected 0x{type_byte:02x}")
    (crc_rx,) = _CRC.unpack_from(data, size - 2)
    if frame_crc(data[:-2]) != crc_rx:
        raise MalformedMessageError(f"{what} frame: CRC mismatch")


def decode_command(data: bytes | bytearray | memoryview) -> CommandFrame:
    """Decode a ``COMMAND`` frame.

    Raises:
        MalformedMessageError: wrong size, type, CRC, or a code out of range.
    """
    data = bytes(data)
    _check_frame(data, COMMAND_FRAME_BYTES, TYPE_COMMAND, "command")
    _, flags, seq = _CMD_HEAD.unpack_from(data, 0)
    h = unpack12(data[4:28])
    k = np.frombuffer(data, dtype=np.uint8, count=16, offset=28).astype(np.uint16)
    f = np.frombuffer(data, dtype=np.uint8, count=16, offset=44).astype(np.uint16)
    (watchdog_ms,) = struct.unpack_from("<H", data, 60)
    if h.max() > HEIGHT_MAX_CODE or k.max() > K_MAX_CODE or f.max() > F_MAX_CODE:
        raise MalformedMessageError("command frame: a height, k or f code is out of range")
    return CommandFrame(seq=seq, flags=flags, height_codes=h, k_codes=k, f_codes=f,
                        watchdog_ms=watchdog_ms)


@dataclass(frozen=True, slots=True, eq=False)
class FeedbackFrame:
    """A decoded ``FEEDBACK`` frame.

    Attributes:
        status: ``STATUS_*`` bits.
        seq_echo: sequence number of the last command the board applied.
        board_t_us: board clock (uint32 microseconds, wraps).
        position_codes: 16 measured positions, 1.25 um each (0..4095).
        saturated_mask: bit i set when pin i is saturated (stiffness limit reached).
        commands_rejected: frames the board dropped (bad CRC/format), uint16, wraps.
        watchdog_trips: times the link-loss watchdog fired, uint16, wraps.
        voltage_codes: 16 piezo drive voltages, 0.05 V each (0..4095).
    """

    status: int
    seq_echo: int
    board_t_us: int
    position_codes: np.ndarray
    saturated_mask: int
    commands_rejected: int
    watchdog_trips: int
    voltage_codes: np.ndarray

    @property
    def position_mm(self) -> np.ndarray:
        """Measured pin positions, mm, shape (16,)."""
        return self.position_codes.astype(float) * HEIGHT_LSB_MM

    @property
    def saturated(self) -> np.ndarray:
        """Saturation flags, bool, shape (16,)."""
        return (self.saturated_mask >> _PIN_BITS) & 1 == 1

    @property
    def drive_voltage_v(self) -> np.ndarray:
        """Piezo drive voltages, V, shape (16,)."""
        return self.voltage_codes.astype(float) * VOLTAGE_LSB_V


def encode_feedback(frame: FeedbackFrame) -> bytes:
    """Encode a ``FEEDBACK`` frame: exactly 64 bytes.

    Raises:
        ValueError: a code out of range.
    """
    p = _check_codes("position_codes", frame.position_codes, POSITION_MAX_CODE)
    v = _check_codes("voltage_codes", frame.voltage_codes, 0xFFF)
    body = (_FB_HEAD.pack(TYPE_FEEDBACK, frame.status & 0xFF, frame.seq_echo & 0xFFFF,
                          frame.board_t_us & 0xFFFFFFFF)
            + pack12(p)
            + _FB_MID.pack(frame.saturated_mask & 0xFFFF, frame.commands_rejected & 0xFFFF,
                           frame.watchdog_trips & 0xFFFF)
            + pack12(v))
    return body + _CRC.pack(frame_crc(body))


def decode_feedback(data: bytes | bytearray | memoryview) -> FeedbackFrame:
    """Decode a ``FEEDBACK`` frame.

    Raises:
        MalformedMessageError: wrong size, type or CRC.
    """
    data = bytes(data)
    _check_frame(data, FEEDBACK_FRAME_BYTES, TYPE_FEEDBACK, "feedback")
    _, status, seq_echo, board_t_us = _FB_HEAD.unpack_from(data, 0)
    sat, rejected, trips = _FB_MID.unpack_from(data, 32)
    return FeedbackFrame(status=status, seq_echo=seq_echo, board_t_us=board_t_us,
                         position_codes=unpack12(data[8:32]), saturated_mask=sat,
                         commands_rejected=rejected, watchdog_trips=trips,
                         voltage_codes=unpack12(data[38:62]))


@dataclass(frozen=True, slots=True)
class SafeStateFrame:
    """A decoded ``SAFE_STATE`` frame: ``mode`` is ``SAFE_FLAT`` or ``SAFE_HOLD``."""

    mode: int
    seq: int


def encode_safe_state(frame: SafeStateFrame) -> bytes:
    """Encode a ``SAFE_STATE`` frame: exactly 8 bytes."""
    if frame.mode not in (SAFE_FLAT, SAFE_HOLD):
        raise ValueError(f"safe-state mode must be {SAFE_FLAT} or {SAFE_HOLD}")
    body = _SAFE.pack(TYPE_SAFE_STATE, frame.mode, frame.seq & 0xFFFF, 0, 0)[:-2]
    return body + _CRC.pack(frame_crc(body))


def decode_safe_state(data: bytes | bytearray | memoryview) -> SafeStateFrame:
    """Decode a ``SAFE_STATE`` frame.

    Raises:
        MalformedMessageError: wrong size, type, CRC or mode.
    """
    data = bytes(data)
    _check_frame(data, SAFE_STATE_FRAME_BYTES, TYPE_SAFE_STATE, "safe-state")
    _, mode, seq, _reserved, _crc = _SAFE.unpack(data)
    if mode not in (SAFE_FLAT, SAFE_HOLD):
        raise MalformedMessageError(f"safe-state frame: unknown mode {mode}")
    return SafeStateFrame(mode=mode, seq=seq)
