"""A broken board link is noticed, reported and reopened (audit of the display driver).

Before: one receive error ended the driver's reader thread for good and nothing noticed it:
the display stayed "connected" and healthy (``connect()`` did nothing), its feedback froze,
and once the board's watchdog had tripped the host never sent ``RESUME``, so the board
refused every command while the display loop showed them as rendered. A board that went
silent went unnoticed the same way. Now a failed reader, or no feedback for
``feedback_timeout_s``, makes the sends raise :class:`DeviceOperationError`, the display loop
goes to ``display_lost`` and reopens the display, and the board applies commands again.
The board's fault and rejection reports reach the driver's counters.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import threading
import uuid
from collections.abc import Callable, Iterator
from types import SimpleNamespace
from typing import Any

import can
import numpy as np
import pytest
import serial

from local_site.agent.display_loop import DisplayLoop, FrameSlot, SameClockLink
from local_site.arraytac_sim.plant import ArrayTacPlant
from local_site.devices import open_display
from local_site.display import frames as fr
from local_site.display.base import ArrayTacDisplay
from local_site.display.can_link import CanArrayTacDisplay
from local_site.display.emulator import FirmwareEmulator, TcpFirmwareTransport
from local_site.display.firmware import ArrayTacFirmware
from local_site.display.serial_link import SerialArrayTacDisplay
from local_site.display.sim import SimCanArrayTacDisplay
from local_site.platform.base import PlatformSample
from local_site.render import Renderer
from local_site.scenes import TactileFrameScene
from shared.errors import ConfigError, DeviceOperationError
from shared.protocol import TactileFrame
from shared.timebase import now_us
from tests.support import scaled, wait_until

GOOD = PlatformSample((30.0, 30.0, 0.0), (0.0, 0.0, 0.0), 0, 1, 0)


def _raises(call: Callable[[], object]) -> DeviceOperationError | None:
    try:
        call()
    except DeviceOperationError as err:
        return err
    return None


# ---------------------------------------------------------------------- reader failure


def _fail_can_receive_once(display: ArrayTacDisplay) -> None:
    """The bus's next receive raises a transient CanError (an rx overflow)."""
    assert isinstance(display, CanArrayTacDisplay) and display._bus is not None
    bus = display._bus
    recv = bus.recv
    fired = threading.Event()

    def flaky(timeout: float | None = None) -> can.Message | None:
        if not fired.is_set():
            fired.set()
            raise can.CanOperationError("transient: rx overflow")
        return recv(timeout)

    bus.recv = flaky  # type: ignore[method-assign]


def _fail_serial_handling_once(display: ArrayTacDisplay) -> None:
    """The serial driver's reader fails on its next bytes (its decoder raises; the reader
    ends; a reopen builds a new decoder)."""
    assert isinstance(display, SerialArrayTacDisplay)
    decoder = display.decoder

    def broken(data: object) -> list[tuple[int, bytes]]:
        raise ValueError("decoder bug")

    decoder.feed = broken  # type: ignore[method-assign]


@pytest.mark.parametrize(("backend", "inject"), [("sim", _fail_can_receive_once),
                                                 ("sim-serial", _fail_serial_handling_once)])
def test_a_failed_reader_breaks_the_link_and_connect_reopens_it(
        backend: str, inject: Callable[[ArrayTacDisplay], None],
        caplog: pytest.LogCaptureFixture) -> None:
    display = open_display(backend, keepalive_interval_s=0.02, watchdog_ms=round(scaled(100)),
                           connect_timeout_s=scaled(3.0))
    try:
        display.send_command(2.0)
        inject(display)
        # every send now says the link is broken (before the fix: sent into a deaf link)
        wait_until(lambda: _raises(lambda: display.send_command(2.5)) is not None, 2.0,
                   "the failed reader reported by the sends")
        err = _raises(lambda: display.send_command(3.0))
        assert err is not None and "reader failed" in str(err)
        assert _raises(lambda: display.keepalive()) is not None
        assert _raises(lambda: display.safe_state("flat")) is not None
        assert "the link's reader failed" in caplog.text
        assert display.is_connected  # open, but broken: connect() must reopen it
        display.connect()
        applied = display.send_command(1.5)
        emulator = getattr(display, "emulator", None)
        assert emulator is not None
        wait_until(lambda: emulator.firmware.seq_echo == applied.seq, 2.0,
                   "the command applied after the reopen")
        # and the new reader hears the board again
        wait_until(lambda: (fb := display.latest_feedback()) is not None
                   and fb.seq_echo == applied.seq, 2.0, "the board's echo read back")
    finally:
        display.disconnect()


