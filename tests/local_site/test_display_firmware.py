"""The emulated drive-board firmware, sans-I/O, with the real ArrayTac plant; and its
real-time loop (:class:`FirmwareEmulator`) on a scripted link: a tick the thread reaches late
runs the watchdog before the frames that queued meanwhile, and a flooding host cannot hold
off the feedback."""

from __future__ import annotations

import collections
import threading
import time

import numpy as np
import pytest

from local_site.arraytac_sim.plant import ArrayTacPlant
from local_site.display import frames as fr
from local_site.display.emulator import FirmwareEmulator, FirmwareTransport
from local_site.display.firmware import ArrayTacFirmware
from shared.errors import ConfigError
from tests.support import wait_until

TICK_S = 0.002


def _command(height_mm: float, seq: int, *, flags: int = 0, watchdog_ms: int = 100,
             friction: float = 0.0) -> bytes:
    return fr.encode_command(fr.CommandFrame(
        seq=seq, flags=flags, height_codes=np.full(16, round(height_mm / fr.HEIGHT_LSB_MM),
                                                   np.uint16),
        k_codes=np.full(16, 250, np.uint16),
        f_codes=np.full(16, round(friction / fr.F_LSB), np.uint16), watchdog_ms=watchdog_ms))


def _run(fw: ArrayTacFirmware, t0: float, duration_s: float, *,
         keepalive: bytes | None = None) -> tuple[float, list[fr.FeedbackFrame]]:
    out = []
    t = t0
    for _ in range(round(duration_s / TICK_S)):
        t += TICK_S
        if keepalive is not None:
            fw.receive(fr.ARB_ID_COMMAND, keepalive, t)
        out += [fr.decode_feedback(p) for _, p in fw.poll(t)]
    return t, out


@pytest.fixture
def firmware() -> ArrayTacFirmware:
    fw = ArrayTacFirmware(ArrayTacPlant(), feedback_period_s=0.002)
    fw.poll(0.0)
    return fw


def test_command_drives_the_pins_and_feedback_reports_them(firmware: ArrayTacFirmware) -> None:
    cmd = _command(3.0, seq=5)
    firmware.receive(fr.ARB_ID_COMMAND, cmd, 0.0)
    _t, feedback = _run(firmware, 0.0, 0.08, keepalive=cmd)
    assert len(feedback) == pytest.approx(0.08 / 0.002, abs=2)  # 500 Hz
    last = feedback[-1]
    np.testing.assert_allclose(last.position_mm, 3.0, atol=0.02)
    assert last.seq_echo == 5 and last.status & fr.STATUS_SAFE_STATE == 0
    times = [f.board_t_us for f in feedback]
    assert np.all(np.diff(times) > 0)


def test_watchdog_parks_the_pins_flat(firmware: ArrayTacFirmware) -> None:
    firmware.receive(fr.ARB_ID_COMMAND, _command(3.0, 1, watchdog_ms=50), 0.0)
    t, fb = _run(firmware, 0.0, 0.04)            # 40 ms silent: still commanded
    assert not fb[-1].status & fr.STATUS_SAFE_STATE
    t, fb = _run(firmware, t, 0.2)               # link lost: safe state, pins retract
    assert fb[-1].status & fr.STATUS_SAFE_STATE and fb[-1].status & fr.STATUS_WATCHDOG_TRIPPED
    assert firmware.watchdog_trips == 1 and fb[-1].watchdog_trips == 1
    np.testing.assert_allclose(fb[-1].position_mm, 0.0, atol=0.05)
    # link back: a command sent without RESUME may have waited in a frozen host: refused
    firmware.receive(fr.ARB_ID_COMMAND, _command(2.0, 2, watchdog_ms=50), t)
    t, fb = _run(firmware, t, 0.004)
    assert fb[-1].status & fr.STATUS_SAFE_STATE and fb[-1].status & fr.STATUS_WATCHDOG_TRIPPED
    assert fb[0].status & fr.STATUS_COMMAND_REJECTED and fb[-1].seq_echo == 1
    assert firmware.commands_refused_latched == firmware.commands_rejected == 1
    # the host has read the trip: its next command carries RESUME and leaves the latch
    firmware.receive(fr.ARB_ID_COMMAND,
                     _command(2.0, 3, flags=fr.FLAG_RESUME, watchdog_ms=50), t)
    t, fb = _run(firmware, t, 0.004)
    assert not fb[-1].status & (fr.STATUS_SAFE_STATE | fr.STATUS_WATCHDOG_TRIPPED)
    assert fb[-1].seq_echo == 3
    # RESUME on a board that is not latched changes nothing
    firmware.receive(fr.ARB_ID_COMMAND,
                     _command(2.0, 4, flags=fr.FLAG_RESUME, watchdog_ms=50), t)
    assert firmware.seq_echo == 4 and firmware.commands_rejected == 1


