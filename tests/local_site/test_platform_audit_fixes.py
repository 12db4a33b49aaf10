"""The platform audit's findings: stamps of queued frames, a board restart on an open link,
the zero across a reconnect after a counter wrap, the reader's latest across a reopen, an
exception in the data callback, counters across reconnects, the stale timeout, bad
timeouts."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator

import pytest
import serial

from local_site.agent.platform_reader import PlatformReader
from local_site.platform.base import PlatformSample, XYZPlatform
from local_site.platform.kinematics import PlatformGeometry
from local_site.platform.motion import HoldMotion
from local_site.platform.protocol import (
    PROTOCOL_VERSION,
    BoardInfo,
    EncoderSample,
    encode_info_frame,
    encode_sample_frame,
)
from local_site.platform.serial_board import SerialEncoderPlatform
from local_site.platform.sim_board import SimulatedEncoderBoard
from shared.errors import ConfigError, DeviceInitError, DeviceOperationError
from shared.timebase import monotonic_s, now_us
from tests.support import scaled, wait_until

HOST0 = 1_700_000_000_000_000  # host clock (us) at the board's sample 0
LINK_US = 1_000  # the link's fixed delay
MM_PER_COUNT_X = PlatformGeometry().mm_per_count[0]
#: the INFO of a board like the default geometry (samples are used only after one)
INFO = encode_info_frame(BoardInfo(PROTOCOL_VERSION, 3, 1024, 4, 1000, 1))


class _Board(XYZPlatform):
    """A platform the test feeds: ``connect()`` publishes ``first``, the test the rest."""

    def __init__(self) -> None:
        super().__init__(connect_timeout_s=scaled(2.0))
        self._info_mismatch = None  # a matching INFO taken as seen
        self.first = EncoderSample(0, 0, (0, 0, 0))

    def _connect(self) -> None:
        self._publish(self.first)

    def _disconnect(self) -> None:
        pass


def _feed(platform: XYZPlatform, seq: int, board_t_us: int, rx_us: int,
          x_counts: int = 0) -> PlatformSample:
    platform._publish(EncoderSample(seq, board_t_us, (x_counts, 0, 0)), rx_us=rx_us)
    sample = platform.latest()
    assert sample is not None
    return sample


@pytest.fixture
def loop_port() -> Iterator[serial.SerialBase]:
    port = serial.serial_for_url("loop://", timeout=0.02)
    yield port
    port.close()


# ---------------------------------------------------------------------- 1: queued frames


def test_a_burst_of_queued_frames_is_not_stamped_fresher_than_it_is() -> None:
    """2 s of a 1 kHz board, then its frames wait 1 s in a queue (a USB stall, a starved reader
    thread) and arrive at once: before, the clock offset rose by 1/1000 of the difference per
    sample and stamped the backlog up to 300 ms younger than it was; now by at most 1 % of
    the board time since the burst began (10 ms here)."""
    platform = _Board()
    for k in range(2000):
        _feed(platform, k, k * 1000, HOST0 + k * 1000 + LINK_US + (k % 7) * 50)
    rx = HOST0 + 3000 * 1000 + LINK_US
    for k in range(2000, 3000):
        sample = _feed(platform, k, k * 1000, rx)
        true_age_us = rx - (HOST0 + k * 1000 + LINK_US)
        allowed_us = (k - 1999) * 1000 // 100 + 1000  # 1 % of the burst's board time
        assert rx - sample.t_us >= true_age_us - allowed_us, (k, rx - sample.t_us, true_age_us)


@pytest.mark.parametrize("ppm", [200, -200, 2500, -2500, 5000])
def test_a_board_clock_drifting_is_still_tracked(ppm: int) -> None:
    """The bounded creep (1 %) follows a board clock off by as much as a ceramic resonator
    (0.5 %) or USB full speed (0.25 %): 60 s at 200 ppm would put the stamps 12 ms off if
    the offset were pinned, and a 1000 ppm cap left a 2500 ppm board 450 ms behind after
    300 s (found by review)."""
    platform = _Board()
    for k in range(60_000):
        latch = HOST0 + k * 1000
        sample = _feed(platform, k, round(k * 1000 * (1 - ppm * 1e-6)),
                       latch + LINK_US + (k % 7) * 50)
    assert abs(sample.t_us - (latch + LINK_US)) <= 500


# ---------------------------------------------------------------------- 2: board restart


@pytest.mark.parametrize("uptime_s", [600, 4290])  # 10 min; 71.5 min: the clock's wrap near
def test_a_board_that_restarts_on_an_open_link_is_stamped_fresh_at_once(uptime_s: int) -> None:
    """seq, the board clock and the counters start again at 0 on the same link: before, the
    stamps stayed at 'previous + 1 us' and the samples looked stale for ~8 s (10 min of
    uptime), and then x jumped from 27.6 mm to the counters' new origin, 0."""
    platform = _Board()
    k0 = uptime_s * 1000
    for k in range(k0 - 1000, k0):
        last = _feed(platform, k, k * 1000 % 2**32, HOST0 + k * 1000 + LINK_US,
                     x_counts=k - k0 + 3000)
    for j in range(20):
        rx = HOST0 + (k0 + j) * 1000 + LINK_US
        sample = _feed(platform, j, j * 1000, rx, x_counts=j)
        assert rx - sample.t_us <= LINK_US, (j, rx - sample.t_us)  # fresh, not stale
        assert sample.seq == j and sample.board_t_us == j * 1000
        assert sample.position_mm[0] == pytest.approx(last.position_mm[0] + j * MM_PER_COUNT_X)
    assert sample.velocity_mm_s[0] == pytest.approx(1000 * MM_PER_COUNT_X)
    stats = platform.stats()
    assert stats.board_restarts == 1 and stats.samples_missed == 0
    assert stats.position_rebases == 1