# ---------------------------------------------------------------------- a silent board


@pytest.fixture
def raw_link(request: pytest.FixtureRequest) -> Iterator[tuple[CanArrayTacDisplay, can.BusABC]]:
    """The CAN driver and a raw bus playing the board (it sends only what the test says);
    more driver options by indirect parametrisation."""
    channel = f"test-{uuid.uuid4().hex}"
    board = can.Bus(interface="virtual", channel=channel, fd=True)
    display = CanArrayTacDisplay(channel, interface="virtual", require_feedback=False,
                                 keepalive_interval_s=0.05, disconnect_mode=None,
                                 **getattr(request, "param", {}))
    display.connect()
    yield display, board
    display.disconnect()
    board.shutdown()


def _feedback(status: int = 0, *, rejected: int = 0, trips: int = 0,
              board_t_us: int = 1_000_000) -> bytes:
    return fr.encode_feedback(fr.FeedbackFrame(
        status=status, seq_echo=0, board_t_us=board_t_us,
        position_codes=np.zeros(16, np.uint16), saturated_mask=0, commands_rejected=rejected,
        watchdog_trips=trips, voltage_codes=np.zeros(16, np.uint16)))


def _feed(display: ArrayTacDisplay, board: can.BusABC, payload: bytes) -> None:
    """Send one feedback frame on the raw bus and wait until the driver decoded it."""
    before = display.stats().feedback_frames
    board.send(can.Message(arbitration_id=fr.ARB_ID_FEEDBACK, data=payload, is_fd=True,
                           is_extended_id=False))
    wait_until(lambda: display.stats().feedback_frames > before, 1.0, "feedback decoded")


def _drain(board: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := board.recv(timeout=scaled(0.05))) is not None:
        out.append(msg)
    return out


@pytest.mark.parametrize("raw_link", [{"feedback_timeout_s": scaled(0.2)}], indirect=True)
def test_a_board_that_goes_silent_breaks_the_link_after_the_feedback_timeout(
        raw_link: tuple[CanArrayTacDisplay, can.BusABC]) -> None:
    display, board = raw_link
    # no feedback yet, and connect() did not wait for it: nothing to judge silence from
    assert display.send_command(1.0).sent
    _feed(display, board, _feedback())
    display.send_command(1.5)
    # the board says nothing more: after feedback_timeout_s the link counts as broken
    wait_until(lambda: _raises(lambda: display.send_command(2.0)) is not None, 2.0,
               "the silence reported")
    err = _raises(lambda: display.send_command(2.0))
    assert err is not None and "no feedback from the drive board" in str(err)
    assert _raises(lambda: display.keepalive()) is not None
    _drain(board)
    # the safe state is still written (the board may hear it), then reported as unsure
    assert _raises(lambda: display.safe_state("hold")) is not None
    assert [m.arbitration_id for m in _drain(board)] == [fr.ARB_ID_SAFE_STATE]
    # connect() on the broken link reopens it (a new session; the counters are totals)
    sent_before = display.stats().frames_sent
    display.connect()
    assert display.stats().frames_sent == sent_before
    assert display.send_command(2.0).sent
    assert display.stats().frames_sent == sent_before + 1


def test_feedback_timeout_must_be_positive() -> None:
    with pytest.raises(ConfigError, match="feedback_timeout_s"):
        CanArrayTacDisplay("x", interface="virtual", feedback_timeout_s=0.0)


# ---------------------------------------------------------------------- the display loop


def _frame(seq: int, height_mm: float) -> TactileFrame:
    return TactileFrame(seq=seq, ts_us=now_us(), center_mm=(30.0, 30.0), pitch_mm=1.0,
                        layers={"height_mm": np.full((9, 9), height_mm, np.float32)})


