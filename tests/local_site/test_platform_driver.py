"""XYZ platform driver through the real byte protocol: loop:// and a pty pair."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from local_site.devices import open_platform
from local_site.platform.kinematics import PlatformGeometry, WrapUnwrapper
from local_site.platform.motion import HoldMotion, WaypointMotion
from local_site.platform.protocol import EncoderSample, encode_sample_frame
from local_site.platform.serial_board import SerialEncoderPlatform
from local_site.platform.sim import SimulatedPlatform
from local_site.platform.sim_board import SimulatedEncoderBoard
from shared.errors import (
    ConfigError,
    DeviceInitError,
    DeviceNotConnectedError,
    DeviceOperationError,
    DeviceTimeoutError,
)
from tests.support import scaled, wait_until

GEOMETRY = PlatformGeometry()
RES_MM = max(abs(s) for s in GEOMETRY.mm_per_count)


def _line(speed_mm_s: float = 10.0) -> WaypointMotion:
    """x moves at ``speed`` from 10 mm for 3 s; y, z fixed."""
    return WaypointMotion(np.array([0.0, 3.0]),
                          np.array([[10.0, 20.0, 50.0], [10.0 + 3 * speed_mm_s, 20.0, 50.0]]))


@pytest.fixture
def loop_port() -> Iterator[serial.SerialBase]:
    port = serial.serial_for_url("loop://", timeout=0.02)
    yield port
    port.close()


def _expected_position(motion: WaypointMotion, board_t_us: int, t0_us: int = 0) -> np.ndarray:
    return motion.sample(np.array([(board_t_us - t0_us) * 1e-6]))[0]


def test_loop_reads_positions_of_the_motion_within_one_count(loop_port: serial.SerialBase) -> None:
    motion = _line()
    board = SimulatedEncoderBoard(motion, loop_port.write, sample_rate_hz=500)
    platform = SerialEncoderPlatform("loop://", port=loop_port)
    with board, platform:
        samples = [platform.read_state(scaled(0.5)) for _ in range(50)]
    for s in samples:
        expected = _expected_position(motion, s.board_t_us)
        assert np.max(np.abs(np.asarray(s.position_mm) - expected)) <= RES_MM
    seqs = [s.seq for s in samples]
    assert seqs == sorted(set(seqs))  # strictly increasing: each read is a newer sample
    vx = np.median([s.velocity_mm_s[0] for s in samples[10:]])
    assert vx == pytest.approx(10.0, abs=1.5)  # +-1 count over the 10 ms window
    assert platform.board_info is not None and platform.board_info.pulses_per_rev == 1024


def test_garbage_and_crc_errors_are_counted_and_skipped(loop_port: serial.SerialBase) -> None:
    board = SimulatedEncoderBoard(HoldMotion((30.0, 30.0, 90.0)), loop_port.write,
                                  sample_rate_hz=500)
    platform = SerialEncoderPlatform("loop://", port=loop_port)
    with board, platform:
        platform.read_state(scaled(0.5))
        corrupt = bytearray(encode_sample_frame(99, 0, (0, 0, 0)))
        corrupt[-1] ^= 0x55
        board.inject(b"\x00\x13\x37" * 10)      # 30 bytes of line noise
        board.inject(bytes(corrupt))             # one frame with a bad CRC
        deadline = time.monotonic() + scaled(2.0)
        while platform.stats().crc_errors < 1 and time.monotonic() < deadline:
            platform.read_state(scaled(0.5))
        sample = platform.read_state(scaled(0.5))
        stats = platform.stats()
    assert stats.crc_errors == 1
    assert stats.garbage_bytes >= 30 + 1
    assert sample.position_mm == pytest.approx((30.0, 30.0, 90.0), abs=RES_MM)


def test_counter_and_board_clock_wrap_around(loop_port: serial.SerialBase) -> None:
    # hold 0.3 s at x = 10 mm (zeroed there), then x moves at 20 mm/s
    motion = WaypointMotion(np.array([0.0, 0.3, 1.3]),
                            np.array([[10.0, 20.0, 50.0], [10.0, 20.0, 50.0],
                                      [30.0, 20.0, 50.0]]))
    x0_counts = GEOMETRY.mm_to_counts((10.0, 0.0, 0.0))[0]
    start = 2**31 - 200 - x0_counts  # x's raw counter crosses +2^31 after ~1.8 mm of travel
    board = SimulatedEncoderBoard(motion, loop_port.write, sample_rate_hz=500,
                                  initial_counts=(start, -(2**31) + 5, 0),
                                  start_board_t_us=2**32 - 200_000, start_seq=2**32 - 50)
    platform = SerialEncoderPlatform("loop://", port=loop_port)
    with board, platform:
        first = platform.read_state(scaled(0.5))
        platform.zero(at_mm=(10.0, 20.0, 50.0))
        first = platform.read_state(scaled(0.5))
        samples = [platform.read_state(scaled(0.5)) for _ in range(300)]
    assert samples[-1].board_t_us > 2**32  # the board clock wrapped and was unwrapped
    assert samples[-1].seq > 2**32
    for s in samples:
        expected = _expected_position(motion, s.board_t_us, 2**32 - 200_000)
        assert np.max(np.abs(np.asarray(s.position_mm) - expected)) <= 2 * RES_MM
    assert first.position_mm[0] < 10.0 + 1.8 < samples[-1].position_mm[0]  # x crossed it


def test_positions_are_clamped_to_the_workspace(loop_port: serial.SerialBase) -> None:
    motion = WaypointMotion(np.array([0.0, 1.0]), np.array([[55.0, 30.0, 5.0],
                                                            [75.0, 30.0, -10.0]]))
    board = SimulatedEncoderBoard(motion, loop_port.write, sample_rate_hz=500)
    platform = SerialEncoderPlatform("loop://", port=loop_port)
    with board, platform:
        deadline = time.monotonic() + scaled(3.0)
        sample = platform.read_state(scaled(0.5))
        while not sample.clamped and time.monotonic() < deadline:
            sample = platform.read_state(scaled(0.5))
        while sample.board_t_us < 1_000_000 and time.monotonic() < deadline:
            sample = platform.read_state(scaled(0.5))
        stats = platform.stats()
    assert sample.clamped
    assert sample.position_mm == pytest.approx((60.0, 30.0, 0.0), abs=RES_MM)
    assert stats.samples_clamped > 0


def test_zero_sets_the_current_pose_as_the_given_position(loop_port: serial.SerialBase) -> None:
    board = SimulatedEncoderBoard(HoldMotion((12.0, 34.0, 56.0)), loop_port.write,
                                  sample_rate_hz=500, initial_counts=(1000, -5000, 77))
    platform = SerialEncoderPlatform("loop://", port=loop_port)
    with board, platform:
        platform.read_state(scaled(0.5))
        platform.zero()
        assert platform.read_state(scaled(0.5)).position_mm == pytest.approx((0.0, 0.0, 0.0))
        platform.zero(at_mm=(30.0, 30.0, 100.0))
        assert platform.read_state(scaled(0.5)).position_mm == \
            pytest.approx((30.0, 30.0, 100.0))
        with pytest.raises(ConfigError):
            platform.zero(at_mm=(61.0, 0.0, 0.0))


def test_silent_device_gives_init_error_then_timeout(loop_port: serial.SerialBase) -> None:
    # The same connect timeout must let the retry below find the board's first frame on a
    # loaded machine, so it scales.
    platform = SerialEncoderPlatform("loop://", port=loop_port, connect_timeout_s=scaled(0.2))
    with pytest.raises(DeviceInitError, match="no valid frame"):
        platform.connect()
    board = SimulatedEncoderBoard(HoldMotion(), loop_port.write, sample_rate_hz=500)
    with board:
        platform.connect()  # retry works once the board talks
        platform.read_state(scaled(0.5))
    wait_until(lambda: not loop_port.in_waiting, 1.0, "the reader to drain the port")
    # Samples the board sent before it stopped may still be in the decoder (a loaded reader
    # thread lags): take them, then the silent device must time out.
    with pytest.raises(DeviceTimeoutError, match="no new valid sample") as timeout:
        for _ in range(50):
            platform.read_state(0.1)
    # the message says whether the driver's reader thread had been reading the silent port
    assert re.search(r"the reader thread (read the port \d+ ms ago|has not run for)",
                     str(timeout.value)), str(timeout.value)
    platform.disconnect()
    with pytest.raises(DeviceNotConnectedError):
        platform.read_state(0.1)


def test_pty_device_disappearing_is_reported_and_connect_retries() -> None:
    platform = SimulatedPlatform(HoldMotion((20.0, 20.0, 20.0)))
    platform.connect()
    try:
        assert platform.read_state(scaled(0.5)).position_mm == pytest.approx(
            (20.0, 20.0, 20.0), abs=RES_MM)
        platform.unplug()
        with pytest.raises((DeviceOperationError, DeviceTimeoutError)) as info:
            for _ in range(20):
                platform.read_state(0.2)
        assert "device" in str(info.value)
        platform.connect()  # the station's retry: a fresh pty and board
        assert platform.read_state(scaled(0.5)).position_mm == pytest.approx(
            (20.0, 20.0, 20.0), abs=RES_MM)
    finally:
        platform.disconnect()


def test_a_reopened_link_finds_the_motion_where_it_is_now_not_at_its_start() -> None:
    # the hand on the platform keeps moving while the station reopens a silent link (the
    # station's recovery): before, every reopen restarted the scripted motion from t = 0,
    # so a busy machine's repeated reopenings kept the demo's operator at the sweep's start
    motion = _line(speed_mm_s=10.0)  # x = 10 + 10 t mm for 3 s
    platform = SimulatedPlatform(motion)
    platform.connect()
    try:
        first = platform.read_state(scaled(0.5))
        platform.disconnect()
        reopened = time.perf_counter()
        gap_s = 0.3
        time.sleep(gap_s)  # the link stays closed a known minimum time
        platform.connect()
        after = platform.read_state(scaled(0.5))
        read = time.perf_counter()
        dt_s = (after.board_t_us - first.board_t_us) * 1e-6
        # the board clock went on through the gap; the position is the motion's at that time
        assert dt_s >= gap_s
        assert dt_s <= (read - reopened) + (first.board_t_us * 1e-6) + scaled(0.5)
        assert after.position_mm[0] == pytest.approx(
            float(_expected_position(motion, after.board_t_us)[0]), abs=RES_MM)
        assert after.position_mm[0] >= 10.0 + 10.0 * gap_s - RES_MM
    finally:
        platform.disconnect()


def test_pty_raw_board_hangup_gives_operation_error() -> None:
    master, slave = os.openpty()
    import tty
    tty.setraw(slave)
    path = os.ttyname(slave)
    board = SimulatedEncoderBoard(HoldMotion(), lambda b: os.write(master, b),
                                  sample_rate_hz=500)
    platform = SerialEncoderPlatform(path)
    try:
        with board:
            platform.connect()
            platform.read_state(scaled(0.5))
        os.close(master)  # hang-up: the slave read fails with EIO
        master = -1
        with pytest.raises(DeviceOperationError, match="disappeared"):
            for _ in range(20):
                platform.read_state(0.2)
    finally:
        platform.disconnect()
        os.close(slave)
        if master >= 0:
            os.close(master)


def _read_rate_hz(platform: Any, seconds: float) -> float:
    """Reads per second over ``seconds`` of reading, less the longest gap between two reads
    if it is above 50 ms (a stall of the machine, not the board, which samples at 1 kHz;
    ``read_state`` returns the newest sample, so a stall holds up one read)."""
    gaps: list[float] = []

    def stall() -> list[float]:
        longest = max(gaps, default=0.0)
        return [longest] if longest > 0.05 else []

    last = time.perf_counter()
    while sum(gaps) - sum(stall()) < seconds:
        platform.read_state(scaled(0.5))
        now = time.perf_counter()
        gaps.append(now - last)
        last = now
    return (len(gaps) - len(stall())) / (sum(gaps) - sum(stall()))


def test_open_platform_sim_reads_at_board_rate() -> None:
    with open_platform("sim", motion="random", motion_options={"seed": 3}) as platform:
        platform.read_state(scaled(0.5))
        rate_hz = _read_rate_hz(platform, 0.5)
        stats = platform.stats()
    assert rate_hz >= 500 / max(1.0, scaled(1.0))
    assert stats.crc_errors == 0 and stats.garbage_bytes == 0


def test_open_platform_bad_url_is_init_error() -> None:
    with pytest.raises(DeviceInitError):
        open_platform("/dev/does-not-exist-teletouch")


def test_unwrapper_against_python_ints() -> None:
    rng = np.random.default_rng(1)
    steps = rng.integers(-(2**30), 2**30, size=2000)
    true = np.cumsum(steps, dtype=object) + (2**31 - 10)
    unwrap = WrapUnwrapper(32, signed=True)
    out = [unwrap.update(((int(v) + 2**31) % 2**32) - 2**31) for v in true]
    assert out[-1] - out[0] == int(true[-1] - true[0])


def test_geometry_resolution_matches_4096_counts_per_rev() -> None:
    assert GEOMETRY.counts_per_rev == 4096
    assert GEOMETRY.mm_per_count[0] == pytest.approx(math.pi * 12 / 4096)
    assert GEOMETRY.mm_per_count[2] == pytest.approx(40 / 4096)
    with pytest.raises(ConfigError):
        PlatformGeometry(mm_per_rev=(1.0, float("nan"), 1.0))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(100, 5_000), st.integers(0, 200_000)), min_size=2,
                max_size=60))
def test_capture_times_never_go_backwards(steps: list[tuple[int, int]]) -> None:
    """Arrival delays of any size and order (a loaded host): t_us strictly increases and
    never precedes the latch time on the host clock (board time + the smallest delay)."""
    platform = SerialEncoderPlatform("loop://")
    platform._info_mismatch = None  # a matching INFO taken as seen
    board_t, previous = 1_000, None
    min_delay = None
    for seq, (dt_us, delay_us) in enumerate(steps, start=1):
        board_t += dt_us
        platform._publish(EncoderSample(seq, board_t, (0, 0, 0)), rx_us=10**12 + board_t
                          + delay_us)
        sample = platform.latest()
        assert sample is not None
        min_delay = delay_us if min_delay is None else min(min_delay, delay_us)
        assert sample.t_us >= 10**12 + board_t + min_delay
        if previous is not None:
            assert sample.t_us > previous
        previous = sample.t_us


# ---------------------------------------------------------------------- board in its own process


def test_sim_process_board_streams_from_its_own_process_and_goes_with_the_link() -> None:
    platform = open_platform("sim-process", motion="hold:x=20,y=30,z=40")
    try:
        child = platform._child  # type: ignore[attr-defined]
        assert child is not None and child.poll() is None
        assert not any(t.name == "sim-encoder-board" for t in threading.enumerate())
        first = platform.read_state(scaled(0.5))
        assert first.position_mm == pytest.approx((20.0, 30.0, 40.0), abs=RES_MM)
        assert _read_rate_hz(platform, 0.3) >= 500 / max(1.0, scaled(1.0))
        # a reopened link: a new board process that continues the board's clock
        platform.disconnect()
        assert child.poll() is not None  # the board's process ended with the link
        time.sleep(0.1)
        platform.connect()
        again = platform.read_state(scaled(0.5))
        assert again.board_t_us - first.board_t_us >= 100_000
        stats = platform.stats()
        assert stats.crc_errors == 0 and stats.garbage_bytes == 0
    finally:
        platform.disconnect()


def test_sim_process_board_ends_when_the_station_process_dies() -> None:
    # the station killed (no disconnect): its board must not stream on for ever
    code = ("import os\nfrom local_site.devices import open_platform\n"
            "p = open_platform('sim-process')\nprint(p._child.pid, flush=True)\nos._exit(0)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=scaled(30.0), check=True)
    pid = int(out.stdout.split()[-1])

    def gone() -> bool:
        try:
            with open(f"/proc/{pid}/stat") as f:
                return f.read().rsplit(")", 1)[1].split()[0] == "Z"  # ended, not yet reaped
        except FileNotFoundError:
            return True

    wait_until(gone, 5.0, "the orphaned board process to end")


@pytest.mark.parametrize("motion, options", [(HoldMotion(), None),
                                             ("random", {"seed": object()})])
def test_sim_process_needs_a_motion_it_can_send_to_the_board(motion: object,
                                                             options: object) -> None:
    with pytest.raises(ConfigError, match="sim-process"):
        open_platform("sim-process", connect=False, motion=motion, motion_options=options)
