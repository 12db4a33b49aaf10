"""Encoder-board protocol: exact bytes, round trips, resynchronisation, random bytes."""

from __future__ import annotations

import contextlib
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from local_site.platform.protocol import (
    BoardInfo,
    EncoderFrameDecoder,
    EncoderSample,
    crc16_ccitt,
    decode_frame,
    encode_info_frame,
    encode_sample_frame,
)
from shared.errors import MalformedMessageError

INT32 = st.integers(-(2**31), 2**31 - 1)
UINT32 = st.integers(0, 2**32 - 1)


def _crc_bitwise(data: bytes) -> int:
    """Independent bit-by-bit CRC-16/CCITT-FALSE reference."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


@given(data=st.binary(max_size=80))
def test_crc_matches_the_bitwise_reference(data: bytes) -> None:
    assert crc16_ccitt(data) == _crc_bitwise(data)
    assert crc16_ccitt(b"123456789") == 0x29B1


def test_sample_frame_exact_bytes_match_the_spec_example() -> None:
    # docs/platform_protocol.md, "Example": seq 7, t 1000 us, counts (4096, -1, 2**31 - 1)
    frame = encode_sample_frame(7, 1000, (4096, -1, 2**31 - 1))
    assert frame.hex(" ") == ("a5 5a 14 01 07 00 00 00 e8 03 00 00 00 10 00 00 "
                              "ff ff ff ff ff ff ff 7f e5 8a")
    body = frame[2:-2]
    assert struct.unpack("<H", frame[-2:])[0] == _crc_bitwise(body)


def test_counts_wrap_to_signed_32_bit_on_encode() -> None:
    frame = encode_sample_frame(0, 0, (2**31, -(2**31) - 1, 0))
    sample = decode_frame(frame)
    assert isinstance(sample, EncoderSample)
    assert sample.counts == (-(2**31), 2**31 - 1, 0)


@given(seq=UINT32, t=UINT32, counts=st.tuples(INT32, INT32, INT32))
def test_sample_round_trip(seq: int, t: int, counts: tuple[int, int, int]) -> None:
    assert decode_frame(encode_sample_frame(seq, t, counts)) == EncoderSample(seq, t, counts)


def test_info_round_trip() -> None:
    info = BoardInfo(1, 3, 1024, 4, 1000, 0x0100)
    assert decode_frame(encode_info_frame(info)) == info


@given(data=st.binary(max_size=200))
def test_decode_frame_of_random_bytes_raises_only_the_typed_error(data: bytes) -> None:
    with contextlib.suppress(MalformedMessageError):
        decode_frame(data)


@settings(max_examples=200)
@given(data=st.binary(max_size=400), chunk=st.integers(1, 50))
def test_stream_decoder_never_crashes_on_random_bytes(data: bytes, chunk: int) -> None:
    decoder = EncoderFrameDecoder()
    for i in range(0, len(data), chunk):
        frames = decoder.feed(data[i:i + chunk])
        assert all(isinstance(f, EncoderSample | BoardInfo) for f in frames)
    stats = decoder.stats
    assert stats.bytes_in == len(data)
    assert stats.garbage_bytes <= len(data)


@given(garbage=st.binary(max_size=60), chunk=st.integers(1, 30),
       counts=st.lists(st.tuples(INT32, INT32, INT32), min_size=1, max_size=5))
def test_good_frames_survive_leading_garbage_in_any_chunking(
        garbage: bytes, chunk: int, counts: list[tuple[int, int, int]]) -> None:
    frames = b"".join(encode_sample_frame(i, i * 1000, c) for i, c in enumerate(counts))
    # garbage must not itself end in a partial sync that fuses with the frame: strip A5
    stream = garbage.replace(b"\xa5", b"\x00") + frames
    decoder = EncoderFrameDecoder()
    got = []
    for i in range(0, len(stream), chunk):
        got += decoder.feed(stream[i:i + chunk])
    assert [g.counts for g in got] == counts  # type: ignore[union-attr]
    assert decoder.stats.garbage_bytes == len(garbage)


def test_crc_error_is_counted_and_the_next_frame_recovered() -> None:
    good1 = encode_sample_frame(1, 1000, (1, 2, 3))
    bad = bytearray(encode_sample_frame(2, 2000, (4, 5, 6)))
    bad[10] ^= 0xFF
    good3 = encode_sample_frame(3, 3000, (7, 8, 9))
    decoder = EncoderFrameDecoder()
    got = decoder.feed(good1 + bytes(bad) + good3)
    assert [g.seq for g in got] == [1, 3]  # type: ignore[union-attr]
    assert decoder.stats.crc_errors == 1
    assert decoder.stats.frames_ok == 2
    assert decoder.stats.garbage_bytes == len(bad)


def test_truncated_frame_then_good_frame() -> None:
    partial = encode_sample_frame(1, 1000, (1, 2, 3))[:12]
    good = encode_sample_frame(2, 2000, (4, 5, 6))
    decoder = EncoderFrameDecoder()
    got = decoder.feed(partial + good)
    assert [g.seq for g in got] == [2]  # type: ignore[union-attr]
    assert decoder.stats.crc_errors >= 1


@pytest.mark.parametrize("frame", [b"", b"\xa5\x5a", b"\x00" * 26])
def test_decode_frame_rejects_short_or_unsynced(frame: bytes) -> None:
    with pytest.raises(MalformedMessageError):
        decode_frame(frame)
