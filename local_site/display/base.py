"""The ArrayTac display device kind: one base class, backends move frames.

:class:`ArrayTacDisplay` owns validation (shape, NaN/Inf), clamping and quantisation to the
wire codes, the "unchanged pins are not re-sent" rule with its keepalive, sequence numbers,
the safe state, feedback decoding and bookkeeping; the lifecycle is
:class:`~shared.devices.base.Device`'s. A backend implements ``_connect()``,
``_disconnect()`` and ``_send_frame(arb_id, payload)``, and hands every frame it receives to
:meth:`ArrayTacDisplay._on_frame` from its reader thread.

The link's health: a backend whose reader fails reports it (:meth:`_on_link_error`), and
feedback is expected at least every ``feedback_timeout_s``; otherwise the sends raise
:class:`~shared.errors.DeviceOperationError` and ``connect()`` reopens the link
(docs/arraytac_can.md, "A broken link").

Pin order: 16 pins, row-major on a 4 x 4 grid, ``index = row * 4 + col``; ``col`` grows along
platform +x and ``row`` along +y; pin (row, col) sits at ((col - 1.5) * 1.7 mm,
(row - 1.5) * 1.7 mm) from the array centre. Arrays may be given as shape (4, 4) in that
layout, as shape (16,), or as a scalar for all pins; results are always shape (16,).
"""

from __future__ import annotations

import logging
import threading
import time
from abc import abstractmethod
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numba import njit
from numpy.typing import NDArray

from local_site.display import frames as fr
from shared.counters import add_counters
from shared.devices import Device
from shared.errors import (
    CommandExpiredError,
    ConfigError,
    DeviceInitError,
    DeviceNotConnectedError,
    DeviceOperationError,
    DeviceTimeoutError,
    InputDataError,
    MalformedMessageError,
)
from shared.timebase import monotonic_s, now_us

__all__ = [
    "FEEDBACK_TIMEOUT_S",
    "FRICTION_RANGE",
    "HEIGHT_RANGE_MM",
    "K_RANGE",
    "AppliedPinCommand",
    "ArrayTacDisplay",
    "DisplayStats",
    "PinFeedback",
    "SafeMode",
]

log = logging.getLogger(__name__)

HEIGHT_RANGE_MM = (0.0, 5.0)
K_RANGE = (0.5, 1.0)
FRICTION_RANGE = (0.0, 1.0)
SafeMode = Literal["flat", "hold"]
_SAFE_CODES = {"flat": fr.SAFE_FLAT, "hold": fr.SAFE_HOLD}
#: per layer (rows: height, k, f): range, and value = code * lsb + offset on the wire
_LOW = np.array([[HEIGHT_RANGE_MM[0]], [K_RANGE[0]], [FRICTION_RANGE[0]]])
_HIGH = np.array([[HEIGHT_RANGE_MM[1]], [K_RANGE[1]], [FRICTION_RANGE[1]]])
_CODE_LSB = np.array([[fr.HEIGHT_LSB_MM], [fr.K_LSB], [fr.F_LSB]])
_CODE_OFFSET = np.array([[0.0], [fr.K_MIN], [0.0]])
#: after a command with ``RESUME``, feedback still showing the watchdog trip is taken as news
#: (the command lost) only when the board stamped it this much later (its own clock) than
#: the board's clock at the write, at the earliest: until then the board's answer may be on
#: its way, and every further ``RESUME`` command would be one more that a freeze could hold
#: past a new trip
RESUME_RETRY_US = 20_000
#: default ``feedback_timeout_s``: the reader thread, running, saw no feedback for this long
#: (100 periods of the board's 500 Hz feedback) and the link counts as broken. Judged on the
#: reader's own polls, not on the sender's clock: a reader starved by a loaded host (0.25-1 s
#: measured here) or a stopped process is late, not a silent board (found by review: judged
#: on the sender's clock, a 250 ms starvation reopened a healthy display and parked its pins)
FEEDBACK_TIMEOUT_S = 0.2
#: a board clock this far behind the estimate of its clock at the last ``RESUME`` is a
#: rebooted board's (feedback read after the write was made after the estimate's feedback:
#: never more than the host's time between that read and the write behind it)
_BOARD_CLOCK_BACK_US = 1_000_000
#: a reader that has not come back from a receive for this long is taken for stuck (its
#: receives time out every 20-50 ms when it runs): the link counts as broken
READER_STALL_S = 3.0
#: a board fault or rejection after this long without one starts a new episode (logged)
_EPISODE_GAP_US = 1_000_000
#: the clock of the link's health: the reader thread stamps each feedback's arrival with it
#: and the sends compare it. ``time.monotonic`` itself (the clock behind
#: :func:`shared.timebase.monotonic_s`), read directly: tests that step ``monotonic_s`` to
#: play a stopped process step the loop's and the deadline's clock, not the reader's arrivals
_link_clock_s = time.monotonic

