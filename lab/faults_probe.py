"""Run a ``teletouch`` station with the fault suite's probe (lab instrumentation, not product).

``python -m lab.faults_probe local|remote ARGS...`` runs ``teletouch local|remote ARGS...`` in
this process after wrapping a few product methods so that what the station *does* is written,
(with ``--render-loop process`` the local station's display process runs through the probe
too: ``python -m lab.faults_probe display-child SETTINGS``, the same file, its own lines)
with the host's monotonic clock (the same in every process on one machine), to the file named
by ``$TELETOUCH_FAULT_PROBE``, one event a line:

* ``A mono seq ts_us`` - the display loop accepted a tactile frame (``ts_us``: its capture
  stamp, the remote station's wall clock);
* ``R mono seq ts_us`` - the first pin command rendered from that frame went to the display
  (``mono``: when the display's ``send_command`` returned, the latest the command can have
  reached the pins; not the end of the tick, which a stopped process may reach much later);
* ``W mono seq ts_us`` - a pin command went out while its frame turned stale (the process was
  stopped or starved during the send) and the loop withdrew it at once by the safe state;
* ``P mono cmd_seq ts_us`` - a pin command frame went to the display (every one sent,
  keepalives included; ``mono``: just before the send; ``cmd_seq``: the command frame's
  sequence number, which the drive board echoes; ``ts_us``: the capture stamp of the newest
  frame the loop had accepted, -1 before any): with a drive board in its own process
  (``teletouch board``), the fault suite joins the board's applied commands to these lines to
  know how old the touch was that the pins actually showed;
* ``S mono reason`` / ``U mono`` - the display entered / left its safe state;
* ``C mono ts_us accepted age_ms`` - the safety layer judged a timestamped arm command
  (``ts_us``: the local station's wall clock; ``age_ms``: the age the station computed;
  ``mono``: for an executed command, when the arm backend's ``_move_to`` was called, after
  the arm's own deadline check);
* ``H mono why`` - the arm was halted (``watchdog``: no command for the timeout; ``stop``: a
  stop call, e.g. the link-loss halt);
* ``K mono offset_us`` - the station's wall clock was stepped (see below); ``offset_us`` is
  how far the step moved the station's *stamps* (``shared.timebase.now_us``), measured.

The fault suite (``lab/faults.py``) turns these into true ages (on one host the sender's stamp
is the true time, minus the clock step it injected) and into halt / safe-state latencies after
the last valid input. The product code paths run unchanged: the wrappers call the originals and
only record their outcome.

Clock steps: when ``$TELETOUCH_FAULT_CLOCK`` names a file, ``time.time`` and ``time.time_ns``
of this process return the real wall clock plus the offset (seconds, a float) read from that
file on each SIGUSR2. The monotonic clock is untouched, as in a real NTP step. (libfaketime was
tried first: Debian's 0.9.10 with ``DONT_FAKE_MONOTONIC=1`` makes every ``time.sleep`` of
Python 3.11 fail with EINVAL, and without that flag a step moves the monotonic clock too.)
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Any, TextIO

__all__ = ["main"]

_lock = threading.RLock()  # the SIGUSR2 handler may run while the main thread writes
_out: TextIO | None = None
_real_time_ns = time.time_ns
_offset_ns = 0
_base_stamp_offset_us = 0


def _emit(*fields: object) -> None:
    if _out is None:
        return
    line = " ".join(str(f) for f in fields) + "\n"
    with _lock:
        _out.write(line)


def _mono() -> str:
    return f"{time.monotonic():.6f}"


def _install_clock(path: str) -> None:
    def fake_time_ns() -> int:
        return _real_time_ns() + _offset_ns

    def fake_time() -> float:
        return fake_time_ns() / 1e9

    def on_step(signum: int, frame: Any) -> None:
        global _offset_ns
        try:
            with open(path) as f:
                _offset_ns = round(float(f.read().strip() or "0") * 1e9)
        except (OSError, ValueError) as err:
            print(f"faults_probe: cannot read the clock offset {path}: {err}", file=sys.stderr)
            return
        # what the step did to the station's *stamp* clock, measured, not assumed: the
        # stamps come from shared.timebase.now_us, which may not follow the wall clock
        from shared.timebase import now_us

        _emit("K", _mono(), now_us() - _real_time_ns() // 1000 - _base_stamp_offset_us)

    from shared.timebase import now_us

    global _base_stamp_offset_us
    # the stamp clock's own offset from the true clock before any step (0 or a few us)
    _base_stamp_offset_us = now_us() - _real_time_ns() // 1000
    time.time_ns = fake_time_ns
    time.time = fake_time
    signal.signal(signal.SIGUSR2, on_step)


def _install_local() -> None:
    from local_site.agent import display_loop as dl
    from local_site.agent.display_process import DisplayProcess

    # a display loop in a process of its own is probed there (the same file, appended)
    DisplayProcess.child_argv = ("-m", "lab.faults_probe", "display-child")

    orig_take = dl.FrameSlot.take
    orig_tick = dl.DisplayLoop.tick

    def take(self: dl.FrameSlot) -> Any:
        item = orig_take(self)
        if item is not None:
            self._probe_taken = item[0]  # type: ignore[attr-defined]
        return item

    def watch_sends(loop: dl.DisplayLoop) -> None:
        display = loop.display
        if getattr(display, "_probe_send_watched", False):
            return
        orig_send = display.send_command

        def send_command(*args: Any, **kw: Any) -> Any:
            before = _mono()
            result = orig_send(*args, **kw)
            display._probe_sent_mono = _mono()  # type: ignore[attr-defined]
            if result.sent:
                stamp = loop._frame_stamp_us
                _emit("P", before, result.seq, -1 if stamp is None else stamp)
            return result

        display.send_command = send_command  # type: ignore[method-assign]
        display._probe_send_watched = True  # type: ignore[attr-defined]

    def tick(self: dl.DisplayLoop) -> None:
        c = self.counters
        watch_sends(self)
        accepted, rendered, safe = c.frames_accepted, c.frames_rendered, self.safe_reason
        withdrawn = c.late_sends_withdrawn
        try:
            orig_tick(self)
        finally:
            now = _mono()
            sent = getattr(self.display, "_probe_sent_mono", now)
            if c.frames_accepted > accepted and self.frames is not None:
                frame = getattr(self.frames, "_probe_taken", None)
                if frame is not None:
                    self._probe_frame = frame  # type: ignore[attr-defined]
                    _emit("A", now, frame.seq, frame.ts_us)
            if safe is not None and self.safe_reason is None:
                _emit("U", now)
            if c.frames_rendered > rendered or c.late_sends_withdrawn > withdrawn:
                frame = getattr(self, "_probe_frame", None)
                if frame is not None:
                    kind = "R" if c.frames_rendered > rendered else "W"
                    _emit(kind, sent, frame.seq, frame.ts_us)
            if safe is None and self.safe_reason is not None:
                _emit("S", now, self.safe_reason)

    dl.FrameSlot.take = take  # type: ignore[method-assign]
    dl.DisplayLoop.tick = tick  # type: ignore[method-assign]


def _install_remote() -> None:
    from remote_site.arm import safety

    orig_move = safety.SafeArm.move
    orig_poll = safety.SafeArm.poll
    orig_stop = safety.SafeArm.stop

    def watch_moves(safe: safety.SafeArm) -> None:
        arm = safe.arm
        if getattr(arm, "_probe_move_watched", False):
            return
        orig_move_to = arm._move_to  # the backend hook: called once the arm will move

        def _move_to(*args: Any, **kw: Any) -> Any:
            arm._probe_move_mono = _mono()  # type: ignore[attr-defined]
            return orig_move_to(*args, **kw)

        arm._move_to = _move_to  # type: ignore[method-assign]
        arm._probe_move_watched = True  # type: ignore[attr-defined]

    def move(self: safety.SafeArm, target_mm: Any, *, sent_ts_us: int | None = None,
             **kw: Any) -> safety.CommandResult:
        watch_moves(self)
        self.arm._probe_move_mono = None  # type: ignore[attr-defined]
        # every other argument (offsets and their error bound) passes through unchanged
        result = orig_move(self, target_mm, sent_ts_us=sent_ts_us, **kw)
        if sent_ts_us is not None:
            age = "nan" if result.age_ms is None else f"{result.age_ms:.3f}"
            # an executed command is timed when the arm backend was told (after the arm's
            # own deadline check), not when the wrapper returned (a starved process may
            # get back much later)
            when = getattr(self.arm, "_probe_move_mono", None) if result.accepted else None
            _emit("C", when or _mono(), sent_ts_us, int(result.accepted), age)
        return result

    def poll(self: safety.SafeArm) -> Any:
        before = self.halted
        reading = orig_poll(self)
        if not before and self.halted:
            _emit("H", _mono(), "watchdog")
        return reading

    def stop(self: safety.SafeArm) -> None:
        before = self.halted
        orig_stop(self)
        if not before:
            _emit("H", _mono(), "stop")

    safety.SafeArm.move = move  # type: ignore[method-assign]
    safety.SafeArm.poll = poll  # type: ignore[method-assign]
    safety.SafeArm.stop = stop  # type: ignore[method-assign]


def main(argv: list[str] | None = None) -> int:
    """Install the probe for the station named first in ``argv`` and run ``teletouch``."""
    global _out
    args = list(sys.argv[1:] if argv is None else argv)
    # the station's subcommand may follow global flags such as --log-level LEVEL
    role = next((a for a in args if a in ("local", "remote", "display-child")), None)
    path = os.environ.get("TELETOUCH_FAULT_PROBE")
    if role is None or not path:
        print("usage: TELETOUCH_FAULT_PROBE=FILE python -m lab.faults_probe "
              "[--log-level L] local|remote ARGS...", file=sys.stderr)
        return 2
    _out = open(path, "a", buffering=1)  # noqa: SIM115 - open for the process's life
    clock = os.environ.get("TELETOUCH_FAULT_CLOCK")
    if clock and role != "display-child":  # the child stamps on its station's clock anyway
        _install_clock(clock)
    if role == "display-child":
        _install_local()
        from local_site.agent.display_child import main as child_main

        try:
            return child_main(args[args.index(role) + 1:])
        finally:
            with _lock:
                _out.close()
                _out = None
    if role == "local":
        _install_local()
    else:
        _install_remote()
    from lab.cli import main as teletouch_main

    try:
        return teletouch_main(args)
    finally:
        with _lock:
            _out.close()
            _out = None


if __name__ == "__main__":
    sys.exit(main())
