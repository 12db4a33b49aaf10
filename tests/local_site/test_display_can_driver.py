"""ArrayTac CAN FD driver on the python-can virtual bus, a raw bus playing the board."""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator

import can
import numpy as np
import pytest

from local_site.devices import open_display, parse_display_spec
from local_site.display import frames as fr
from local_site.display.can_link import CanArrayTacDisplay
from shared.errors import ConfigError, DeviceNotConnectedError, InputDataError
from shared.timebase import now_us
from tests.support import scaled, wait_until


@pytest.fixture
def link() -> Iterator[tuple[CanArrayTacDisplay, can.BusABC]]:
    channel = f"test-{uuid.uuid4().hex}"
    board = can.Bus(interface="virtual", channel=channel, fd=True)
    display = CanArrayTacDisplay(channel, interface="virtual", require_feedback=False,
                                 keepalive_interval_s=0.05, disconnect_mode=None)
    display.connect()
    yield display, board
    display.disconnect()
    board.shutdown()


def _frames(board: can.BusABC, timeout_s: float = 0.05) -> list[can.Message]:
    out = []
    while (msg := board.recv(timeout=timeout_s)) is not None:
        out.append(msg)
    return out


def test_command_frame_bytes_are_exactly_as_documented(link) -> None:
    display, board = link
    pins = np.arange(16)
    applied = display.send_command((pins * 0.3125).reshape(4, 4), 1.0 - pins * 0.02, pins * 0.02)
    (msg,) = _frames(board)
    assert msg.arbitration_id == fr.ARB_ID_COMMAND and msg.is_fd and not msg.is_extended_id
    assert len(msg.data) == 64
    frame = fr.decode_command(bytes(msg.data))
    expected = fr.encode_command(fr.CommandFrame(
        seq=applied.seq, flags=0, height_codes=(pins * 250).astype(np.uint16),
        k_codes=(250 - pins * 10).astype(np.uint16), f_codes=(pins * 5).astype(np.uint16),
        watchdog_ms=100))
    assert bytes(msg.data) == expected
    assert frame.seq == applied.seq == 1
    np.testing.assert_allclose(applied.height_mm, pins * 0.3125)


def test_clamped_command_is_returned_as_applied(link) -> None:
    display, board = link
    applied = display.send_command(np.linspace(-1.0, 7.0, 16), 0.2, 1.7)
    assert applied.clamped and applied.sent
    assert applied.height_mm.min() == 0.0 and applied.height_mm.max() == 5.0
    np.testing.assert_allclose(applied.stiffness_k, 0.5)
    np.testing.assert_allclose(applied.friction, 1.0)
    (msg,) = _frames(board)
    wire = fr.decode_command(bytes(msg.data))
    np.testing.assert_allclose(wire.height_mm, applied.height_mm)
    np.testing.assert_allclose(wire.stiffness_k, applied.stiffness_k)
    # quantisation is part of "applied": 1.2345 mm -> 1.235 (a 1.25 um multiple)
    applied = display.send_command(1.2345)
    assert applied.height_mm[0] == pytest.approx(1.235) and not applied.clamped


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_input_is_rejected_and_nothing_sent(link, bad: float) -> None:
    display, board = link
    height = np.full(16, 1.0)
    height[5] = bad
    with pytest.raises(InputDataError, match="pin"):
        display.send_command(height)
    with pytest.raises(InputDataError):
        display.send_command(1.0, friction=np.full((4, 4), bad))
    with pytest.raises(InputDataError, match="shape"):
        display.send_command(np.ones(15))
    assert _frames(board) == []
    assert display.stats().rejected_inputs == 3 and display.stats().frames_sent == 0