#: the shapes a layer may have as an array (a scalar is the third form)
_PIN_SHAPES = ((4, 4), (fr.N_PINS,))
_F64 = np.dtype(np.float64)


@njit(cache=True, nogil=True)
def _quantise_kernel(h: NDArray[np.float64], k: NDArray[np.float64], f: NDArray[np.float64],
                     low: NDArray[np.float64], high: NDArray[np.float64],
                     offset: NDArray[np.float64], lsb: NDArray[np.float64],
                     last: NDArray[np.uint16], has_last: bool, codes: NDArray[np.uint16],
                     applied: NDArray[np.float64]
                     ) -> tuple[bool, bool, bool]:  # pragma: no cover - compiled
    """Clamp, quantise and compare the three layers (rows h, k, f of 16 pins) in one pass:
    per value the array steps it replaced, in their order (clip to the layer's range, minus
    its offset, divided by its step, rounded half to even), about ten numpy calls a command.

    ``codes`` (3, 16) gets the wire codes, ``applied`` (3, 16) the values they stand for.
    Returns (all finite, any value clamped, codes equal to ``last``); when not all finite,
    the outputs are garbage.
    """
    clamped = False
    same = has_last
    for row in range(3):
        src = h if row == 0 else (k if row == 1 else f)
        lo, hi, off, step = low[row, 0], high[row, 0], offset[row, 0], lsb[row, 0]
        for i in range(src.shape[0]):
            v = src[i]
            if not np.isfinite(v):
                return False, False, False
            if v < lo or v > hi:
                clamped = True
            code = np.uint16(np.rint((min(max(v, lo), hi) - off) / step))
            codes[row, i] = code
            applied[row, i] = code * step + off
            if has_last and last[row, i] != code:
                same = False
    return True, clamped, same


_warmed = False


def _warm_up() -> None:
    """Run :func:`_quantise_kernel` and the command encoder once for each type of argument
    the sends use: writable and read-only layers (numba compiles at the first call of each,
    or loads its cache: about 0.5 s here). Once per process."""
    global _warmed
    if _warmed:
        return
    codes = np.zeros((3, fr.N_PINS), np.uint16)
    row = np.zeros(fr.N_PINS)
    frozen = np.zeros(fr.N_PINS)
    frozen.setflags(write=False)  # the renderer's commands are read-only (a type of its own)
    for layer in (row, frozen):
        _quantise_kernel(layer, layer, layer, _LOW, _HIGH, _CODE_OFFSET, _CODE_LSB, codes,
                         False, codes, np.empty((3, fr.N_PINS)))
    fr.encode_command(fr.CommandFrame(seq=0, flags=0, height_codes=codes[0], k_codes=codes[1],
                                      f_codes=codes[2]))
    _warmed = True


