"""ArrayTac frame codecs: the documented bytes, round trips, random bytes, COBS framing."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from local_site.display import frames as fr
from local_site.display.serial_framing import (
    LinkFrameDecoder,
    cobs_decode,
    cobs_encode,
    encode_link_frame,
)
from shared.errors import MalformedMessageError

PINS = np.arange(16)

# docs/arraytac_can.md, "Example": exactly these bytes
DOC_COMMAND_HEX = (
    "11 01 34 12 00 a0 0f f4 e1 2e e8 23 4e dc 65 6d "
    "d0 a7 8c c4 e9 ab b8 2b cb ac 6d ea fa f0 e6 dc "
    "d2 c8 be b4 aa a0 96 8c 82 78 6e 64 00 05 0a 0f "
    "14 19 1e 23 28 2d 32 37 3c 41 46 4b 64 00 73 06")
DOC_FEEDBACK_HEX = (
    "21 03 34 12 15 cd 5b 07 00 a0 0f f4 e1 2e e8 23 "
    "4e dc 65 6d d0 a7 8c c4 e9 ab b8 2b cb ac 6d ea "
    "01 80 02 00 01 00 e8 c3 44 b0 44 51 78 c5 5d 40 "
    "46 6a 08 c7 76 d0 47 83 98 c8 8f 60 49 9c 9b ad")
DOC_SAFE_HEX = "31 01 35 12 00 00 c2 73"


def _crc_bitwise(data: bytes) -> int:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def test_command_frame_matches_the_documented_example() -> None:
    frame = fr.CommandFrame(seq=0x1234, flags=fr.FLAG_KEEPALIVE,
                            height_codes=(PINS * 250).astype(np.uint16),
                            k_codes=(250 - PINS * 10).astype(np.uint16),
                            f_codes=(PINS * 5).astype(np.uint16), watchdog_ms=100)
    data = fr.encode_command(frame)
    assert len(data) == 64
    assert data.hex(" ") == DOC_COMMAND_HEX
    assert int.from_bytes(data[62:], "little") == _crc_bitwise(data[:62])
    back = fr.decode_command(data)
    np.testing.assert_allclose(back.height_mm, PINS * 0.3125)
    np.testing.assert_allclose(back.stiffness_k, 1.0 - PINS * 0.02)
    np.testing.assert_allclose(back.friction, PINS * 0.02)
    assert (back.seq, back.flags, back.watchdog_ms) == (0x1234, 1, 100)


def test_feedback_and_safe_state_match_the_documented_examples() -> None:
    fb = fr.FeedbackFrame(status=fr.STATUS_SAFE_STATE | fr.STATUS_WATCHDOG_TRIPPED,
                          seq_echo=0x1234, board_t_us=123456789,
                          position_codes=(PINS * 250).astype(np.uint16), saturated_mask=0x8001,
                          commands_rejected=2, watchdog_trips=1,
                          voltage_codes=(1000 + PINS * 100).astype(np.uint16))
    data = fr.encode_feedback(fb)
    assert data.hex(" ") == DOC_FEEDBACK_HEX
    back = fr.decode_feedback(data)
    assert back.saturated.tolist() == [True] + [False] * 14 + [True]
    np.testing.assert_allclose(back.drive_voltage_v, 50.0 + PINS * 5.0)
    safe = fr.encode_safe_state(fr.SafeStateFrame(mode=fr.SAFE_HOLD, seq=0x1235))
    assert safe.hex(" ") == DOC_SAFE_HEX
    assert fr.decode_safe_state(safe) == fr.SafeStateFrame(fr.SAFE_HOLD, 0x1235)


def _codes(max_code: int) -> st.SearchStrategy[np.ndarray]:
    return st.lists(st.integers(0, max_code), min_size=16, max_size=16).map(
        lambda v: np.asarray(v, dtype=np.uint16))


@given(seq=st.integers(0, 0xFFFF), flags=st.integers(0, 0xFF), h=_codes(4000),
       k=_codes(250), f=_codes(250), wd=st.integers(0, 0xFFFF))
def test_command_round_trip_over_the_whole_range(seq: int, flags: int, h: np.ndarray,
                                                 k: np.ndarray, f: np.ndarray, wd: int) -> None:
    frame = fr.CommandFrame(seq, flags, h, k, f, wd)
    back = fr.decode_command(fr.encode_command(frame))
    assert (back.seq, back.flags, back.watchdog_ms) == (seq, flags, wd)
    np.testing.assert_array_equal(back.height_codes, h)
    np.testing.assert_array_equal(back.k_codes, k)
    np.testing.assert_array_equal(back.f_codes, f)


@given(status=st.integers(0, 0xFF), seq=st.integers(0, 0xFFFF), t=st.integers(0, 2**32 - 1),
       p=_codes(0xFFF), sat=st.integers(0, 0xFFFF), rej=st.integers(0, 0xFFFF),
       trips=st.integers(0, 0xFFFF), v=_codes(0xFFF))
def test_feedback_round_trip_over_the_whole_range(status: int, seq: int, t: int, p: np.ndarray,
                                                  sat: int, rej: int, trips: int,
                                                  v: np.ndarray) -> None:
    back = fr.decode_feedback(fr.encode_feedback(
        fr.FeedbackFrame(status, seq, t, p, sat, rej, trips, v)))
    assert (back.status, back.seq_echo, back.board_t_us, back.saturated_mask,
            back.commands_rejected, back.watchdog_trips) == (status, seq, t, sat, rej, trips)
    np.testing.assert_array_equal(back.position_codes, p)
    np.testing.assert_array_equal(back.voltage_codes, v)


def _pack12_reference(codes: np.ndarray) -> bytes:
    """The layout as docs/arraytac_can.md states it, byte by byte, for each pair (a, b)."""
    out = bytearray()
    for a, b in np.asarray(codes, dtype=np.int64).reshape(-1, 2).tolist():
        out += bytes((a & 0xFF, ((a >> 8) & 0x0F) | ((b & 0x0F) << 4), (b >> 4) & 0xFF))
    return bytes(out)


@given(codes=_codes(0xFFF))
def test_pack12_round_trip(codes: np.ndarray) -> None:
    packed = fr.pack12(codes)
    assert len(packed) == 24
    assert packed == _pack12_reference(codes)  # an independent reference of the layout
    unpacked = fr.unpack12(packed)
    assert unpacked.dtype == np.uint16
    np.testing.assert_array_equal(unpacked, codes)
    np.testing.assert_array_equal(fr.unpack12(memoryview(b"head" + packed)[4:]), codes)


def test_pack12_refuses_odd_lengths() -> None:
    with pytest.raises(ValueError, match="even number"):
        fr.pack12(np.zeros(3, np.uint16))
    with pytest.raises(ValueError, match="multiple of 3"):
        fr.unpack12(b"\x00" * 23)


@settings(max_examples=300)
@given(data=st.binary(max_size=80))
def test_decoders_of_random_bytes_raise_only_the_typed_error(data: bytes) -> None:
    for decode in (fr.decode_command, fr.decode_feedback, fr.decode_safe_state):
        with contextlib.suppress(MalformedMessageError):
            decode(data)


def test_single_bit_flips_are_rejected() -> None:
    good = bytearray.fromhex(DOC_COMMAND_HEX.replace(" ", ""))
    for bit in range(0, 64 * 8, 7):
        bad = bytearray(good)
        bad[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(MalformedMessageError):
            fr.decode_command(bytes(bad))


def test_out_of_range_codes_with_valid_crc_are_rejected() -> None:
    data = bytearray.fromhex(DOC_COMMAND_HEX.replace(" ", ""))
    data[28] = 251  # k code of pin 0 beyond 1.0
    data[62:] = fr.frame_crc(data[:62]).to_bytes(2, "little")
    with pytest.raises(MalformedMessageError, match="out of range"):
        fr.decode_command(bytes(data))


@settings(max_examples=200)
@given(seq=st.integers(-2**70, 2**70), flags=st.integers(-2**70, 2**70),
       wd=st.integers(-2**70, 2**70), h=_codes(0xFFFF), k=_codes(0xFFFF), f=_codes(0xFFFF),
       in_range=st.booleans())
def test_compiled_command_encoder_gives_the_bytes_and_refusals_of_the_python_one(
        seq: int, flags: int, wd: int, h: np.ndarray, k: np.ndarray, f: np.ndarray,
        in_range: bool) -> None:
    """uint16 codes (the display's own) take the compiled encoder; int64 codes take the
    Python one: the same 64 bytes (header fields masked to their widths, whatever integers
    they were given), or the same refusal of a code out of range."""
    if in_range:
        h, k, f = h % 4001, k % 251, f % 251
    fast = fr.CommandFrame(seq, flags, h, k, f, wd)
    slow = fr.CommandFrame(seq, flags, h.astype(np.int64), k.astype(np.int64),
                           f.astype(np.int64), wd)
    ok = bool(h.max() <= 4000 and k.max() <= 250 and f.max() <= 250)
    if ok:
        assert fr.encode_command(fast) == fr.encode_command(slow)
        assert fr.encode_command(fast)[4:28] == fr.pack12(h)  # the heights, packed in Python
    else:
        for frame in (fast, slow):
            with pytest.raises(ValueError, match="codes in"):
                fr.encode_command(frame)


def test_encoder_refuses_unquantised_codes() -> None:
    with pytest.raises(ValueError):
        fr.encode_command(fr.CommandFrame(0, 0, np.full(16, 4001, np.uint16),
                                          np.zeros(16, np.uint16), np.zeros(16, np.uint16)))


@given(data=st.binary(max_size=600))
def test_cobs_round_trip_has_no_zero_bytes(data: bytes) -> None:
    encoded = cobs_encode(data)
    assert 0 not in encoded
    assert cobs_decode(encoded) == data


def _cobs_reference(data: bytes) -> bytes:
    """The textbook byte-by-byte COBS encoder (the form the station used before)."""
    out, block = bytearray(), bytearray()
    for byte in data:
        if byte == 0:
            out.append(len(block) + 1)
            out += block
            block.clear()
        else:
            block.append(byte)
            if len(block) == 254:
                out.append(255)
                out += block
                block.clear()
    out.append(len(block) + 1)
    out += block
    return bytes(out)


#: data made of runs of non-zero bytes around the 254-byte block length, joined by zeros
_RUNS = st.lists(st.tuples(st.one_of(st.sampled_from([253, 254, 255, 508]), st.integers(0, 600)),
                           st.integers(1, 255), st.integers(0, 2)),
                 max_size=5).map(lambda runs: b"".join(bytes([v]) * n + b"\x00" * z
                                                       for n, v, z in runs))


@given(data=st.one_of(st.binary(max_size=600), _RUNS))
def test_cobs_encoder_equals_the_byte_by_byte_reference(data: bytes) -> None:
    assert cobs_encode(data) == _cobs_reference(data)
    assert cobs_decode(cobs_encode(data)) == data


def test_cobs_known_vectors() -> None:
    assert cobs_encode(b"") == b"\x01"
    assert cobs_encode(b"\x00") == b"\x01\x01"
    assert cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    run = bytes(range(1, 255))  # 254 non-zero bytes: one full block, then an empty one
    assert cobs_encode(run) == b"\xff" + run + b"\x01"
    assert cobs_encode(run + b"\x00") == b"\xff" + run + b"\x01\x01"


@settings(max_examples=300)
@given(noise=st.binary(max_size=300), chunk=st.integers(1, 40))
def test_link_decoder_survives_noise_and_recovers(noise: bytes, chunk: int) -> None:
    frame = encode_link_frame(fr.ARB_ID_FEEDBACK, bytes.fromhex(DOC_FEEDBACK_HEX.replace(" ", "")))
    stream = noise + b"\x00" + frame
    decoder = LinkFrameDecoder()
    got = []
    for i in range(0, len(stream), chunk):
        got += decoder.feed(stream[i:i + chunk])
    assert got[-1] == (fr.ARB_ID_FEEDBACK, bytes.fromhex(DOC_FEEDBACK_HEX.replace(" ", "")))