def test_a_board_that_describes_itself_differently_restarted() -> None:
    platform = _Board()
    info = BoardInfo(1, 3, 1024, 4, 1000, 0x0100)
    platform._publish_info(info)
    for k in range(10):
        _feed(platform, k, k * 1000, HOST0 + k * 1000 + LINK_US)
    platform._publish_info(info)  # the same board, once a second: no restart
    assert platform.stats().board_restarts == 0
    platform._publish_info(BoardInfo(1, 3, 1024, 4, 1000, 0x0200))  # reflashed and restarted
    assert platform.stats().board_restarts == 1
    rx = HOST0 + 20_000 + LINK_US
    assert _feed(platform, 10, 10_000, rx).t_us == rx  # the new clock mapping starts here


# ---------------------------------------------------------------------- 3: zero and a wrap


def test_the_zero_holds_across_a_reconnect_after_a_counter_wrap() -> None:
    """X crossed +2^31 while connected; after a reconnect the kept zero (unwrapped counts)
    and the restarted unwrapping (raw counts) differed by 2^32: x went from 2 mm to 0."""
    platform = _Board()
    start = 2**31 - 100
    platform.first = EncoderSample(0, 0, (start, 0, 0))
    platform.connect()
    platform.zero()
    moved = start + 217 - 2**32  # 217 counts further: the raw counter wrapped to -2^31 + 117
    x_before = _feed(platform, 1, 1000, now_us(), x_counts=moved).position_mm[0]
    assert x_before == pytest.approx(217 * MM_PER_COUNT_X)
    platform._link_failed(OSError("unplugged"))
    platform.first = EncoderSample(2, 2000, (moved, 0, 0))
    platform.connect()  # reopens the broken link
    after = platform.latest()
    assert after is not None and after.seq == 2
    assert after.position_mm[0] == pytest.approx(x_before) and not after.clamped
    platform.disconnect()


# ---------------------------------------------------------------------- 4: reader's latest


class _Watched(_Board):
    """Records the reader's ``latest`` at the moment ``connect()`` forgets the driver's
    newest sample."""

    def __init__(self) -> None:
        super().__init__()
        self.reader: PlatformReader | None = None
        self.seen_at_reopen: list[PlatformSample | None] = []

    def _before_connect(self) -> None:
        super()._before_connect()
        if self.reader is not None:
            self.seen_at_reopen.append(self.reader.latest)


def test_the_readers_latest_never_steps_back_while_the_platform_is_reopened() -> None:
    """The reader thread reads every poll_s, the board streams faster: at a reopen, latest
    fell back to the reader's own last read sample, older than the driver's newest."""
    platform = _Watched()
    reader = PlatformReader(platform, read_timeout_s=scaled(5.0), poll_s=scaled(0.5),
                            retry_min_s=0.01)
    platform.reader = reader
    reader.start()
    try:
        wait_until(lambda: reader.reads >= 1, 3.0, "the reader's first read")
        with platform._cond:  # the reader thread sees none of these before the link error
            for k in range(1, 6):
                _feed(platform, k, k * 1000, now_us())
            newest = platform.latest()
            platform._link_failed(OSError("unplugged"))
        wait_until(lambda: reader.reconnects >= 1, 3.0, "the reopen")
        assert platform.seen_at_reopen[-1] is newest
    finally:
        reader.stop()
        platform.disconnect()