def _float_rows(height_mm: object, stiffness_k: object, friction: object
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None:
    """The three layers as 1-D float64 arrays of 16 pins when each already is a contiguous
    float64 array of shape (4, 4) or (16,), all three read-only or all writable (the
    renderer's commands, the keepalive's re-send: the types :func:`_quantise_kernel` was
    compiled for); None for anything else (scalars, lists, other dtypes, shapes or layouts,
    a mix: :meth:`ArrayTacDisplay._as_pins3`)."""
    if not (type(height_mm) is np.ndarray and type(stiffness_k) is np.ndarray
            and type(friction) is np.ndarray):
        return None
    if not (height_mm.dtype == _F64 and stiffness_k.dtype == _F64 and friction.dtype == _F64
            and height_mm.shape in _PIN_SHAPES and stiffness_k.shape in _PIN_SHAPES
            and friction.shape in _PIN_SHAPES and height_mm.flags.c_contiguous
            and stiffness_k.flags.c_contiguous and friction.flags.c_contiguous
            and height_mm.flags.writeable == stiffness_k.flags.writeable
            == friction.flags.writeable):
        return None
    return (height_mm.reshape(fr.N_PINS), stiffness_k.reshape(fr.N_PINS),
            friction.reshape(fr.N_PINS))


@dataclass(frozen=True, slots=True, eq=False)
class AppliedPinCommand:
    """The command actually applied: after clamping and quantisation to the wire codes.

    Attributes:
        height_mm: (16,) heights, multiples of 1.25 um in [0, 5] (read-only, as the other
            two layers: the display re-sends them as its keepalive).
        stiffness_k: (16,) k, multiples of 0.002 in [0.5, 1].
        friction: (16,) f, multiples of 0.004 in [0, 1].
        seq: sequence number of the frame that carried it (of the last one sent when skipped).
        clamped: True when any requested value was outside its range.
        sent: False when the frame was skipped because nothing changed.
        keepalive: True when an unchanged command was re-sent to feed the watchdog.
    """

    height_mm: np.ndarray
    stiffness_k: np.ndarray
    friction: np.ndarray
    seq: int
    clamped: bool
    sent: bool
    keepalive: bool = False


@dataclass(frozen=True, slots=True, eq=False)
class PinFeedback:
    """The board's latest report.

    Attributes:
        position_mm: (16,) measured pin positions (Hall sensor), mm.
        saturated: (16,) True where the stiffness limit is reached.
        drive_voltage_v: (16,) piezo drive voltages.
        t_us: host wall-clock arrival time, microseconds.
        board_t_us: board clock (uint32, wraps).
        seq_echo: sequence number of the last command the board applied.
        safe_state: the board is in its safe state.
        watchdog_tripped: the safe state was entered by the link-loss watchdog, and the
            board refuses commands until one carries ``RESUME`` (sent automatically).
        commands_rejected: frames the board dropped (CRC/format, or a command without
            ``RESUME`` after a watchdog trip), wrapping counter.
        watchdog_trips: watchdog firings, wrapping counter.
        safe_hold: the safe state is ``hold`` (status ``SAFE_HOLD``).
        command_rejected: the board rejected a frame since its previous feedback (status
            ``COMMAND_REJECTED``).
        fault: a plant/sensor fault since the board's previous feedback (status ``FAULT``;
            it does not latch).
    """

    position_mm: np.ndarray
    saturated: np.ndarray
    drive_voltage_v: np.ndarray
    t_us: int
    board_t_us: int
    seq_echo: int
    safe_state: bool
    watchdog_tripped: bool
    commands_rejected: int
    watchdog_trips: int
    safe_hold: bool = False
    command_rejected: bool = False
    fault: bool = False


@dataclass(frozen=True, slots=True)
class DisplayStats:
    """Counters of the command and feedback streams: totals since the driver was created,
    over all its connections (a reopened link used to start them at 0, losing the counts of
    the fault episodes that made it reopen).

    Attributes:
        commands: ``send_command`` calls accepted.
        frames_sent: command frames put on the link (including keepalives).
        skipped_unchanged: commands not sent because nothing changed.
        keepalives: unchanged commands re-sent to feed the watchdog.
        clamped: commands with at least one value clamped.
        rejected_inputs: ``send_command`` calls refused (NaN/Inf/shape).
        safe_states_sent: safe-state frames sent.
        feedback_frames: valid feedback frames received.
        bad_frames: received frames that failed to decode.
        resumes: command frames sent with ``RESUME`` (the board's watchdog latch was seen).
        board_faults: feedback frames reporting a board fault (``FAULT``: a plant/sensor
            fault since the previous feedback).
        board_rejections: frames the board rejected (the growth of its wrapping
            ``commands_rejected`` counter since the session's first feedback: bad CRC or
            format, or commands refused while its watchdog latch was set).
    """

    commands: int = 0
    frames_sent: int = 0
    skipped_unchanged: int = 0
    keepalives: int = 0
    clamped: int = 0
    rejected_inputs: int = 0
    safe_states_sent: int = 0
    feedback_frames: int = 0
    bad_frames: int = 0
    resumes: int = 0
    board_faults: int = 0
    board_rejections: int = 0


class ArrayTacDisplay(Device):
    """Base of every ArrayTac backend (CAN FD, serial, and their simulators).

    Args:
        keepalive_interval_s: an unchanged command is re-sent at least this often so the
            board's watchdog stays fed (must be well under ``watchdog_ms``).
        watchdog_ms: link-loss timeout written into every command frame; the board goes
            to ``watchdog_mode`` when no command arrives for this long.
        watchdog_mode: the board's safe state on link loss, ``flat`` or ``hold``.
        disconnect_mode: safe state sent by ``disconnect()`` (None: send none).
        connect_timeout_s: ``connect()`` waits this long for the first feedback frame.
        require_feedback: wait for feedback in ``connect()`` (a board always sends it).
        feedback_timeout_s: no feedback for this long means the link is broken (a silent
            board, a reader stalled); counted from the session's first feedback frame. A
            failed reader breaks it at once. A broken link makes ``send_command``,
            ``keepalive`` and ``safe_state`` raise :class:`DeviceOperationError` and
            ``connect()`` reopen it. Must exceed the board's feedback period with room for a
            starved reader thread (default 0.2 s: 100 periods at 500 Hz).
    """

    _seq: int
    _last_codes: np.ndarray | None
    _last_applied: np.ndarray
    _last_send_s: float
    _force_next: bool
    _feedback: PinFeedback | None
    _n_commands: int
    _n_frames: int
    _n_skipped: int
    _n_keepalives: int
    _n_clamped: int
    _n_rejected: int
    _n_safe: int
    _n_feedback: int
    _n_bad: int
    _n_resumes: int
    _n_board_faults: int
    _n_board_rejections: int
    #: the board's rejection counter in the last feedback (None before the first)
    _board_rejected: int | None
    #: host arrival (us) of the last feedback reporting a fault / new rejections
    _fault_seen_us: int
    _rejection_seen_us: int
    #: the board's clock (us, uint32) at the last ``RESUME`` write, at the earliest, and
    #: its trip counter then (None: no ``RESUME`` sent in this session)
    _resume_board_us: int | None
    _resume_trips: int
    #: host time (now_us) of the last ``RESUME`` write
    _resume_sent_us: int
    #: the counters of the connections before this one
    _carried: DisplayStats
    #: the link's reader failed (None: it runs)
    _link_error: BaseException | None
    #: ``_link_clock_s()`` at the last feedback frame and at the reader's last return from
    #: a receive (frame or timeout); None before the session's first feedback
    _feedback_s: float | None
    _polled_s: float

    def __init__(self, *, keepalive_interval_s: float = 0.02, watchdog_ms: int = 100,
                 watchdog_mode: SafeMode = "flat", disconnect_mode: SafeMode | None = "flat",
                 connect_timeout_s: float = 2.0, require_feedback: bool = True,
                 feedback_timeout_s: float = FEEDBACK_TIMEOUT_S) -> None:
        super().__init__()
        if not feedback_timeout_s > 0:
            raise ConfigError(f"feedback_timeout_s must be > 0, got {feedback_timeout_s}")
        if not 0 < watchdog_ms <= 0xFFFF:
            raise ConfigError(f"watchdog_ms must be in [1, 65535], got {watchdog_ms}")
        if not 0 < keepalive_interval_s < watchdog_ms / 1000.0:
            raise ConfigError(f"keepalive_interval_s ({keepalive_interval_s}) must be > 0 and "
                              f"shorter than the watchdog ({watchdog_ms} ms)")
        for mode in (watchdog_mode, disconnect_mode):
            if mode is not None and mode not in _SAFE_CODES:
                raise ConfigError(f"safe-state mode must be 'flat' or 'hold', got {mode!r}")
        self._keepalive_interval_s = keepalive_interval_s
        self._watchdog_ms = int(watchdog_ms)
        self._flags = fr.FLAG_WATCHDOG_HOLD if watchdog_mode == "hold" else 0
        self._disconnect_mode = disconnect_mode
        self._connect_timeout_s = connect_timeout_s
        self._require_feedback = require_feedback
        self._feedback_timeout_s = float(feedback_timeout_s)
        self._send_lock = threading.Lock()
        self._cond = threading.Condition()
        self._reset_session()

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the send path's kernels now, not in the first
        command: the display loop calls it when it is built, and :meth:`connect` at the
        latest. Not at construction: a station that only checks the display's settings (its
        loop runs in another process) never spends the time."""
        _warm_up()

    # ------------------------------------------------------------------ backend interface
    # _connect() / _disconnect(): see shared.devices.base.Device

    @abstractmethod
    def _send_frame(self, arb_id: int, payload: bytes) -> None:
        """Put one frame on the link; raise DeviceOperationError on failure."""

    # ------------------------------------------------------------------ lifecycle steps

    def _before_connect(self) -> None:
        _warm_up()
        self._reset_session()

    def _after_connect(self) -> None:
        """Wait for the board's first feedback frame (unless ``require_feedback`` is off)."""
        if not self._require_feedback:
            return
        try:
            self.read_feedback(timeout_s=self._connect_timeout_s)
        except DeviceTimeoutError as err:
            raise DeviceInitError(f"{self.name}: no feedback from the drive board within "
                                  f"{self._connect_timeout_s:.2f} s") from err

    def _is_healthy(self) -> bool:
        """False once the reader failed, ran ``feedback_timeout_s`` without feedback, or has
        not returned from a receive for :data:`READER_STALL_S`."""
        return self._link_error is None and not self._silent()

    def _silent(self) -> bool:
        """The board is silent by the reader's own polls (see :data:`FEEDBACK_TIMEOUT_S`),
        or the reader is stuck (:data:`READER_STALL_S`)."""
        polled_s = self._polled_s  # (read first: the reader writes feedback, then poll)
        feedback_s = self._feedback_s
        if feedback_s is None:  # judged from the session's first feedback frame on
            return False
        return polled_s - feedback_s > self._feedback_timeout_s or \
            _link_clock_s() - max(polled_s, feedback_s) > READER_STALL_S

    def _note_poll(self) -> None:
        """The reader came back from a receive (a frame or a timeout): called by backends
        from their reader thread."""
        self._polled_s = _link_clock_s()

    def _before_disconnect(self) -> None:
        """Send the disconnect safe state, best effort (a broken link is tried too)."""
        if self._disconnect_mode is not None:
            try:
                self._send_safe_state(self._disconnect_mode)
            except DeviceOperationError as err:
                log.warning("%s: safe state on disconnect failed: %s", self.name, err)

    def _after_disconnect(self) -> None:
        with self._cond:
            self._cond.notify_all()

    # ------------------------------------------------------------------ lifecycle

    def connect(self) -> None:
        """Open the link and (by default) wait for the board's first feedback frame.

        Raises:
            DeviceInitError: the link cannot be opened or the board stays silent.
        """
        super().connect()

    def disconnect(self) -> None:
        """Send the disconnect safe state (best effort), stop and close (idempotent)."""
        super().disconnect()

    # ------------------------------------------------------------------ commands

    def send_command(self, height_mm: np.ndarray | float, stiffness_k: np.ndarray | float = 1.0,
                     friction: np.ndarray | float = 0.0, *,
                     not_after_s: float | None = None) -> AppliedPinCommand:
        """Command the 16 pins; return what was actually applied.

        Values are clamped to height [0, 5] mm, k [0.5, 1], f [0, 1] and quantised to the
        wire resolution (1.25 um, 0.002, 0.004). A command equal (after quantisation) to the
        last one sent is not re-sent unless ``keepalive_interval_s`` has passed.

        Args:
            height_mm: pin heights, shape (4, 4), (16,) or scalar.
            stiffness_k: stiffness k, same shapes.
            friction: friction f, same shapes.
            not_after_s: a deadline on :func:`shared.timebase.monotonic_s` (the moment the
                touch this command renders becomes too old): checked right before the bytes
                are written, so a process stopped or starved since its caller's age check
                does not put old touch on the pins.

        Returns:
            The applied command (shape (16,) arrays).

        Raises:
            InputDataError: a wrong shape or a NaN/Inf value; nothing is sent.
            CommandExpiredError: ``not_after_s`` had passed; nothing is sent.
            DeviceNotConnectedError: not connected.
            DeviceOperationError: the link refused the frame, or it is broken (its reader
                failed, or no feedback for ``feedback_timeout_s``); nothing is sent, and
                ``connect()`` reopens it.
        """
        if not self._connected:
            raise DeviceNotConnectedError(f"{self.name}: send_command() before connect()")
        if self._link_error is not None or self._silent():
            raise self._broken_link_error()
        rows = _float_rows(height_mm, stiffness_k, friction)
        if rows is None:
            try:
                values = self._as_pins3(height_mm, stiffness_k, friction)
            except InputDataError:
                self._n_rejected += 1
                raise
            rows = (values[0], values[1], values[2])
        codes = np.empty((3, fr.N_PINS), np.uint16)
        applied = np.empty((3, fr.N_PINS))
        with self._send_lock:
            last = self._last_codes
            finite, clamped, same = _quantise_kernel(
                rows[0], rows[1], rows[2], _LOW, _HIGH, _CODE_OFFSET, _CODE_LSB,
                codes if last is None else last, last is not None, codes, applied)
            if not finite:
                self._n_rejected += 1
                self._as_pins3(height_mm, stiffness_k, friction)  # raises the specific error
                raise InputDataError("NaN or Inf in a pin command; nothing sent")
            # returned to the caller and kept for the keepalive's re-send: nobody may edit it
            applied.setflags(write=False)
            self._n_commands += 1
            self._n_clamped += clamped
            now_s = monotonic_s()
            unchanged = same and not self._force_next
            keepalive = unchanged and now_s - self._last_send_s >= self._keepalive_interval_s
            if unchanged and not keepalive:
                self._n_skipped += 1
                return self._applied(applied, clamped, sent=False)
            # RESUME only once the board's trip was read back (see docs/arraytac_can.md).
            # Decided *before* the deadline check: a freeze after this line carries the
            # feedback known before it into the write (a board that tripped meanwhile
            # refuses the command), and a freeze before it is caught by the deadline check.
            # (Decided after the check, a reader thread that read the trip first after the
            # freeze would let the held command through with RESUME.)
            fb = self._feedback
            resume = fb is not None and fb.watchdog_tripped and self._trip_is_news(fb)
            if not_after_s is not None:
                late_s = monotonic_s() - not_after_s
                if late_s > 0:
                    raise CommandExpiredError(f"{self.name}: pin command {late_s * 1e3:.1f} ms "
                                              "past its deadline; not sent")
            frame = fr.CommandFrame(seq=self._next_seq(),
                                    flags=(self._flags
                                           | (fr.FLAG_KEEPALIVE if keepalive else 0)
                                           | (fr.FLAG_RESUME if resume else 0)),
                                    height_codes=codes[0], k_codes=codes[1], f_codes=codes[2],
                                    watchdog_ms=self._watchdog_ms)
            self._send_frame(fr.ARB_ID_COMMAND, fr.encode_command(frame))
            self._last_codes = codes
            self._last_applied = applied
            self._last_send_s = now_s
            self._force_next = False
            self._n_frames += 1
            self._n_keepalives += keepalive
            if resume and fb is not None:
                self._n_resumes += 1
                # the board's clock now is at least its stamp on that feedback plus the
                # host time since it arrived (it was read after the board sent it)
                sent_us = self._resume_sent_us = now_us()
                self._resume_board_us = (fb.board_t_us + sent_us - fb.t_us) & 0xFFFFFFFF
                self._resume_trips = fb.watchdog_trips
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s: command seq %d keepalive=%s", self.name, frame.seq, keepalive)
            return self._applied(applied, clamped, sent=True, keepalive=keepalive)

    def keepalive(self, not_after_s: float | None = None) -> bool:
        """Re-send the last command if the keepalive interval has passed.

        Args:
            not_after_s: as for :meth:`send_command` (a keepalive re-sends old touch too).

        Returns:
            True when a frame was sent.

        Raises:
            CommandExpiredError: ``not_after_s`` had passed; nothing is sent.
            DeviceOperationError: as for :meth:`send_command` (a broken link is reported
                even when no keepalive is due).
        """
        self.check_link()
        with self._send_lock:
            last = self._last_codes
            if last is None:
                return False
            if not self._force_next and \
                    monotonic_s() - self._last_send_s < self._keepalive_interval_s:
                # not due: counted as send_command would count it, without re-quantising
                self._n_commands += 1
                self._n_skipped += 1
                return False
            values = self._last_applied
        applied = self.send_command(values[0], values[1], values[2], not_after_s=not_after_s)
        return applied.sent

    def check_link(self) -> None:
        """Raise if the link is broken, without sending anything: for a caller that holds
        the pins in their safe state and sends nothing, yet must notice a dead board (and
        reopen it) before it renders again.

        Raises:
            DeviceOperationError: the link is broken (its reader failed, or no feedback for
                ``feedback_timeout_s``); ``connect()`` reopens it.
        """
        if self._connected and (self._link_error is not None or self._silent()):
            raise self._broken_link_error()

    def safe_state(self, mode: SafeMode = "flat") -> None:
        """Put the pins in a safe state now: ``flat`` (all retracted, no vibration) or
        ``hold`` (stay where they are, no vibration). The next ``send_command`` is always
        sent, whatever it contains.

        On a broken link (reader failed, no feedback for ``feedback_timeout_s``) the frame
        is still written (the board may still hear it), then :class:`DeviceOperationError`
        says the pins' state is unknown.

        Raises:
            ConfigError: unknown mode.
            DeviceNotConnectedError: not connected.
            DeviceOperationError: the link refused the frame, or it is broken.
        """
        self._send_safe_state(mode)
        if self._link_error is not None or self._silent():
            raise self._broken_link_error("safe state sent, but ")

    def _send_safe_state(self, mode: SafeMode) -> None:
        """Write the safe-state frame (:meth:`safe_state` without the link's health)."""
        if mode not in _SAFE_CODES:
            raise ConfigError(f"safe-state mode must be 'flat' or 'hold', got {mode!r}")
        if not self._connected:
            raise DeviceNotConnectedError(f"{self.name}: safe_state() before connect()")
        with self._send_lock:
            frame = fr.SafeStateFrame(mode=_SAFE_CODES[mode], seq=self._next_seq())
            self._send_frame(fr.ARB_ID_SAFE_STATE, fr.encode_safe_state(frame))
            self._force_next = True
            # the withdrawn command is forgotten: a keepalive never sends it again
            self._last_codes = None
            self._last_applied = np.zeros((3, fr.N_PINS))
            self._n_safe += 1
        log.info("%s: safe state %s sent", self.name, mode)

    # ------------------------------------------------------------------ feedback

    def read_feedback(self, timeout_s: float = 0.1, *, newer_than_us: int | None = None) \
            -> PinFeedback:
        """The latest feedback from the board.

        Args:
            timeout_s: how long to wait when no (new enough) feedback has arrived yet.
            newer_than_us: wait for feedback that arrived after this host time.

        Raises:
            DeviceNotConnectedError: not connected.
            DeviceTimeoutError: nothing (new enough) within ``timeout_s``.
        """
        if not self._connected:
            raise DeviceNotConnectedError(f"{self.name}: read_feedback() before connect()")
        deadline = monotonic_s() + timeout_s
        with self._cond:
            while True:
                fb = self._feedback
                if fb is not None and (newer_than_us is None or fb.t_us > newer_than_us):
                    return fb
                remaining = deadline - monotonic_s()
                if remaining <= 0 or not self._connected:
                    raise DeviceTimeoutError(f"{self.name}: no feedback from the drive board "
                                             f"within {timeout_s * 1e3:.0f} ms")
                self._cond.wait(remaining)

    def latest_feedback(self) -> PinFeedback | None:
        """The newest feedback without waiting (None before the first frame)."""
        return self._feedback

    def stats(self) -> DisplayStats:
        """A snapshot of the counters (totals over every connection)."""
        session = self._session_stats()
        carried = self._carried
        return add_counters(session, carried)

    def _session_stats(self) -> DisplayStats:
        """The counters of the current connection."""
        return DisplayStats(commands=self._n_commands, frames_sent=self._n_frames,
                            skipped_unchanged=self._n_skipped, keepalives=self._n_keepalives,
                            clamped=self._n_clamped, rejected_inputs=self._n_rejected,
                            safe_states_sent=self._n_safe, feedback_frames=self._n_feedback,
                            bad_frames=self._n_bad, resumes=self._n_resumes,
                            board_faults=self._n_board_faults,
                            board_rejections=self._n_board_rejections)

    # ------------------------------------------------------------------ for backends

    def _on_frame(self, arb_id: int, payload: bytes, rx_us: int | None = None) -> None:
        """Handle one received frame (called by the backend's reader thread)."""
        if arb_id != fr.ARB_ID_FEEDBACK:
            return  # our own commands echoed, other nodes' traffic
        try:
            frame = fr.decode_feedback(payload)
        except MalformedMessageError as err:
            self._n_bad += 1
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s: bad feedback frame: %s", self.name, err)
            return
        status = frame.status
        feedback = PinFeedback(
            position_mm=frame.position_mm, saturated=frame.saturated,
            drive_voltage_v=frame.drive_voltage_v,
            t_us=now_us() if rx_us is None else rx_us, board_t_us=frame.board_t_us,
            seq_echo=frame.seq_echo, safe_state=bool(status & fr.STATUS_SAFE_STATE),
            watchdog_tripped=bool(status & fr.STATUS_WATCHDOG_TRIPPED),
            commands_rejected=frame.commands_rejected, watchdog_trips=frame.watchdog_trips,
            safe_hold=bool(status & fr.STATUS_SAFE_HOLD),
            command_rejected=bool(status & fr.STATUS_COMMAND_REJECTED),
            fault=bool(status & fr.STATUS_FAULT))
        with self._cond:
            if feedback.safe_state:
                self._force_next = True  # the board is parked: the next command must go out
            self._feedback = feedback
            self._feedback_s = self._polled_s = _link_clock_s()
            self._n_feedback += 1
            self._count_board_errors(feedback)
            self._cond.notify_all()

    def _count_board_errors(self, fb: PinFeedback) -> None:
        """Count the board's faults and newly rejected frames; log the first of each episode
        (one after ``_EPISODE_GAP_US`` without any)."""
        last, self._board_rejected = self._board_rejected, fb.commands_rejected
        rejected = 0 if last is None else (fb.commands_rejected - last) & 0xFFFF
        if rejected:
            self._n_board_rejections += rejected
            if fb.t_us - self._rejection_seen_us > _EPISODE_GAP_US:
                log.warning("%s: the board rejected %d frame(s) (bad CRC or format, or "
                            "commands refused while its watchdog latch was set); further "
                            "ones are counted in board_rejections", self.name, rejected)
            self._rejection_seen_us = fb.t_us
        if fb.fault:
            self._n_board_faults += 1
            if fb.t_us - self._fault_seen_us > _EPISODE_GAP_US:
                log.warning("%s: the board reports a fault (plant/sensor); further ones are "
                            "counted in board_faults", self.name)
            self._fault_seen_us = fb.t_us

    def _on_link_error(self, err: BaseException) -> None:
        """The backend's reader failed (called from it before it ends): the link counts as
        broken until ``connect()`` reopens it."""
        log.error("%s: the link's reader failed: %s; the display reports a broken link "
                  "until it is reopened", self.name, err)
        with self._cond:
            self._link_error = err
            self._cond.notify_all()

    def _broken_link_error(self, prefix: str = "") -> DeviceOperationError:
        """The error for a broken link (the reader failed, or the board went silent)."""
        err = self._link_error
        if err is not None:
            return DeviceOperationError(f"{self.name}: {prefix}the link's reader failed "
                                        f"({err}); reopen the display")
        feedback_s = self._feedback_s or 0.0
        if _link_clock_s() - max(self._polled_s, feedback_s) > READER_STALL_S:
            return DeviceOperationError(
                f"{self.name}: {prefix}the link's reader has not come back from a receive "
                f"for {(_link_clock_s() - self._polled_s) * 1e3:.0f} ms (stuck); reopen the "
                "display")
        return DeviceOperationError(
            f"{self.name}: {prefix}no feedback from the drive board for "
            f"{(self._polled_s - feedback_s) * 1e3:.0f} ms of the reader's polling "
            f"(feedback_timeout_s {self._feedback_timeout_s * 1e3:.0f} ms); reopen the "
            "display")

    def _trip_is_news(self, fb: PinFeedback) -> bool:
        """Whether feedback showing a watchdog trip asks for a ``RESUME``: none was sent in
        this session, the trip is a new one (the board's trip counter moved: also a
        rebooted board), or that ``RESUME`` was lost: the feedback arrived
        ``RESUME_RETRY_US`` after its write *and* the board stamped it that much after its
        clock at the write (estimated from the newest feedback then). Either test alone sent
        a second ``RESUME`` on feedback the board made before the first reached it: by
        arrival, when it was delivered late (a backlog); by the board's clock, when the
        reader had read the newest feedback late (the estimate is low by that much, found by
        review)."""
        since = self._resume_board_us
        if since is None or fb.watchdog_trips != self._resume_trips:
            return True
        # wrap-aware difference of two uint32 clocks, as a signed 32-bit number
        elapsed_us = ((fb.board_t_us - since + 0x80000000) & 0xFFFFFFFF) - 0x80000000
        if elapsed_us < -_BOARD_CLOCK_BACK_US:
            return True  # the board's clock went back: a rebooted board, tripped anew with
            # its trip counter restarted at the same count (it never got a RESUME: review)
        if fb.t_us - self._resume_sent_us <= RESUME_RETRY_US:
            return False
        return elapsed_us > RESUME_RETRY_US

    def _reset_session(self) -> None:
        # the counters are totals: a new connection carries the previous ones' over
        self._carried = self.stats() if hasattr(self, "_n_commands") else DisplayStats()
        self._seq = 0
        self._last_codes = None
        self._last_applied = np.zeros((3, fr.N_PINS))
        self._last_send_s = 0.0
        self._force_next = False
        self._feedback = None
        self._n_commands = self._n_frames = self._n_skipped = self._n_keepalives = 0
        self._n_clamped = self._n_rejected = self._n_safe = self._n_feedback = self._n_bad = 0
        self._n_resumes = self._n_board_faults = self._n_board_rejections = 0
        self._board_rejected = None
        self._fault_seen_us = self._rejection_seen_us = -(1 << 62)
        self._resume_board_us = None
        self._resume_trips = 0
        self._resume_sent_us = 0
        self._link_error = None
        # armed by the first feedback frame (connect() waits for it unless require_feedback
        # is off)
        self._feedback_s = None
        self._polled_s = _link_clock_s()

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFFFF
        return self._seq

    def _applied(self, values: np.ndarray, clamped: bool, *, sent: bool,
                 keepalive: bool = False) -> AppliedPinCommand:
        """``values``: (3, 16) applied height, k and friction."""
        return AppliedPinCommand(height_mm=values[0], stiffness_k=values[1], friction=values[2],
                                 seq=self._seq, clamped=clamped, sent=sent, keepalive=keepalive)

    def _as_pins3(self, height_mm: np.ndarray | float, stiffness_k: np.ndarray | float,
                  friction: np.ndarray | float) -> np.ndarray:
        """The three layers as one (3, 16) float array (rows: height, k, f), validated."""
        out = np.empty((3, fr.N_PINS))
        for row, (name, value) in enumerate((("height_mm", height_mm),
                                             ("stiffness_k", stiffness_k),
                                             ("friction", friction))):
            try:
                arr = np.asarray(value, dtype=float)
            except (TypeError, ValueError) as err:
                raise InputDataError(f"{name}: not numeric: {err}") from err
            if arr.ndim and arr.shape not in ((4, 4), (fr.N_PINS,)):
                raise InputDataError(f"{name}: shape {arr.shape}, expected (4, 4), (16,) or "
                                     "scalar")
            out[row] = arr.reshape(fr.N_PINS) if arr.ndim else arr
        if not np.isfinite(out).all():
            row = int(np.flatnonzero(~np.isfinite(out).all(axis=1))[0])
            name = ("height_mm", "stiffness_k", "friction")[row]
            raise InputDataError(f"{name}: NaN or Inf at pin(s) "
                                 f"{np.flatnonzero(~np.isfinite(out[row])).tolist()}; "
                                 "nothing sent")
        return out