def test_the_watchdog_latch_outlives_an_explicit_safe_state(firmware: ArrayTacFirmware) -> None:
    firmware.receive(fr.ARB_ID_COMMAND, _command(3.0, 1, watchdog_ms=50), 0.0)
    t, fb = _run(firmware, 0.0, 0.1)
    assert firmware.watchdog_tripped
    firmware.receive(fr.ARB_ID_SAFE_STATE,
                     fr.encode_safe_state(fr.SafeStateFrame(fr.SAFE_HOLD, 2)), t)
    firmware.receive(fr.ARB_ID_COMMAND, _command(3.0, 3, watchdog_ms=50), t)
    t, fb = _run(firmware, t, 0.01)
    assert fb[-1].status & fr.STATUS_SAFE_STATE and fb[-1].status & fr.STATUS_WATCHDOG_TRIPPED
    assert fb[-1].seq_echo == 2 and firmware.commands_refused_latched == 1
    firmware.receive(fr.ARB_ID_COMMAND,
                     _command(3.0, 4, flags=fr.FLAG_RESUME, watchdog_ms=50), t)
    assert not firmware.safe_state and not firmware.watchdog_tripped


def test_watchdog_hold_keeps_the_pins_and_stops_vibration(firmware: ArrayTacFirmware) -> None:
    cmd = _command(3.0, 1, flags=fr.FLAG_WATCHDOG_HOLD, watchdog_ms=50, friction=0.5)
    firmware.receive(fr.ARB_ID_COMMAND, cmd, 0.0)
    t, _ = _run(firmware, 0.0, 0.1, keepalive=cmd)
    t, fb = _run(firmware, t, 0.3)
    assert fb[-1].status & fr.STATUS_SAFE_HOLD
    assert np.all(firmware.friction == 0.0)
    np.testing.assert_allclose(fb[-1].position_mm, 3.0, atol=0.1)


def test_safe_state_frame_and_bad_frames(firmware: ArrayTacFirmware) -> None:
    firmware.receive(fr.ARB_ID_COMMAND, _command(4.0, 1), 0.0)
    t, _ = _run(firmware, 0.0, 0.05, keepalive=_command(4.0, 1))
    firmware.receive(fr.ARB_ID_SAFE_STATE,
                     fr.encode_safe_state(fr.SafeStateFrame(fr.SAFE_FLAT, 9)), t)
    bad = bytearray(_command(1.0, 10))
    bad[5] ^= 0x40
    firmware.receive(fr.ARB_ID_COMMAND, bytes(bad), t)      # CRC error: rejected
    firmware.receive(fr.ARB_ID_COMMAND, b"\x11" * 12, t)   # wrong size: rejected
    t, fb = _run(firmware, t, 0.3)
    assert firmware.commands_rejected == 2
    assert fb[0].status & fr.STATUS_COMMAND_REJECTED
    assert fb[-1].status & fr.STATUS_SAFE_STATE and not fb[-1].status & fr.STATUS_WATCHDOG_TRIPPED
    assert fb[-1].seq_echo == 9
    np.testing.assert_allclose(fb[-1].position_mm, 0.0, atol=0.05)
    assert firmware.watchdog_trips == 0  # parked on purpose: the watchdog is disarmed


def test_non_finite_plant_state_degrades_safely() -> None:
    class BrokenPlant(ArrayTacPlant):
        broken = False

        @property
        def position_mm(self) -> np.ndarray:
            p = super().position_mm
            return np.full_like(p, np.nan) if self.broken else p

    plant = BrokenPlant()
    fw = ArrayTacFirmware(plant)
    fw.poll(0.0)
    fw.receive(fr.ARB_ID_COMMAND, _command(2.0, 1), 0.0)
    plant.broken = True
    frames = fw.poll(0.002)
    plant.broken = False
    frames += fw.poll(0.004) + fw.poll(0.006)
    feedback = [fr.decode_feedback(p) for _, p in frames]
    assert fw.faults >= 1 and fw.safe_state
    assert feedback[0].status & fr.STATUS_FAULT
    assert all(np.all(np.isfinite(fb.position_mm)) for fb in feedback)
    np.testing.assert_array_equal(fw.targets_mm, 0.0)