class _RunningLoop:
    """A display loop in its thread, fed fresh frames by the test."""

    def __init__(self, display: ArrayTacDisplay, **options: Any) -> None:
        self.slot = FrameSlot()
        self.loop = DisplayLoop(display, Renderer(), TactileFrameScene(),
                                positions=lambda: GOOD, platform_ok=lambda: True,
                                frames=self.slot, link=SameClockLink(), stale_timeout_s=10.0,
                                max_frame_age_s=10.0, **options)
        self.seq = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.loop.run_in_thread, args=(self.stop,),
                                       daemon=True)

    def rendering(self, height_mm: float) -> bool:
        """Offer a fresh frame; True while the loop shows a command and no safe reason."""
        self.seq += 1
        self.slot.put(_frame(self.seq, height_mm), now_us())
        pins = self.loop.pin_state
        return pins.command is not None and pins.safe_reason is None

    def __enter__(self) -> _RunningLoop:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(scaled(10.0))
        assert not self.thread.is_alive()


@pytest.fixture
def tcp_board() -> Iterator[FirmwareEmulator]:
    """An emulated board of its own (it keeps running, and its latch, across reconnects)."""
    firmware = ArrayTacFirmware(ArrayTacPlant(), default_watchdog_ms=100)
    emulator = FirmwareEmulator(firmware, TcpFirmwareTransport("127.0.0.1", 0))
    emulator.start()
    yield emulator
    emulator.stop()


def test_the_loop_reopens_a_link_whose_reader_failed_and_the_latched_board_obeys_again(
        tcp_board: FirmwareEmulator) -> None:
    transport = tcp_board.transport
    assert isinstance(transport, TcpFirmwareTransport)
    fw = tcp_board.firmware
    watchdog_ms = round(scaled(100))
    # no safe state on disconnect: the board parks itself by its watchdog while the display
    # is reopened (the reopen waits three watchdog periods), so it is latched when the
    # driver is back, and only a RESUME the driver sends after reading the trip frees it
    display = open_display(transport.url, keepalive_interval_s=0.02, watchdog_ms=watchdog_ms,
                           connect_timeout_s=scaled(3.0), disconnect_mode=None)
    retry_s = 3 * watchdog_ms / 1000.0
    with _RunningLoop(display, retry_min_s=retry_s, retry_max_s=2 * retry_s) as running:
        wait_until(lambda: running.rendering(2.0) and fw.targets_mm.max() == 2.0, 5.0,
                   "the loop renders")
        trips = fw.watchdog_trips
        _fail_serial_handling_once(display)
        wait_until(lambda: running.loop.counters.display_errors >= 1, 5.0,
                   "the loop to see the broken link (before the fix: never)")
        wait_until(lambda: running.loop.counters.display_reconnects >= 1, 10.0,
                   "the display reopened")
        assert fw.watchdog_trips > trips  # parked by the board while the host was away
        wait_until(lambda: running.rendering(3.0) and fw.targets_mm.max() == 3.0
                   and not fw.watchdog_tripped, 5.0, "the board to apply commands again")
        assert display.stats().resumes >= 1
        assert running.loop.counters.safe_entries.get("display_lost", 0) >= 1
    display.disconnect()
    assert tcp_board.error is None


def _sim_board_that_dies_once() -> tuple[SimCanArrayTacDisplay, FirmwareEmulator,
                                          Callable[[], None]]:
    """A connected simulated display, its first board, and what makes that board's thread
    die at its next step (a bug in its plant): the bus takes the commands, nothing answers;
    a reopen starts a new board."""
    display = SimCanArrayTacDisplay(keepalive_interval_s=0.02, watchdog_ms=round(scaled(100)),
                                    connect_timeout_s=scaled(3.0))
    display.connect()
    first = display.emulator
    assert first is not None
    plant = first.firmware.plant
    advance = plant.advance
    broken = threading.Event()

    def dies_once(duration_s: float) -> None:
        if not broken.is_set():
            broken.set()
            raise RuntimeError("plant bug")
        advance(duration_s)

    def kill() -> None:
        plant.advance = dies_once  # type: ignore[method-assign]

    return display, first, kill


