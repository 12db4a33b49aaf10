"""The ArrayTac drive-board firmware, emulated: sans-I/O frames in, frames out.

:class:`ArrayTacFirmware` is what the MCU does with the link: decode ``COMMAND`` and
``SAFE_STATE`` frames (rejecting and counting bad ones), hand targets to the physics plant,
run the link-loss watchdog, and report ``FEEDBACK`` at a fixed rate. A watchdog trip
latches: until a ``COMMAND`` carrying ``FLAG_RESUME`` arrives, commands are refused (counted
as rejected), so a command held in a host that froze (SIGSTOP, a VM pause) between its own
age check and the write cannot undo the park when the host wakes; the host sets the flag
only once it has read the trip in the feedback (docs/arraytac_can.md). Time is passed in
explicitly (``now_s``), so it is tested without threads; :mod:`local_site.display.emulator`
runs it in real time on a CAN or serial link.

The plant is :class:`local_site.arraytac_sim.plant.ArrayTacPlant` (any object with the same
interface, :class:`PlantLike`, will do).
"""

from __future__ import annotations

import logging
from typing import Any, Protocol

import numpy as np

from local_site.display import frames as fr
from shared.errors import ConfigError, DeviceInitError, MalformedMessageError

__all__ = ["ArrayTacFirmware", "PlantLike", "make_plant"]

log = logging.getLogger(__name__)


class PlantLike(Protocol):
    """What the firmware needs from the physics plant (16 units)."""

    def set_targets(self, height_mm: np.ndarray, stiffness_k: np.ndarray,
                    friction: np.ndarray) -> None: ...

    def set_finger_force(self, force_n: float | np.ndarray) -> None: ...

    def advance(self, duration_s: float) -> None: ...

    def reset(self) -> None: ...

    @property
    def position_mm(self) -> np.ndarray: ...

    @property
    def saturated(self) -> np.ndarray: ...

    @property
    def drive_voltage_v(self) -> np.ndarray: ...


def make_plant(**options: Any) -> PlantLike:
    """Build the simulator's plant (imported lazily: it is the heavy part).

    Raises:
        DeviceInitError: the plant module is missing or rejects the options.
    """
    try:
        from local_site.arraytac_sim.plant import ArrayTacPlant
    except ImportError as err:
        raise DeviceInitError(f"ArrayTac plant unavailable: {err}") from err
    try:
        return ArrayTacPlant(**options)
    except (TypeError, ValueError, ConfigError) as err:
        raise DeviceInitError(f"ArrayTac plant rejected options {options}: {err}") from err


