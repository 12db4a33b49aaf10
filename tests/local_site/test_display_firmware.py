"""The emulated drive-board firmware, sans-I/O, with the real ArrayTac plant."""

from __future__ import annotations

import numpy as np
import pytest

from local_site.arraytac_sim.plant import ArrayTacPlant
from local_site.display import frames as fr
from local_site.display.firmware import ArrayTacFirmware

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