def test_the_loop_reopens_the_display_of_a_board_that_went_silent() -> None:
    display, first, kill = _sim_board_that_dies_once()
    try:
        with _RunningLoop(display, retry_min_s=0.01, retry_max_s=0.05) as running:
            wait_until(lambda: running.rendering(2.0), 5.0, "the loop renders")
            kill()
            wait_until(lambda: running.loop.counters.display_reconnects >= 1, 10.0,
                       "the silent board noticed and the display reopened (before: never)")
            assert first.error is not None
            wait_until(lambda: running.rendering(3.0) and display.emulator is not None
                       and display.emulator.firmware.targets_mm.max() == 3.0, 5.0,
                       "the new board applies commands")
    finally:
        display.disconnect()


def test_a_board_that_dies_while_the_pins_are_safe_is_reopened_before_rendering_resumes() -> None:
    """No frame has come yet (the pins are safe, nothing is sent): the board's thread dies.
    Before, the loop sent nothing while safe and never asked, so the dead link stood until
    the first fresh frame's render raised (found by review); now it is reopened meanwhile."""
    display, first, kill = _sim_board_that_dies_once()
    try:
        with _RunningLoop(display, retry_min_s=0.01, retry_max_s=0.05) as running:
            wait_until(lambda: running.loop.safe_reason == "no_frames", 5.0, "the pins safe")
            kill()
            wait_until(lambda: running.loop.counters.display_reconnects >= 1, 10.0,
                       "the dead board noticed while safe, and the display reopened")
            assert first.error is not None
            assert running.loop.counters.display_errors == 1
            wait_until(lambda: running.loop.safe_reason == "no_frames", 5.0,
                       "the pins safe again on the new board")
    finally:
        display.disconnect()


def test_a_finish_on_a_broken_link_shows_no_command() -> None:
    """The last command stayed in ``pin_state`` (shown as live) when the shutdown's safe
    state raised on a broken link (found by review)."""
    display = SimCanArrayTacDisplay(keepalive_interval_s=0.02, connect_timeout_s=scaled(3.0))
    display.connect()
    slot = FrameSlot()
    loop = DisplayLoop(display, Renderer(), TactileFrameScene(), positions=lambda: GOOD,
                       platform_ok=lambda: True, frames=slot, link=SameClockLink(),
                       stale_timeout_s=10.0, max_frame_age_s=10.0)
    try:
        slot.put(_frame(1, 2.0), now_us())
        loop.tick()
        assert loop.pin_state.command is not None and loop.safe_reason is None
        display._on_link_error(OSError("receive failed"))
        loop.finish("shutdown")
        assert loop.pin_state.command is None and loop.safe_reason == "shutdown"
        # the shutdown opens no safe episode: neither an entry nor safe time
        assert loop.counters.safe_entries == {} and loop.safe_since_s is None
    finally:
        display.disconnect()


# ---------------------------------------------------------------------- board reports


def test_board_faults_and_rejections_are_decoded_counted_and_logged_once_per_episode(
        raw_link: tuple[CanArrayTacDisplay, can.BusABC],
        caplog: pytest.LogCaptureFixture) -> None:
    display, board = raw_link
    caplog.set_level(logging.WARNING, logger="local_site.display.base")
    _feed(display, board, _feedback(rejected=65_534))  # the baseline: counted from here
    assert display.stats().board_rejections == 0
    fault = fr.STATUS_SAFE_STATE | fr.STATUS_FAULT
    _feed(display, board, _feedback(fault, rejected=65_534))
    fb = display.read_feedback(scaled(1.0))
    assert fb.fault and fb.safe_state and not fb.command_rejected and not fb.safe_hold
    _feed(display, board, _feedback(fault | fr.STATUS_COMMAND_REJECTED, rejected=65_535))
    _feed(display, board, _feedback(fr.STATUS_COMMAND_REJECTED, rejected=1))  # wrapped: +2
    fb = display.read_feedback(scaled(1.0))
    assert fb.command_rejected and not fb.fault
    _feed(display, board, _feedback(fr.STATUS_SAFE_STATE | fr.STATUS_SAFE_HOLD, rejected=1))
    assert display.read_feedback(scaled(1.0)).safe_hold
    stats = display.stats()
    assert (stats.board_faults, stats.board_rejections) == (2, 3)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert sum("reports a fault" in m for m in warnings) == 1
    assert sum("rejected 1 frame(s)" in m for m in warnings) == 1
    # a second episode, after a quiet second (host arrival time), is logged again
    display._on_frame(fr.ARB_ID_FEEDBACK, _feedback(fault, rejected=4),
                      rx_us=now_us() + 2_000_000)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert sum("reports a fault" in m for m in warnings) == 2
    assert sum("rejected 3 frame(s)" in m for m in warnings) == 1
    # what the station's summary takes (dataclasses.asdict of the driver's stats)
    summary = dataclasses.asdict(display.stats())
    assert summary["board_faults"] == 3 and summary["board_rejections"] == 6


