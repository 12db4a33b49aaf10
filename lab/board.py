"""The emulated ArrayTac drive board as a process of its own (``teletouch board``).

:func:`run_board` runs :class:`~local_site.display.firmware.ArrayTacFirmware` (with the real
plant) in :class:`~local_site.display.emulator.FirmwareEmulator` behind a
:class:`~local_site.display.emulator.TcpFirmwareTransport`: the local station reaches it with
``--display socket://127.0.0.1:PORT``, its ordinary serial driver, no product change. Frozen,
killed or restarted, the station cannot move this board's pins: only the frames it sent and
the firmware's own link-loss watchdog (configured by the station in every command frame,
``watchdog_ms`` / ``watchdog_mode``) do, exactly as with the in-process simulator.

What the pins do is written to an event file, one line per event, stamped with
``time.monotonic()`` (the host's clock, shared with the fault suite's probes):

* ``S mono reason`` - the pins went to the safe state (``watchdog``: no command for the
  watchdog timeout; ``safe_state_frame``: the host asked; ``fault``: the plant failed);
* ``U mono`` - they left it (a command was applied);
* ``R mono seq`` - a command frame was applied (``seq``: the frame's sequence number);
* ``X mono`` - a valid command was refused: the watchdog had tripped and the command did not
  carry ``RESUME`` (one that waited in a frozen station, or sent before it read the trip).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from local_site.display.emulator import FirmwareEmulator, TcpFirmwareTransport
from local_site.display.firmware import ArrayTacFirmware, PlantLike, make_plant

__all__ = ["BoardEvents", "RecordingFirmware", "run_board"]

log = logging.getLogger(__name__)

#: ``R`` lines are flushed at least this often (``S`` / ``U`` lines at once)
FLUSH_PERIOD_S = 0.02


class BoardEvents:
    """The event file (see the module docstring); written from the emulator's thread only.

    Args:
        path: the file (appended to; None: no file, events are only counted).
    """

    def __init__(self, path: Path | None) -> None:
        self._out: TextIO | None = open(path, "a") if path is not None else None  # noqa: SIM115
        self._lock = threading.Lock()
        self._last_flush = 0.0
        self.counts = Counter({"S": 0, "U": 0, "R": 0, "X": 0})

    def write(self, kind: str, *fields: object) -> None:
        """One line ``kind mono fields...``, stamped now."""
        now = time.monotonic()
        self.counts[kind] += 1
        with self._lock:
            if self._out is None:
                return
            self._out.write(" ".join([kind, f"{now:.6f}", *map(str, fields)]) + "\n")
            if kind != "R" or now - self._last_flush >= FLUSH_PERIOD_S:
                self._out.flush()
                self._last_flush = now

    def flush(self) -> None:
        """Write out what is buffered (``R`` lines wait up to ``FLUSH_PERIOD_S`` otherwise)."""
        with self._lock:
            if self._out is not None:
                self._out.flush()

    def close(self) -> None:
        """Flush and close (idempotent)."""
        with self._lock:
            if self._out is not None:
                self._out.close()
                self._out = None


class RecordingFirmware(ArrayTacFirmware):
    """The firmware, unchanged, with each change of the pins' state written to ``events``.

    Args:
        plant: the physics plant.
        events: where the events go.
        **kwargs: passed to :class:`ArrayTacFirmware`.
    """

    def __init__(self, plant: PlantLike, events: BoardEvents, **kwargs: Any) -> None:
        super().__init__(plant, **kwargs)
        self.events = events

    def receive(self, arb_id: int, payload: bytes, now_s: float) -> None:
        was_safe, applied, faults = self.safe_state, self.commands_applied, self.faults
        refused = self.commands_refused_latched
        super().receive(arb_id, payload, now_s)
        if self.commands_refused_latched > refused:
            self.events.write("X")
        if self.faults > faults:
            self._note(was_safe, "fault")
            was_safe = self.safe_state
        self._note(was_safe, "safe_state_frame")
        if self.commands_applied > applied:
            self.events.write("R", self.seq_echo)

    def poll(self, now_s: float) -> list[tuple[int, bytes]]:
        was_safe, faults = self.safe_state, self.faults
        out = super().poll(now_s)  # (a watchdog trip in it is noted by run_watchdog)
        if self.faults > faults:
            self._note(was_safe, "fault")
        return out

    def run_watchdog(self, now_s: float) -> bool:
        # the emulator runs it before it hands over the frames of a tick, outside poll
        was_safe = self.safe_state
        tripped = super().run_watchdog(now_s)
        if tripped:
            self._note(was_safe, "watchdog")
        return tripped

    def _note(self, was_safe: bool, reason: str) -> None:
        if self.safe_state and not was_safe:
            self.events.write("S", reason)
        elif was_safe and not self.safe_state:
            self.events.write("U")


def run_board(stop: threading.Event, *, host: str = "127.0.0.1", port: int = 0,
              events_path: Path | None = None, default_watchdog_ms: int = 100,
              feedback_rate_hz: float = 500.0, tick_s: float = 0.002,
              plant: PlantLike | None = None,
              on_ready: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the board until ``stop`` is set or its loop fails; return its counters.

    Args:
        stop: set it to stop the board.
        host, port: where to listen (port 0: a free one).
        events_path: the event file (None: none).
        default_watchdog_ms: the firmware's watchdog when a command carries 0.
        feedback_rate_hz: feedback frames per second.
        tick_s: the emulator's tick (plant, watchdog, feedback).
        plant: a plant to use (default: a new ``ArrayTacPlant``).
        on_ready: called with the transport's URL once it listens.

    Raises:
        DeviceInitError: the port cannot be bound or the plant cannot be built.
    """
    plant = plant if plant is not None else make_plant()
    events = BoardEvents(events_path)
    transport = TcpFirmwareTransport(host, port)
    firmware = RecordingFirmware(plant, events, default_watchdog_ms=default_watchdog_ms,
                                 feedback_period_s=1.0 / feedback_rate_hz)
    emulator = FirmwareEmulator(firmware, transport, tick_s=tick_s)
    started = time.monotonic()
    emulator.start()
    try:
        if on_ready is not None:
            on_ready(transport.url)
        while not stop.wait(FLUSH_PERIOD_S):
            events.flush()  # the last R lines before a silence
            if emulator.error is not None:
                break
    finally:
        emulator.stop()
        events.close()
    stream = transport.stream_stats()
    return {
        "url": transport.url,
        "wall_s": time.monotonic() - started,
        "error": None if emulator.error is None else repr(emulator.error),
        "commands_applied": firmware.commands_applied,
        "commands_rejected": firmware.commands_rejected,
        "commands_refused_latched": firmware.commands_refused_latched,
        "watchdog_trips": firmware.watchdog_trips,
        # of which at a tick the emulator reached late (its own lateness may be the cause)
        "watchdog_trips_on_late_ticks": emulator.late_tick_trips,
        "faults": firmware.faults,
        "overruns": firmware.overruns,
        "safe_state_at_exit": firmware.safe_state,
        "events": dict(events.counts),
        "link": {"connects": transport.connects, "disconnects": transport.disconnects,
                 "replaced": transport.replaced, "feedback_dropped": transport.dropped,
                 "bytes_in": stream.bytes_in, "frames_ok": stream.frames_ok,
                 "bad_frames": stream.bad_frames, "garbage_bytes": stream.garbage_bytes},
    }