def test_unchanged_commands_are_skipped_then_kept_alive(link) -> None:
    display, board = link
    first = display.send_command(2.0, 0.8, 0.1)
    skipped = [display.send_command(2.0, 0.8, 0.1) for _ in range(20)]
    assert first.sent and not any(s.sent for s in skipped)
    assert len(_frames(board, 0.01)) == 1
    time.sleep(0.06)  # past the 50 ms keepalive interval
    kept = display.send_command(2.0 + 1e-5, 0.8, 0.1)  # same after quantisation
    assert kept.sent and kept.keepalive
    (msg,) = _frames(board, 0.01)
    assert fr.decode_command(bytes(msg.data)).flags & fr.FLAG_KEEPALIVE
    changed = display.send_command(2.5, 0.8, 0.1)
    assert changed.sent and not changed.keepalive
    stats = display.stats()
    assert (stats.skipped_unchanged, stats.keepalives, stats.frames_sent) == (20, 1, 3)


def test_safe_state_frame_and_forced_resend(link) -> None:
    display, board = link
    display.send_command(3.0)
    display.safe_state("hold")
    after = display.send_command(3.0)  # unchanged, but the board is parked: must go out
    msgs = _frames(board)
    assert [m.arbitration_id for m in msgs] == [fr.ARB_ID_COMMAND, fr.ARB_ID_SAFE_STATE,
                                                fr.ARB_ID_COMMAND]
    assert len(msgs[1].data) == 8
    assert fr.decode_safe_state(bytes(msgs[1].data)) == fr.SafeStateFrame(fr.SAFE_HOLD, 2)
    assert after.sent and after.seq == 3
    with pytest.raises(ConfigError):
        display.safe_state("limp")


def test_feedback_is_decoded(link) -> None:
    display, board = link
    pins = np.arange(16)
    payload = fr.encode_feedback(fr.FeedbackFrame(
        status=fr.STATUS_SAFE_STATE | fr.STATUS_WATCHDOG_TRIPPED, seq_echo=7, board_t_us=99,
        position_codes=(pins * 100).astype(np.uint16), saturated_mask=0b101,
        commands_rejected=3, watchdog_trips=1, voltage_codes=(pins * 20).astype(np.uint16)))
    board.send(can.Message(arbitration_id=fr.ARB_ID_FEEDBACK, data=payload, is_fd=True,
                           is_extended_id=False))
    board.send(can.Message(arbitration_id=fr.ARB_ID_FEEDBACK, data=b"\x21" * 64, is_fd=True,
                           is_extended_id=False))  # corrupt: counted, ignored
    fb = display.read_feedback(timeout_s=scaled(1.0))
    np.testing.assert_allclose(fb.position_mm, pins * 0.125)
    assert fb.saturated.tolist()[:4] == [True, False, True, False]
    assert fb.safe_state and fb.watchdog_tripped and fb.seq_echo == 7
    np.testing.assert_allclose(fb.drive_voltage_v, pins * 1.0)
    deadline = time.monotonic() + scaled(1.0)
    while display.stats().bad_frames < 1 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert display.stats().bad_frames == 1 and display.stats().feedback_frames == 1


def test_not_connected_and_config_errors() -> None:
    display = CanArrayTacDisplay("nowhere", interface="virtual", require_feedback=False)
    with pytest.raises(DeviceNotConnectedError):
        display.send_command(1.0)
    with pytest.raises(ConfigError):
        CanArrayTacDisplay("x", interface="virtual", keepalive_interval_s=0.2, watchdog_ms=100)


def test_display_specs_parse() -> None:
    assert parse_display_spec("sim") == ("sim", {})
    assert parse_display_spec("can://socketcan/can0") == \
        ("can", {"interface": "socketcan", "channel": "can0"})
    assert parse_display_spec("virtual:bench") == \
        ("can", {"interface": "virtual", "channel": "bench"})
    assert parse_display_spec("/dev/ttyACM0") == ("serial", {"url": "/dev/ttyACM0"})
    assert parse_display_spec("socket://10.0.0.2:5000") == \
        ("serial", {"url": "socket://10.0.0.2:5000"})
    with pytest.raises(ConfigError):
        parse_display_spec("bogus")
    with pytest.raises(ConfigError):
        open_display("sim", bogus_option=1)