# ---------------------------------------------------------------------- review of the above


class _StallingSimDisplay(SimCanArrayTacDisplay):
    """A simulated display whose reader thread, once armed, is not scheduled for ``stall_s``
    (a loaded host starving it), or never comes back (``stall_s`` None: stuck)."""

    def __init__(self) -> None:
        super().__init__()
        self.armed = threading.Event()
        self.stalled = threading.Event()
        self.release = threading.Event()
        self.stall_s: float | None = 0.3

    def _receive_once(self, bus: can.BusABC, reader: Any) -> bool:
        if self.armed.is_set() and not self.stalled.is_set():
            self.stalled.set()
            if self.stall_s is None:
                self.release.wait(30.0)
            else:
                self.release.wait(self.stall_s)
        return super()._receive_once(bus, reader)


def test_a_starved_reader_is_late_not_a_silent_board() -> None:
    """The reader not scheduled for 300 ms while the loop commands a healthy board: judged on
    the sender's clock, the send after 200 ms raised and the loop reopened the display and
    parked its pins (found by review); judged on the reader's polls, nothing is wrong."""
    display = _StallingSimDisplay()
    display.connect()
    try:
        display.armed.set()
        wait_until(display.stalled.is_set, 2.0, "the reader's stall")
        errors = []
        for k in range(40):  # 400 ms of commands while the reader does not run
            err = _raises(functools.partial(display.send_command, 1.0 + 0.5 * (k % 2)))
            if err is not None:
                errors.append(str(err))
            display.stalled.wait(0.01)  # (set: returns at once; paces the loop)
            threading.Event().wait(0.01)
        assert errors == []
        assert display._is_healthy()
    finally:
        display.release.set()
        display.disconnect()


def test_a_reader_stuck_in_a_receive_breaks_the_link(monkeypatch: pytest.MonkeyPatch) -> None:
    import local_site.display.base as base

    monkeypatch.setattr(base, "READER_STALL_S", scaled(0.3))
    display = _StallingSimDisplay()
    display.stall_s = None
    display.connect()
    try:
        display.armed.set()
        wait_until(display.stalled.is_set, 2.0, "the reader's stall")
        wait_until(lambda: _raises(lambda: display.send_command(1.0)) is not None, 3.0,
                   "the stuck reader reported")
        err = _raises(lambda: display.send_command(1.0))
        assert err is not None and "has not come back from a receive" in str(err)
    finally:
        display.release.set()
        display.disconnect()


class _RecordingDisplay(ArrayTacDisplay):
    def __init__(self) -> None:
        super().__init__(require_feedback=False)
        self.sent: list[fr.CommandFrame] = []

    def _connect(self) -> None:
        pass

    def _disconnect(self) -> None:
        pass

    def _send_frame(self, arb_id: int, payload: bytes) -> None:
        if arb_id == fr.ARB_ID_COMMAND:
            self.sent.append(fr.decode_command(payload))