# ---------------------------------------------------------------------- 5: callback errors


def test_an_exception_in_the_data_callback_fails_the_link_and_connect_reopens(
        loop_port: serial.SerialBase, caplog: pytest.LogCaptureFixture) -> None:
    """Before, it ended the reader thread unseen: healthy, connect() a no-op, and the next
    read_state blamed a busy host for the silence."""
    board = SimulatedEncoderBoard(HoldMotion((20.0, 20.0, 20.0)), loop_port.write,
                                  sample_rate_hz=500)
    platform = SerialEncoderPlatform("loop://", port=loop_port)
    calls = [0]

    def listener(_sample: PlatformSample) -> None:
        calls[0] += 1
        if calls[0] == 5:
            raise ValueError("listener broke")

    platform.sample_listener = listener
    with board, platform:
        with pytest.raises(DeviceOperationError,
                           match="handling received bytes failed: ValueError: listener broke"):
            for _ in range(100):
                platform.read_state(scaled(0.5))
        assert "handling received bytes failed" in caplog.text
        platform.connect()  # the station's retry reopens the port
        assert platform.read_state(scaled(0.5)).position_mm == pytest.approx(
            (20.0, 20.0, 20.0), abs=0.01)


class _FailsAfterOpening(_Board):
    """Opens fine and delivers samples, then its link fails from the reader thread 20 ms
    later, every time (a data callback that raises after a few samples); records when each
    connection was made. (A failure inside _connect fails connect() itself, whose own retry
    loop backed off before this fix too: found by review.)"""

    def __init__(self) -> None:
        super().__init__()
        self.opened_at_s: list[float] = []
        self.seq = 0

    def _connect(self) -> None:
        self.opened_at_s.append(monotonic_s())

        def feed() -> None:
            for _ in range(4):
                self.seq += 1
                self._publish(EncoderSample(self.seq, self.seq * 5000, (0, 0, 0)))
                threading.Event().wait(0.005)
            self._link_failed(OSError("the data callback raised"))

        threading.Thread(target=feed, daemon=True).start()


def test_a_link_that_fails_right_after_every_reopen_backs_off() -> None:
    """Before, each reopen waited retry_min_s again (the backoff started anew with every
    successful open): about five reopens a second, each with a traceback, for ever. Now the
    waits go on doubling while a reopened link fails within retry_max_s (lower bounds only:
    a loaded machine makes them longer, never shorter)."""
    platform = _FailsAfterOpening()
    reader = PlatformReader(platform, read_timeout_s=scaled(5.0), poll_s=0.001,
                            retry_min_s=0.05, retry_max_s=0.4)
    reader.start()
    try:
        wait_until(lambda: len(platform.opened_at_s) >= 6, 10.0, "six openings")
    finally:
        reader.stop()
        platform.disconnect()
    gaps = [b - a for a, b in zip(platform.opened_at_s, platform.opened_at_s[1:], strict=False)]
    for k, gap in enumerate(gaps[:5]):
        assert gap >= min(0.4, 0.05 * 2**k) * 0.95, (k, gaps)