def _feed(display: CanArrayTacDisplay, board: can.BusABC, status: int, *,
          board_t_us: int = 0, trips: int = 1) -> None:
    """The raw bus plays the board: one feedback frame, waited for until decoded."""
    before = display.stats().feedback_frames
    board.send(can.Message(arbitration_id=fr.ARB_ID_FEEDBACK, is_fd=True, is_extended_id=False,
                           data=fr.encode_feedback(fr.FeedbackFrame(
                               status=status, seq_echo=0, board_t_us=board_t_us,
                               position_codes=np.zeros(16, np.uint16), saturated_mask=0,
                               commands_rejected=0, watchdog_trips=trips,
                               voltage_codes=np.zeros(16, np.uint16)))))
    wait_until(lambda: display.stats().feedback_frames > before, 1.0, "feedback decoded")


def _flags(board: can.BusABC) -> list[int]:
    return [fr.decode_command(bytes(m.data)).flags for m in _frames(board)
            if m.arbitration_id == fr.ARB_ID_COMMAND]


TRIPPED = fr.STATUS_SAFE_STATE | fr.STATUS_WATCHDOG_TRIPPED


def test_resume_once_per_trip_read_and_again_only_when_the_trip_persists(link) -> None:
    display, board = link
    display.send_command(1.0)
    assert _flags(board) == [0]
    _feed(display, board, TRIPPED, board_t_us=1_000_000)
    display.send_command(2.0)  # built after the trip was read: RESUME
    assert _flags(board) == [fr.FLAG_RESUME]
    # more feedback still showing the trip, stamped by the board within the retry time of
    # the RESUME (the board's answer may be on its way): no second RESUME a freeze could
    # hold past a new trip
    _feed(display, board, TRIPPED, board_t_us=1_005_000)
    display.send_command(3.0)
    assert _flags(board) == [0]
    # the trip still reported a second later on the board's clock: the RESUME was lost
    _feed(display, board, TRIPPED, board_t_us=2_000_000)
    display.send_command(4.0)
    assert _flags(board) == [fr.FLAG_RESUME]
    # the board left the latch: no RESUME
    _feed(display, board, 0, board_t_us=2_010_000)
    display.send_command(5.0)
    assert _flags(board) == [0] and display.stats().resumes == 2


@pytest.mark.parametrize("trip_t_us", [1_000_000, 0xFFFF_FFFF - 1_000])
def test_late_delivered_feedback_is_judged_by_the_boards_clock_not_its_arrival(
        link, trip_t_us: int) -> None:
    # Found by audit: the retry was judged on the host's arrival time, so feedback the board
    # sent before it applied the RESUME, delivered 20 ms late (a starved reader, a backlog
    # on the bus or in a socket), counted as "RESUME lost" and a second RESUME went out.
    display, board = link
    _feed(display, board, TRIPPED, board_t_us=trip_t_us)
    display.send_command(1.0)
    assert _flags(board) == [fr.FLAG_RESUME]
    sent_us = now_us()
    # the retry time passes on the host: the board's reply is late
    wait_until(lambda: now_us() > sent_us + 25_000, 1.0, "25 ms on the host clock")
    # sent 2 ms after the trip frame by the board's clock (wrapping past 2**32 in the
    # second case), i.e. before the board could have seen the RESUME: not news
    _feed(display, board, TRIPPED, board_t_us=(trip_t_us + 2_000) & 0xFFFF_FFFF)
    display.send_command(2.0)
    assert _flags(board) == [0] and display.stats().resumes == 1
    # a second later by the board's clock (wrapped), still tripped: lost, sent again
    _feed(display, board, TRIPPED, board_t_us=(trip_t_us + 1_000_000) & 0xFFFF_FFFF)
    display.send_command(3.0)
    assert _flags(board) == [fr.FLAG_RESUME] and display.stats().resumes == 2


def test_a_new_trip_asks_for_a_resume_at_once(link) -> None:
    # the board left the latch and tripped again within the retry time (its trip counter
    # moved): the new trip needs its own RESUME
    display, board = link
    _feed(display, board, TRIPPED, board_t_us=1_000_000, trips=1)
    display.send_command(1.0)
    _feed(display, board, TRIPPED, board_t_us=1_001_000, trips=2)
    display.send_command(2.0)
    assert _flags(board) == [fr.FLAG_RESUME, fr.FLAG_RESUME]