def test_backlog_feedback_made_before_the_resume_arrived_asks_for_no_second_one() -> None:
    """The reader read the trip 30 ms after the board sent it; the loop sent RESUME at once;
    the reader then read a frame the board made 25 ms after the first, before the RESUME
    reached it. Judged on the board's clock alone, it looked 20 ms past the RESUME and a
    second one went out (found by review); it arrived at once after the write, so it is
    not news."""
    display = _RecordingDisplay()
    display.connect()
    board_us = 1_000_000
    tripped = fr.STATUS_SAFE_STATE | fr.STATUS_WATCHDOG_TRIPPED
    # read now, 30 ms after the board made it: its arrival stamp says nothing of that
    display._on_frame(fr.ARB_ID_FEEDBACK, _feedback(tripped, trips=1, board_t_us=board_us))
    display.send_command(1.0)
    display._on_frame(fr.ARB_ID_FEEDBACK, _feedback(tripped, trips=1,
                                                    board_t_us=board_us + 25_000))
    display.send_command(1.5)
    assert [bool(c.flags & fr.FLAG_RESUME) for c in display.sent] == [True, False]
    assert display.stats().resumes == 1


def test_the_counters_are_totals_over_reopened_links() -> None:
    display = SimCanArrayTacDisplay()
    display.connect()
    try:
        display.send_command(1.0)
        assert display.emulator is not None
        display.emulator.firmware.commands_rejected += 5  # the board rejected 5 frames
        wait_until(lambda: display.stats().board_rejections == 5, 2.0, "the rejections")
        before = display.stats()
        display._on_link_error(OSError("receive failed"))
        display.connect()  # the loop's reopen
        after = display.stats()
        assert after.board_rejections == 5 and after.commands == before.commands
        assert after.frames_sent >= before.frames_sent
    finally:
        display.disconnect()


def test_a_rebooted_board_tripped_anew_gets_a_resume() -> None:
    """RESUME for trip 1; the board reboots quickly (under feedback_timeout_s: no reopen),
    its trip counter restarted and its clock near 0, and trips again (trip 1 again): no
    RESUME went out until its clock passed the old estimate, up to 35 min, the board
    refusing every command meanwhile (found by review)."""
    display = _RecordingDisplay()
    display.connect()
    tripped = fr.STATUS_SAFE_STATE | fr.STATUS_WATCHDOG_TRIPPED
    display._on_frame(fr.ARB_ID_FEEDBACK, _feedback(tripped, trips=1, board_t_us=1_000_000_000))
    display.send_command(1.0)  # RESUME for trip 1
    display._on_frame(fr.ARB_ID_FEEDBACK, _feedback(0, trips=1, board_t_us=1_000_010_000))
    display.send_command(1.5)
    display._on_frame(fr.ARB_ID_FEEDBACK, _feedback(tripped, trips=1, board_t_us=150_000))
    display.send_command(1.0)
    assert [bool(c.flags & fr.FLAG_RESUME) for c in display.sent] == [True, False, True]


def test_the_readers_poll_is_noted_after_the_frames_it_read() -> None:
    """Noted before the frames were handled, the poll was fresh while the feedback in the
    same read still looked old: after a stall, a busy sender saw 'no feedback for 300 ms'
    and reopened a healthy display (7 of 10 trials on serial; found by review)."""
    order: list[str] = []

    class _Bus:
        def recv(self, timeout: float) -> can.Message:
            return can.Message(arbitration_id=fr.ARB_ID_FEEDBACK, data=_feedback(), is_fd=True)

    display = CanArrayTacDisplay("order", interface="virtual")
    display._on_frame = lambda *a, **k: order.append("frame")  # type: ignore[method-assign]
    display._note_poll = lambda: order.append("poll")  # type: ignore[method-assign]
    display._receive_once(_Bus(), SimpleNamespace(stopping=False))  # type: ignore[arg-type]
    assert order == ["frame", "poll"]

    from local_site.serial_port import SerialPortReader

    order.clear()
    port = serial.serial_for_url("loop://", timeout=0.02)
    try:
        reader = SerialPortReader("loop://", name="order", thread_name="t",
                                  on_data=lambda data: order.append("data"),
                                  on_error=lambda err: None, port=port,
                                  on_poll=lambda: order.append("poll"))
        port.write(b"abc")
        reader._read_once(port, SimpleNamespace(stopping=False))  # type: ignore[arg-type]
        assert order == ["data", "poll"]
    finally:
        port.close()