def test_a_link_that_failed_after_a_long_run_is_reopened_after_the_shortest_wait(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The backoff of a flapping link does not carry over to a failure after a connection
    that lasted a second or more."""
    reader = PlatformReader(_Board(), read_timeout_s=1.0, retry_min_s=0.05, retry_max_s=0.4)
    reader.errors, reader._lost_at_s = 1, 0.0
    waits: list[float] = []

    def wait(seconds: float) -> bool:
        waits.append(seconds)
        return False

    monkeypatch.setattr(reader._stop, "wait", wait)
    reader._opened_at_s, reader._flap_delay_s = monotonic_s() - 2.0, 0.4  # lived 2 s
    assert reader._connect_with_backoff(link_failed=True) and waits == [0.05]
    reader._opened_at_s, reader._flap_delay_s = monotonic_s(), 0.2
    assert reader._connect_with_backoff(link_failed=True) and waits == [0.05, 0.2]
    assert reader._flap_delay_s == 0.4  # doubled for the next failure
    reader._opened_at_s = monotonic_s()  # a silent device's reopen does not back off on
    assert reader._connect_with_backoff(link_failed=False) and waits[-1] == 0.05
    reader.platform.disconnect()


# ---------------------------------------------------------------------- 6: lower findings


def test_the_link_counters_are_totals_over_reconnects(loop_port: serial.SerialBase) -> None:
    corrupt = bytearray(encode_sample_frame(1, 1000, (0, 0, 0)))
    corrupt[-1] ^= 0x55
    loop_port.write(INFO + encode_sample_frame(0, 0, (0, 0, 0)) + bytes(corrupt)
                    + encode_sample_frame(2, 2000, (0, 0, 0)))
    platform = SerialEncoderPlatform("loop://", port=loop_port)
    platform.connect()
    try:
        wait_until(lambda: platform.stats().frames_ok == 3, 2.0, "the INFO and both good frames")
        platform.read_state(scaled(0.5))
        before = platform.stats()
        assert (before.crc_errors, before.samples_missed, before.reads) == (1, 1, 1)
        platform.disconnect()  # (the frame below must wait for the new connection)
        loop_port.write(encode_sample_frame(3, 3000, (0, 0, 0)))
        platform.connect()
        wait_until(lambda: platform.stats().frames_ok == 4, 2.0, "the frame after the reopen")
        after = platform.stats()
        assert (after.crc_errors, after.samples_missed, after.reads) == (1, 1, 1)
        assert after.bytes_in == before.bytes_in + 26
        assert after.garbage_bytes == before.garbage_bytes
    finally:
        platform.disconnect()


def test_connect_reopens_a_link_silent_for_the_stale_timeout(
        loop_port: serial.SerialBase, caplog: pytest.LogCaptureFixture) -> None:
    """Before, stale_timeout_s was accepted and never used: connect() on a link silent for
    ten times that long did nothing."""
    loop_port.write(INFO + encode_sample_frame(0, 0, (0, 0, 0)))
    platform = SerialEncoderPlatform("loop://", port=loop_port, stale_timeout_s=0.05,
                                     connect_timeout_s=scaled(0.5))
    platform.connect()
    try:
        wait_until(lambda: not platform._is_healthy(), 2.0, "the stale timeout")
        with caplog.at_level(logging.INFO, logger="shared.devices.base"), \
                pytest.raises(DeviceInitError, match="no valid frame"):
            platform.connect()  # closes and reopens; the board is still silent
        assert "link broken, reconnecting" in caplog.text
    finally:
        platform.disconnect()


@pytest.mark.parametrize("timeout_s", [float("nan"), float("inf"), -1.0])
def test_read_state_refuses_a_timeout_that_is_not_finite_and_positive(timeout_s: float) -> None:
    platform = _Board()
    platform.connect()  # a sample waits: before, read_state returned it (or, silent, hung)
    with pytest.raises(ConfigError, match="timeout_s must be finite and >= 0"):
        platform.read_state(timeout_s)
    platform.disconnect()


@pytest.mark.parametrize("name", ["connect_timeout_s", "stale_timeout_s", "velocity_window_s"])
def test_the_driver_refuses_an_infinite_duration(name: str) -> None:
    with pytest.raises(ConfigError, match=f"{name} must be finite and > 0"):
        SerialEncoderPlatform("loop://", **{name: float("inf")})  # type: ignore[arg-type]


def test_a_frame_delivered_twice_is_dropped_not_a_restart() -> None:
    """The same frame again (seq and board time equal to the last): dropped and counted, not
    taken for a restart (found by review: it counted a restart and republished the frame)."""
    platform = _Board()
    for k in range(1, 100):
        _feed(platform, k, k * 1000, HOST0 + k * 1000 + LINK_US)
    last = platform.latest()
    platform._publish(EncoderSample(99, 99_000, (0, 0, 0)), rx_us=HOST0 + 100_000 + LINK_US)
    assert platform.latest() is last
    sample = _feed(platform, 100, 100_000, HOST0 + 100_000 + LINK_US)
    stats = platform.stats()
    assert stats.duplicates == 1 and stats.board_restarts == 0
    assert sample.seq == 100 and sample.t_us == HOST0 + 100_000 + LINK_US