class ArrayTacFirmware:
    """Emulated drive-board firmware around a plant.

    Args:
        plant: the 16-unit physics plant.
        default_watchdog_ms: watchdog timeout when a command frame carries 0.
        feedback_period_s: feedback frame period (0.002 s = 500 Hz).
        max_step_s: longest plant advance per call; a longer gap (the thread was starved)
            is not caught up, it is counted in ``overruns`` (the plant falls behind the wall).
    """

    def __init__(self, plant: PlantLike, *, default_watchdog_ms: int = 100,
                 feedback_period_s: float = 0.002, max_step_s: float = 0.02) -> None:
        self.plant = plant
        self._default_watchdog_s = default_watchdog_ms / 1000.0
        self._feedback_period_s = feedback_period_s
        self._max_step_s = max_step_s
        self._t0_s: float | None = None
        self._last_s = 0.0
        self._next_feedback_s = 0.0
        self._last_command_s: float | None = None
        self._watchdog_s = self._default_watchdog_s
        self._watchdog_hold = False
        self.k = np.ones(fr.N_PINS)
        self.targets_mm = np.zeros(fr.N_PINS)
        self.friction = np.zeros(fr.N_PINS)
        #: targets set since the plant last advanced (handed over when it next does)
        self._targets_pending = False
        self.safe_state = False
        self.safe_hold = False
        self.watchdog_tripped = False
        self.seq_echo = 0
        self.commands_applied = 0
        self.commands_rejected = 0
        #: of ``commands_rejected``: valid commands refused because the watchdog latch was set
        self.commands_refused_latched = 0
        self.watchdog_trips = 0
        self.faults = 0
        self.overruns = 0
        self._rejected_since_feedback = False
        self._fault_since_feedback = False

    # ------------------------------------------------------------------ link side

    def receive(self, arb_id: int, payload: bytes, now_s: float) -> None:
        """Handle one frame from the host at time ``now_s`` (seconds, any monotonic origin).

        Like the MCU, which latches a new command at its next control period, the plant sees
        the new targets from the next :meth:`poll` on (latch delay <= one emulator tick): they
        are handed to the plant once, when it next advances, so of several commands within
        one tick only the last costs a plant update (each is still decoded, checked and
        counted).
        """
        if self._t0_s is None:
            self._advance_to(now_s)
        try:
            if arb_id == fr.ARB_ID_COMMAND:
                self._apply_command(fr.decode_command(payload), now_s)
            elif arb_id == fr.ARB_ID_SAFE_STATE:
                frame = fr.decode_safe_state(payload)
                self.seq_echo = frame.seq
                self._enter_safe(hold=frame.mode == fr.SAFE_HOLD, by_watchdog=False)
                self._last_command_s = None  # parked on purpose: watchdog disarmed
        except MalformedMessageError as err:
            self.commands_rejected += 1
            self._rejected_since_feedback = True
            if log.isEnabledFor(logging.DEBUG):
                log.debug("firmware rejected frame 0x%03x: %s", arb_id, err)

    def poll(self, now_s: float) -> list[tuple[int, bytes]]:
        """Advance to ``now_s``, run the watchdog, return the frames to send (feedback)."""
        self._advance_to(now_s)
        self.run_watchdog(now_s)
        if now_s < self._next_feedback_s:
            return []
        self._next_feedback_s = max(self._next_feedback_s + self._feedback_period_s,
                                    now_s - self._feedback_period_s)
        return [(fr.ARB_ID_FEEDBACK, fr.encode_feedback(self.feedback_frame(now_s)))]

    @property
    def watchdog_s(self) -> float:
        """The link-loss watchdog's timeout in force (set by the commands)."""
        return self._watchdog_s

    def run_watchdog(self, now_s: float) -> bool:
        """Trip the link-loss watchdog if no command came for longer than its timeout.

        :meth:`poll` runs it. A caller that hands over frames which queued while it was late
        (the emulator's thread after a late tick) runs it first, at the time it handles
        them: a real MCU's timer fires on time whatever waits in the receive FIFO, so a
        command that arrives after the timeout (a frozen host's held one) finds the latch
        set and is refused, not applied in place of the trip.

        Returns:
            True when it tripped now.
        """
        if self._last_command_s is None or self.safe_state \
                or now_s - self._last_command_s <= self._watchdog_s:
            return False
        self.watchdog_trips += 1
        log.info("firmware watchdog: no command for %.0f ms -> safe state (%s)",
                 (now_s - self._last_command_s) * 1e3,
                 "hold" if self._watchdog_hold else "flat")
        self._enter_safe(hold=self._watchdog_hold, by_watchdog=True)
        return True

    def feedback_frame(self, now_s: float) -> fr.FeedbackFrame:
        """The feedback frame describing the state at ``now_s``."""
        position = np.asarray(self.plant.position_mm, dtype=float)
        voltage = np.asarray(self.plant.drive_voltage_v, dtype=float)
        saturated = np.asarray(self.plant.saturated, dtype=bool)
        if not (np.isfinite(position).all() and np.isfinite(voltage).all()):
            self._fault_since_feedback = True  # never put NaN on the wire: report 0 + fault
            position = np.nan_to_num(position, nan=0.0, posinf=0.0, neginf=0.0)
            voltage = np.nan_to_num(voltage, nan=0.0, posinf=0.0, neginf=0.0)
        status = ((fr.STATUS_SAFE_STATE if self.safe_state else 0)
                  | (fr.STATUS_WATCHDOG_TRIPPED if self.watchdog_tripped else 0)
                  | (fr.STATUS_SAFE_HOLD if self.safe_state and self.safe_hold else 0)
                  | (fr.STATUS_COMMAND_REJECTED if self._rejected_since_feedback else 0)
                  | (fr.STATUS_FAULT if self._fault_since_feedback else 0))
        self._rejected_since_feedback = self._fault_since_feedback = False
        board_t_us = round((now_s - (self._t0_s if self._t0_s is not None else now_s)) * 1e6)
        return fr.FeedbackFrame(
            status=status, seq_echo=self.seq_echo, board_t_us=board_t_us & 0xFFFFFFFF,
            position_codes=_codes(position, fr.HEIGHT_LSB_MM),
            saturated_mask=int(saturated @ _PIN_BITS),
            commands_rejected=self.commands_rejected & 0xFFFF,
            watchdog_trips=self.watchdog_trips & 0xFFFF,
            voltage_codes=_codes(voltage, fr.VOLTAGE_LSB_V))

    # ------------------------------------------------------------------ internals

    def _apply_command(self, frame: fr.CommandFrame, now_s: float) -> None:
        if self.watchdog_tripped and not frame.flags & fr.FLAG_RESUME:
            # latched: this command may have waited in a frozen host; the pins stay parked
            self.commands_rejected += 1
            self.commands_refused_latched += 1
            self._rejected_since_feedback = True
            if log.isEnabledFor(logging.DEBUG):
                log.debug("firmware refused command seq %d: watchdog latch, no RESUME",
                          frame.seq)
            return
        self.targets_mm = frame.height_mm
        self.k = frame.stiffness_k
        self.friction = frame.friction
        self._targets_pending = True
        self.seq_echo = frame.seq
        self._last_command_s = now_s
        self._watchdog_s = (frame.watchdog_ms / 1000.0) if frame.watchdog_ms \
            else self._default_watchdog_s
        self._watchdog_hold = bool(frame.flags & fr.FLAG_WATCHDOG_HOLD)
        self.safe_state = self.watchdog_tripped = False
        self.commands_applied += 1

    def _enter_safe(self, *, hold: bool, by_watchdog: bool) -> None:
        if hold:
            self.targets_mm = np.clip(np.nan_to_num(np.asarray(self.plant.position_mm,
                                                               dtype=float)), 0.0, 5.0)
        else:
            self.targets_mm = np.zeros(fr.N_PINS)
        self.friction = np.zeros(fr.N_PINS)
        self._targets_pending = True
        self.safe_state = True
        self.safe_hold = hold
        # the latch outlives a later explicit safe state or fault: only RESUME clears it
        self.watchdog_tripped = by_watchdog or self.watchdog_tripped

    def _advance_to(self, now_s: float) -> None:
        if self._t0_s is None:
            self._t0_s = self._last_s = self._next_feedback_s = now_s
            return
        step_s = now_s - self._last_s
        if step_s <= 0:
            return
        if step_s > self._max_step_s:
            self.overruns += 1
            step_s = self._max_step_s
        if self._targets_pending:
            self.plant.set_targets(self.targets_mm, self.k, self.friction)
            self._targets_pending = False
        self.plant.advance(step_s)
        self._last_s = now_s
        if not (np.all(np.isfinite(self.plant.position_mm))
                and np.all(np.isfinite(self.plant.drive_voltage_v))):
            # degrade safely: never report or act on NaN; restart the plant, park the pins
            self.faults += 1
            self._fault_since_feedback = True
            log.error("firmware: plant produced non-finite state; reset and safe state (flat)")
            self.plant.reset()
            self._enter_safe(hold=False, by_watchdog=False)


#: bit i of the saturation mask is pin i
_PIN_BITS = 1 << np.arange(fr.N_PINS, dtype=np.int64)


def _codes(values: np.ndarray, lsb: float) -> np.ndarray:
    """Quantise to 12-bit codes, clipping into range (NaN never reaches here)."""
    return np.clip(np.rint(values / lsb), 0, 0xFFF).astype(np.uint16)