# ------------------------------------------------------------------ the real-time loop


class _ScriptedLink(FirmwareTransport):
    """The board's end of a link the test drives: frames to deliver, feedback received."""

    def __init__(self) -> None:
        self.inbox: collections.deque[tuple[int, bytes]] = collections.deque()
        self.feedback: list[fr.FeedbackFrame] = []
        self.closed = threading.Event()

    def recv(self, timeout_s: float) -> tuple[int, bytes] | None:
        return self.inbox.popleft() if self.inbox else None

    def send(self, arb_id: int, payload: bytes) -> None:
        self.feedback.append(fr.decode_feedback(payload))

    def close(self) -> None:
        self.closed.set()


def test_a_late_tick_runs_the_watchdog_before_the_frames_that_queued_meanwhile() -> None:
    """The board's thread stalls 150 ms (a starved process) right after a 100 ms-watchdog
    command, while a frozen host's held command (no RESUME) queues: a real board's timer
    trips at 100 ms and its latch refuses the held command. The emulator applied the queued
    frame first, then ran the watchdog: the held command replaced the trip."""
    stall_s = 0.15

    class StallingLink(_ScriptedLink):
        stalled = False

        def send(self, arb_id: int, payload: bytes) -> None:
            super().send(arb_id, payload)
            if not self.stalled and self.feedback[-1].seq_echo == 1:
                self.stalled = True
                time.sleep(stall_s)  # the stall itself (the thread is off the CPU)
                self.inbox.append((fr.ARB_ID_COMMAND, _command(4.5, 2, watchdog_ms=100)))

    link = StallingLink()
    link.inbox.append((fr.ARB_ID_COMMAND, _command(2.0, 1, watchdog_ms=100)))
    fw = ArrayTacFirmware(ArrayTacPlant())
    with FirmwareEmulator(fw, link) as emulator:
        wait_until(lambda: link.stalled and not link.inbox and len(link.feedback) >= 3, 5.0,
                   "feedback after the stall")
    assert emulator.late_tick_trips == 1  # told apart from a trip a real board would make
    after = link.feedback[1]  # the first feedback of the late tick
    assert after.status & fr.STATUS_WATCHDOG_TRIPPED and after.status & fr.STATUS_SAFE_STATE
    assert after.seq_echo == 1 and after.status & fr.STATUS_COMMAND_REJECTED
    assert fw.watchdog_trips == 1 and fw.commands_applied == 1
    assert fw.commands_refused_latched == 1
    np.testing.assert_array_equal(fw.targets_mm, 0.0)  # parked flat, not at 4.5 mm
    assert link.closed.is_set()


def test_a_host_flooding_the_link_does_not_hold_off_the_feedback() -> None:
    """Frames are taken from the link up to a bound per tick: a host that sends faster than
    the board decodes once kept the loop in its first tick (no feedback, no watchdog)."""
    flooding = threading.Event()
    flooding.set()
    cmd = (fr.ARB_ID_COMMAND, _command(1.0, 7))

    class FloodLink(_ScriptedLink):
        def recv(self, timeout_s: float) -> tuple[int, bytes] | None:
            return cmd if flooding.is_set() else None

    link = FloodLink()
    fw = ArrayTacFirmware(ArrayTacPlant())
    emulator = FirmwareEmulator(fw, link)
    try:
        emulator.start()
        wait_until(lambda: len(link.feedback) >= 5, 5.0, "feedback during the flood")
    finally:
        flooding.clear()  # (unfixed, the thread leaves its first tick only now)
        emulator.stop()
    assert emulator.error is None and link.closed.is_set()
    assert all(f.seq_echo == 7 and not f.status & fr.STATUS_SAFE_STATE for f in link.feedback)
    assert fw.commands_applied >= 5 and fw.watchdog_trips == 0
    with pytest.raises(ConfigError, match="max_frames_per_tick"):
        FirmwareEmulator(fw, link, max_frames_per_tick=0)

