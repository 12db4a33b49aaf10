"""The display loop: tactile frames in, safety rules, render, ArrayTac out, at the refresh rate.

One iteration (:meth:`DisplayLoop.tick`):

1. take the newest tactile frame handed over by the link (:class:`FrameSlot`, latest wins)
   and apply it to the :class:`~local_site.scenes.TactileFrameScene`; a bad frame (NaN,
   out of range, malformed) is rejected and counted and the pins are not touched;
2. decide whether the pins must be in their safe state, in this order: the platform is
   lost, the link has been down longer than ``link_loss_timeout_s``, no frame has
   arrived yet, the clock offsets needed to age the frame are unknown or too uncertain
   (``clock_uncertain``), the frame *may* be older than ``max_frame_age_s`` by its own
   capture stamp (converted to our clock with the relay's offsets, error bound included:
   :func:`shared.freshness.judge_age`), or no frame arrived for ``stale_timeout_s`` (the
   last four only for the remote stream). So a frame held in a queue or a socket during an
   outage, or frozen with a stopped process, is never rendered as fresh: its stamp says how
   old it is, whenever it arrives. Entering the safe state sends ``safe_state(mode)`` once;
   while in it, nothing else is sent (the board's watchdog is set to the same mode). It is left as
   soon as no reason remains (for the remote stream: a fresh frame arrived);
3. render the scene at the newest platform position; the renderer returns the same
   object when nothing changed, in which case only the driver's keepalive runs; the
   command (and a keepalive) carries the moment the frame may turn too old, and the driver
   checks it right before it writes (a process stopped or starved since the check must not
   put an old frame on the pins: refused, safe state, counted ``late_sends_refused``); a
   frame found stale just after the send (stopped during the write) is withdrawn at once by
   the safe state and counted (``late_sends_withdrawn``);
4. when the first command rendered from a new frame goes to the display, stamp
   ``local.rendered`` and account the frame's hops in the motion-to-touch ledger.

All scene access happens in this loop, so the scene needs no lock. Display errors are
caught by the runner, which reopens the display with backoff. The loop runs in a
dedicated thread (:meth:`DisplayLoop.run_in_thread`) or as an asyncio task
(:meth:`DisplayLoop.run_async`); benchmarks/bench_display_loop_agent.py measures both.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from local_site.agent.period_stats import PeriodStats
from local_site.display.base import ArrayTacDisplay, SafeMode
from local_site.platform.base import PlatformSample
from local_site.render import PinCommand, Renderer
from local_site.scenes import SceneSource, TactileFrameScene
from shared.errors import (
    CommandExpiredError,
    ConfigError,
    DeviceError,
    DeviceInitError,
    InputDataError,
)
from shared.freshness import AgeVerdict, ClockView, judge_age
from shared.motion_to_touch import MotionToTouchLedger
from shared.protocol import Hop, TactileFrame, carry_motion
from shared.timebase import monotonic_s, now_us

__all__ = ["SAFE_REASONS", "DisplayLoop", "DisplayLoopCounters", "FrameSlot", "LinkHealth",
           "LoopRecorder", "PinState", "SameClockLink", "opening_scheduling", "thread_priority",
           "thread_realtime"]

log = logging.getLogger(__name__)

#: why the pins are in their safe state, in order of precedence
SAFE_REASONS = ("platform_lost", "link_lost", "no_frames", "clock_uncertain", "stale_frame",
                "stale_scene", "display_lost", "shutdown")


class LoopRecorder(Protocol):
    """What the loop tells a recorder (a :class:`~local_site.recording.SessionRecorder`)."""

    def add_frame(self, frame: TactileFrame, rx_us: int) -> None:
        """A frame the loop accepted into its scene (received at ``rx_us``)."""

    def add_pins(self, commanded: Any, display: Any, safe_reason: str | None) -> None:
        """The pins' state, offered every tick (the recorder samples it at its rate)."""


@dataclass(frozen=True, slots=True)
class PinState:
    """What the pins are doing, as one object the loop replaces whole (never edits).

    Another thread (the live view) reads :attr:`DisplayLoop.pin_state` once and gets the
    command and the safe-state reason of the same moment: never the last command together
    with the safe state that withdrew it, nor the reverse.

    Attributes:
        command: the pin command last sent (None in the safe state and before the first).
        safe_reason: why the pins are in their safe state (None: rendering).
        seq: counts the changes of this state (a reader can tell a newer one).
    """

    command: PinCommand | None = None
    safe_reason: str | None = None
    seq: int = 0


class LinkHealth(Protocol):
    """What the loop needs from the relay link (:class:`shared.client.StationLink`)."""

    def link_down_for_s(self, now_s: float | None = None) -> float: ...

    @property
    def clock_offsets_us(self) -> Mapping[str, int | None]: ...

    @property
    def clock_view(self) -> ClockView | None: ...


class SameClockLink:
    """A :class:`LinkHealth` without a relay: always up, every party on this process's clock.

    For a replay of a recording (its frames are re-stamped when handed over, so the loop's age
    rule measures replay time) and for tests. ``offset_bound_us``: the error bound reported
    for the (zero) clock offsets.
    """

    is_connected = True

    def __init__(self, offset_bound_us: int = 0) -> None:
        self._bound_us = offset_bound_us

    def link_down_for_s(self, now_s: float | None = None) -> float:
        return 0.0

    @property
    def clock_offsets_us(self) -> dict[str, int | None]:
        return {"local": 0, "remote": 0}

    @property
    def clock_view(self) -> ClockView:
        return ClockView({"local": 0, "remote": 0},
                         {"local": self._bound_us, "remote": self._bound_us}, now_us())


#: the thread named in the log when a raised priority is refused
_LOOP_THREAD = "display loop thread"


@contextlib.contextmanager
def _thread_setting(value: int, keeps: str, read: Callable[[], Any],
                    write: Callable[[Any], None], setting: Any,
                    grant: str, who: str) -> Iterator[int | None]:
    """Apply ``setting`` to the calling thread for the block (``write``), restore what
    ``read`` returned before it after; yield ``value``, or None when the OS refused (logged:
    the thread, ``who``, ``keeps`` its ..., and how to ``grant`` the right)."""
    try:
        before = read()
        write(setting)
    except OSError as err:
        log.info("%s keeps its %s refused: %s); to allow it, %s", who, keeps, err, grant)
        refused = True
    else:
        refused = False
    if refused:  # yielded outside the handler: the block's errors are not chained to it
        yield None
        return
    try:
        yield value
    finally:
        with contextlib.suppress(OSError):
            write(before)


@contextlib.contextmanager
def thread_priority(nice: int, who: str = _LOOP_THREAD) -> Iterator[int | None]:
    """Give the calling thread the nice value ``nice`` for the block (Linux: per thread).

    Yields the value applied, or None when ``nice`` is 0 or the OS refused (raising the
    priority needs root or ``CAP_SYS_NICE``; logged once, the thread keeps its priority).
    The previous value is restored after the block (lowering is always permitted).
    """
    if nice == 0 or not hasattr(os, "setpriority"):
        yield None
        return
    tid = threading.get_native_id()
    with _thread_setting(nice, f"priority (nice {nice}",
                         lambda: os.getpriority(os.PRIO_PROCESS, tid),
                         lambda v: os.setpriority(os.PRIO_PROCESS, tid, v), nice,
                         f"run as root or with CAP_SYS_NICE, or set RLIMIT_NICE >= {20 - nice} "
                         f"(systemd: LimitNICE={nice})", who) as applied:
        yield applied


@contextlib.contextmanager
def thread_realtime(priority: int, who: str = _LOOP_THREAD) -> Iterator[int | None]:
    """Run the calling thread under ``SCHED_FIFO`` at ``priority`` (1-99) for the block.

    Yields the priority applied, or None when ``priority`` is 0 or the OS refused (it needs
    root or ``CAP_SYS_NICE``; logged, naming the thread ``who``, which keeps its policy). The
    thread's previous policy and priority are restored after the block. A real-time thread
    runs as soon as it wakes, ahead of every ordinary thread; the display loop sleeps every
    period, and the kernel's real-time throttling (``/proc/sys/kernel/sched_rt_runtime_us``,
    95 % by default) would still leave the rest of the machine its share if it did not.
    """
    if priority == 0 or not hasattr(os, "sched_setscheduler"):
        yield None
        return
    tid = threading.get_native_id()
    with _thread_setting(priority, f"scheduling policy (SCHED_FIFO {priority}",
                         lambda: (os.sched_getscheduler(tid), os.sched_getparam(tid)),
                         lambda v: os.sched_setscheduler(tid, *v),
                         (os.SCHED_FIFO, os.sched_param(priority)),
                         f"run as root or with CAP_SYS_NICE, or set RLIMIT_RTPRIO >= {priority} "
                         f"(systemd: LimitRTPRIO={priority}; docker: --ulimit rtprio="
                         f"{priority})", who) as applied:
        yield applied


_Scheduling = tuple[int, Any, int]  # policy, sched_param, nice value


def _read_scheduling(tid: int) -> _Scheduling:
    return (os.sched_getscheduler(tid), os.sched_getparam(tid),
            os.getpriority(os.PRIO_PROCESS, tid))


def _write_scheduling(tid: int, value: _Scheduling) -> None:
    os.setpriority(os.PRIO_PROCESS, tid, value[2])
    os.sched_setscheduler(tid, value[0], value[1])


def read_thread_scheduling() -> _Scheduling | None:
    """The calling thread's scheduling policy and nice value (None where not readable)."""
    if not hasattr(os, "sched_setscheduler"):
        return None
    try:
        return _read_scheduling(threading.get_native_id())
    except OSError:  # pragma: no cover - /proc-less or exotic kernels
        return None


@contextlib.contextmanager
def opening_scheduling(scheduling: _Scheduling | None = None) -> Iterator[None]:
    """Give the calling thread the scheduling to open a display with for the block:
    ``scheduling`` (default: the scheduling policy and nice value of the process's main
    thread); restore its own after.

    A thread inherits them from the thread that starts it. The display loop's thread runs
    with a raised priority (:func:`thread_realtime`, :func:`thread_priority`) and (re)opens
    the display, which starts the driver's reader thread (and, for an emulated board, the
    board's own thread): opened inside this block, those run like the process's other
    threads instead of at the loop's real-time priority, where a reader flooded by a faulty
    device would hold a core ahead of every ordinary thread. Where the loop runs on the
    main thread itself (the display process), the main thread's scheduling is the raised
    one: the loop passes the ``scheduling`` its thread had before it raised it. Lowering a
    priority is always permitted, and raising it back needs the right the loop's thread
    already used.
    """
    if not hasattr(os, "sched_setscheduler"):
        yield
        return
    tid = threading.get_native_id()
    try:
        own = _read_scheduling(tid)
        main = scheduling if scheduling is not None else _read_scheduling(os.getpid())
    except OSError as err:  # pragma: no cover - /proc-less or exotic kernels
        log.debug("scheduling of the display loop's thread not read: %s", err)
        yield
        return
    if own == main:
        yield
        return
    try:
        _write_scheduling(tid, main)
    except OSError as err:  # pragma: no cover - lowering is always permitted
        log.warning("display loop thread: could not lower its priority to open the display "
                    "(%s); the display's threads inherit the loop's", err)
    try:
        yield
    finally:
        try:
            _write_scheduling(tid, own)
        except OSError as err:  # pragma: no cover - the right was used on the way in
            log.warning("display loop thread: its raised priority could not be restored "
                        "after opening the display: %s", err)


class FrameSlot:
    """Latest-wins hand-over of tactile frames from the link task to the display loop.

    Args:
        prepare: run on each frame by :meth:`put`, in the thread that offers it (e.g.
            :meth:`TactileFrameScene.prepare`: validation and the interpolation grid, about
            half a millisecond of work per frame that would otherwise land inside one of the
            loop's 1 ms periods); its result, or the :class:`InputDataError` it raised,
            travels with the frame. None: the loop prepares the frame itself.
    """

    def __init__(self, prepare: Callable[[TactileFrame], Any] | None = None) -> None:
        self._lock = threading.Lock()
        self._item: tuple[TactileFrame, int, Any] | None = None
        self.prepare = prepare
        self.put_count = 0
        self.superseded = 0
        #: the loop renders (set by it): a frame replaced meanwhile was late, and its
        #: successor takes its start on; while the pins are safe or the loop has not begun,
        #: the touch path is out, not slow, and the successor counts from its own start
        self.rendering = False

    def put(self, frame: TactileFrame, rx_us: int) -> None:
        """Offer a frame (replaces one the loop has not taken yet, counted; while the loop
        renders, the newer frame then starts where the replaced one started:
        :func:`~shared.protocol.carry_motion`)."""
        prepared: Any = None
        if self.prepare is not None:
            try:
                prepared = self.prepare(frame)
            except InputDataError as err:
                prepared = err  # refused by the loop, which counts and reports it
        with self._lock:
            if self._item is not None:
                self.superseded += 1
                if self.rendering:  # never taken: this one shows first what it showed
                    frame = carry_motion(self._item[0], frame)
            self._item = (frame, rx_us, prepared)
            self.put_count += 1

    def take(self) -> tuple[TactileFrame, int, Any] | None:
        """The newest frame, its arrival time and what ``prepare`` gave (None without
        one), or None."""
        with self._lock:
            item, self._item = self._item, None
            return item


@dataclass
class DisplayLoopCounters:
    """What the display loop did (read for the status line and the summary)."""

    frames_accepted: int = 0
    frames_rejected: int = 0
    frames_rendered: int = 0
    frames_superseded_unrendered: int = 0
    commands_sent: int = 0
    commands_skipped_unchanged: int = 0
    keepalives_sent: int = 0
    render_rejected: int = 0
    safe_entries: dict[str, int] = field(default_factory=dict)
    safe_time_s: float = 0.0
    link_loss_to_safe_ms: list[float] = field(default_factory=list)
    display_errors: int = 0
    display_reconnects: int = 0
    last_reject_reason: str | None = None
    #: pin commands that went out while their frame turned stale (process stopped or
    #: starved during the send); each was followed at once by the safe state
    late_sends_withdrawn: int = 0
    #: pin commands (keepalives included) the display driver refused to write because the
    #: frame's deadline had passed since the loop's check (nothing reached the pins)
    late_sends_refused: int = 0
    #: the oldest clock-corrected capture age of a frame while it was on the pins (ms)
    rendered_frame_age_max_ms: float = 0.0


class DisplayLoop:
    """Drives the display from the scene at the platform position (see module docstring).

    Args:
        display: the ArrayTac display (the loop connects it when needed).
        renderer: the renderer.
        scene: a local scene, or a :class:`TactileFrameScene` fed through ``frames``.
        positions: returns the newest platform sample (None before the first).
        platform_ok: returns False while the platform is lost.
        rate_hz: loop rate (the array refresh rate).
        safe_mode: ``flat`` or ``hold``.
        frames: the frame hand-over (remote stream only).
        link: the relay link (remote stream only).
        link_loss_timeout_s: link down longer than this -> safe state.
        stale_timeout_s: no frame arrived for this long -> safe state.
        max_frame_age_s: a frame that may be older than this (capture stamp, clock-corrected,
            error bound included) is not rendered (safe state ``stale_frame``).
        max_offset_uncertainty_s: frames are not rendered while the clock offsets' error
            bound is wider than this (safe state ``clock_uncertain``).
        recorder: records every accepted frame and the pins (optional).
        ledger: motion-to-touch accounting (optional).
        retry_min_s: first delay before reopening a failed display.
        retry_max_s: largest such delay.
        frame_listener: called with each accepted frame and its arrival time (the live
            view's hand-over; must be as cheap as a ``deque.append``).

    Raises:
        ConfigError: ``frames`` given without a :class:`TactileFrameScene`, or bad values.
    """

    def __init__(self, display: ArrayTacDisplay, renderer: Renderer, scene: SceneSource, *,
                 positions: Callable[[], PlatformSample | None],
                 platform_ok: Callable[[], bool], rate_hz: float = 1000.0,
                 safe_mode: SafeMode = "flat", frames: FrameSlot | None = None,
                 link: LinkHealth | None = None, link_loss_timeout_s: float = 0.1,
                 stale_timeout_s: float = 0.08, max_frame_age_s: float = 0.15,
                 max_offset_uncertainty_s: float = 0.03,
                 recorder: LoopRecorder | None = None,
                 ledger: MotionToTouchLedger | None = None, retry_min_s: float = 0.2,
                 retry_max_s: float = 5.0,
                 frame_listener: Callable[[TactileFrame, int], None] | None = None) -> None:
        if frames is not None and not isinstance(scene, TactileFrameScene):
            raise ConfigError("a frame hand-over needs a TactileFrameScene")
        if frames is not None and frames.prepare is not None \
                and frames.prepare != getattr(scene, "prepare", None):
            raise ConfigError("the frame hand-over prepares frames for another scene than "
                              "the loop's (FrameSlot(prepare=scene.prepare))")
        if not (rate_hz > 0 and link_loss_timeout_s > 0 and stale_timeout_s > 0
                and max_frame_age_s > 0 and max_offset_uncertainty_s > 0):
            raise ConfigError("rate, timeouts and age bounds of the display loop must be > 0")
        self.display = display
        display.warm_up()  # its send path compiled now, not in the first command
        self.renderer = renderer
        self.scene = scene
        self._positions = positions
        self._platform_ok = platform_ok
        self.period_s = 1.0 / rate_hz
        self.safe_mode: SafeMode = safe_mode
        self.frames = frames
        self._stream = scene if isinstance(scene, TactileFrameScene) and frames is not None \
            else None
        self.link = link
        self._link_loss_timeout_s = link_loss_timeout_s
        self._stale_timeout_s = stale_timeout_s
        self._max_frame_age_us = max_frame_age_s * 1e6
        self._max_uncertainty_us = max_offset_uncertainty_s * 1e6
        #: the current frame's capture stamp (sender clock) and (our clock minus the
        #: sender's, error bound) when it was taken in; None: the clock was unknown
        self._frame_stamp_us: int | None = None
        self._frame_clock: tuple[float, float] | None = None
        #: when the current frame may turn too old (monotonic s; None: local scene)
        self._frame_deadline_s: float | None = None
        #: the same for the frame the pins' command was rendered from
        self._pins_deadline_s: float | None = None
        self.recorder = recorder
        self.ledger = ledger
        self._retry_min_s = retry_min_s
        self._retry_max_s = retry_max_s
        self.periods = PeriodStats(self.period_s)
        self.counters = DisplayLoopCounters()
        #: the command on the pins and the safe-state reason, replaced whole (:class:`PinState`)
        self.pin_state = PinState()
        #: why the last frame was judged unusable (for the status line and logs)
        self.last_frame_verdict: AgeVerdict | None = None
        self._safe_since_s: float | None = None
        self._pending_hops: tuple[tuple[Hop, ...], int] | None = None
        #: recent end-to-end latencies (ms) for the status line (the ledger is read at exit)
        self.recent_e2e_ms: collections.deque[float] = collections.deque(maxlen=2000)
        #: the newest frame's stages and end-to-end (us) and when it was rendered (monotonic s)
        self.last_trace: tuple[tuple[tuple[str, float], ...], float | None, float] | None = None
        self.frame_listener = frame_listener
        #: the nice value the loop's thread got (None: left alone or not permitted)
        self.priority_applied: int | None = None
        #: the SCHED_FIFO priority the loop's thread got (None: left alone or not permitted)
        self.realtime_applied: int | None = None
        #: when the loop first ticked, i.e. began to drive the board (monotonic s; None before)
        self.started_s: float | None = None
        #: the scheduling the display is opened with (None: the main thread's)
        self._open_scheduling: _Scheduling | None = None

    @property
    def last_command(self) -> PinCommand | None:
        """The pin command last sent (None in the safe state and before the first)."""
        return self.pin_state.command

    @property
    def safe_reason(self) -> str | None:
        """Why the pins are in their safe state now (None: rendering)."""
        return self.pin_state.safe_reason

    @property
    def safe_since_s(self) -> float | None:
        """Since when (monotonic clock) the open safe episode not yet in
        ``counters.safe_time_s`` runs (None: rendering)."""
        return self._safe_since_s

    def _set_pins(self, command: PinCommand | None, safe_reason: str | None) -> None:
        """Publish a new pin state (one assignment: readers in other threads see it whole)."""
        old = self.pin_state
        if old.command is not command or old.safe_reason != safe_reason:
            self.pin_state = PinState(command, safe_reason, old.seq + 1)
            if self.frames is not None:
                self.frames.rendering = safe_reason is None and command is not None

    # ------------------------------------------------------------------ one iteration

    def _intake(self) -> None:
        if self.frames is None:
            return
        item = self.frames.take()
        if item is None:
            return
        frame, rx_us, prepared = item
        scene = self._stream
        if scene is None:
            return
        try:
            scene.update(frame, prepared=prepared)
        except InputDataError as err:
            self.counters.frames_rejected += 1
            self.counters.last_reject_reason = str(err)
            if self.counters.frames_rejected == 1 or log.isEnabledFor(logging.DEBUG):
                log.warning("tactile frame seq=%s rejected, pins untouched: %s", frame.seq, err)
            return
        self.counters.frames_accepted += 1
        self._frame_stamp_us = frame.ts_us
        view = self.link.clock_view if self.link is not None else None
        self._frame_clock = None if view is None else view.relative("local", "remote", now_us())
        if self._pending_hops is not None:  # never rendered: the pins were safe or the tick
            # sent nothing (no sample, a refused render or send): not handed on, as in an
            # outage (FrameSlot.rendering)
            self.counters.frames_superseded_unrendered += 1
        self._pending_hops = (tuple(frame.hops), scene.version)
        if self.recorder is not None:
            self.recorder.add_frame(frame, rx_us)
        if self.frame_listener is not None:
            self.frame_listener(frame, rx_us)

    def _safety_reason(self, now_s: float) -> str | None:
        if not self._platform_ok():
            return "platform_lost"
        if self.link is not None and \
                self.link.link_down_for_s(now_s) > self._link_loss_timeout_s:
            return "link_lost"
        if self._stream is not None:
            age_s = self._stream.age_s(now_s)
            if age_s is None or self._frame_stamp_us is None:
                return "no_frames"
            verdict = self._frame_verdict()
            if not verdict.fresh:
                self.last_frame_verdict = verdict
                return "stale_frame" if verdict.verdict == "stale" else "clock_uncertain"
            if age_s > self._stale_timeout_s:
                return "stale_scene"
            if verdict.age_us is not None:
                self.counters.rendered_frame_age_max_ms = max(
                    self.counters.rendered_frame_age_max_ms, verdict.age_us / 1000.0)
                # the moment the frame may turn too old, for the display driver's own check
                self._frame_deadline_s = now_s + (self._max_frame_age_us - verdict.age_us
                                                  - (verdict.uncertainty_us or 0.0)) / 1e6
        return None

    def _frame_verdict(self) -> AgeVerdict:
        """The current frame's age, judged now (capture stamp, clock-corrected, bounded)."""
        if self._frame_stamp_us is None:
            return AgeVerdict("unknown_clock")
        return judge_age(self._frame_stamp_us, now_us(), self._frame_clock,
                         max_age_us=self._max_frame_age_us,
                         max_uncertainty_us=self._max_uncertainty_us)

    def _frame_went_stale(self) -> bool:
        """The remote stream's frame is no longer fresh (re-checked around the send)."""
        if self._stream is None:
            return False
        verdict = self._frame_verdict()
        if verdict.fresh:
            return False
        self.last_frame_verdict = verdict
        return True

    def enter_safe_state(self, reason: str, now_s: float | None = None) -> None:
        """Put the pins in the safe state now (idempotent while already safe).

        Raises:
            DeviceError: the display refused the frame.
        """
        now_s = monotonic_s() if now_s is None else now_s
        if self.safe_reason is not None:
            return
        # published before the board is told: from the decision on, no reader (the live
        # view) may show the withdrawn command as current
        self._set_pins(None, reason)
        try:
            self.display.safe_state(self.safe_mode)
        except DeviceError:
            self._set_pins(None, None)  # not safe yet: the next tick tries again
            raise
        self._safe_since_s = now_s
        self.counters.safe_entries[reason] = self.counters.safe_entries.get(reason, 0) + 1
        if self.link is not None:
            down_s = self.link.link_down_for_s(now_s)
            if down_s > 0 and len(self.counters.link_loss_to_safe_ms) < 1000:
                self.counters.link_loss_to_safe_ms.append(down_s * 1e3)
        self.renderer.invalidate()
        log.info("display to safe state %r (%s)", self.safe_mode, reason)

    def _close_safe_episode(self, now_s: float) -> None:
        """Count the open safe episode into ``safe_time_s``. Its start is cleared first: a
        reader in another thread (the display process's reporter) may find the episode
        neither open nor counted for a moment, never both."""
        since, self._safe_since_s = self._safe_since_s, None
        if since is not None:
            self.counters.safe_time_s += max(0.0, now_s - since)

    def _leave_safe_state(self, now_s: float) -> None:
        self._close_safe_episode(now_s)
        log.info("display resumes rendering (was safe: %s)", self.safe_reason)
        self._set_pins(None, None)

    def tick(self) -> None:
        """One iteration (see the module docstring).

        Raises:
            DeviceError: the display failed (the runner reopens it).
        """
        self._intake()
        if self.recorder is not None:
            pins = self.pin_state
            self.recorder.add_pins(pins.command, self.display, pins.safe_reason)
        now_s = monotonic_s()
        reason = self._safety_reason(now_s)
        if reason is not None:
            if self.safe_reason is None:
                self.enter_safe_state(reason, now_s)
            else:
                # nothing is sent while safe, so a dead board must be asked for: found
                # only when rendering resumed, it cost the first fresh frame a reopen
                self.display.check_link()
            return
        if self.safe_reason is not None:
            self._leave_safe_state(now_s)
        sample = self._positions()
        if sample is None:
            return
        try:
            command = self.renderer.render(self.scene, sample.position_mm)
        except InputDataError as err:
            self.counters.render_rejected += 1
            if self.counters.render_rejected == 1 or log.isEnabledFor(logging.DEBUG):
                log.warning("render refused, pins keep their last command: %s", err)
            # kept alive only while the frame it was rendered from is fresh (not the newest
            # frame's deadline: that frame was never rendered), and only a command rendered
            # since the pins were last safe or reset: none -> nothing is re-sent
            if self.pin_state.command is not None:
                self._keepalive(self._pins_deadline_s)
            return
        if command is self.pin_state.command:
            self._keepalive()
            return
        # the age again at the moment of sending: rendering took time since the check, and
        # a stopped or starved process may have slept anywhere in between; the driver
        # checks the frame's deadline once more right before it writes the bytes
        try:
            applied = self.display.send_command(*command.arrays(),
                                                not_after_s=self._deadline())
        except CommandExpiredError as err:
            self._refuse_late(err)
            return
        self._set_pins(command, None)
        self._pins_deadline_s = self._deadline()
        if self._frame_went_stale():
            # the process was stopped or starved *during* the send: the command may have
            # reached the pins with an old frame; it is withdrawn at once (safe state) and
            # counted, never counted as rendered
            self.counters.late_sends_withdrawn += 1
            late_ms = self._overshoot_ms()
            # a frame that just crossed its bound during the write is routine (the next tick
            # would have gone safe); one far past it means this process was stopped or starved
            log.log(logging.WARNING if late_ms > 5.0 else logging.DEBUG,
                    "a pin command went out %.1f ms after its frame's bound; withdrawn", late_ms)
            self._pending_hops = None
            self.enter_safe_state("stale_frame")
            return
        if applied.sent:
            self.counters.commands_sent += 1
        else:
            self.counters.commands_skipped_unchanged += 1
        pending = self._pending_hops
        if pending is not None and command.scene_version >= pending[1]:
            self._pending_hops = None
            self.counters.frames_rendered += 1
            if self.ledger is not None:
                offsets = dict(self.link.clock_offsets_us) if self.link is not None else {}
                trace = self.ledger.add_hops((*pending[0], Hop("local", "rendered", now_us())),
                                             offsets)
                if trace.end_to_end_us is not None:
                    self.recent_e2e_ms.append(trace.end_to_end_us / 1e3)
                self.last_trace = (trace.stages_us, trace.end_to_end_us, now_s)

    def _overshoot_ms(self) -> float:
        """How far past its bound the current frame may be now (0 when unknown)."""
        v = self.last_frame_verdict
        if v is None or v.age_us is None:
            return 0.0
        return max(0.0, (v.age_us + (v.uncertainty_us or 0.0) - self._max_frame_age_us) / 1e3)

    def _deadline(self) -> float | None:
        return self._frame_deadline_s if self._stream is not None else None

    def _refuse_late(self, err: CommandExpiredError) -> None:
        """The driver refused a pin command past its frame's deadline (nothing was sent)."""
        self.counters.late_sends_refused += 1
        log.warning("%s", err)
        self.enter_safe_state("stale_frame")

    def _keepalive(self, not_after_s: float | None = None) -> None:
        """Re-send the pins' command when due, refused past ``not_after_s`` (default: the
        current frame's deadline, for a command rendered from it)."""
        try:
            if self.display.keepalive(not_after_s=self._deadline() if not_after_s is None
                                      else not_after_s):
                self.counters.keepalives_sent += 1
        except CommandExpiredError as err:
            self._refuse_late(err)

    # ------------------------------------------------------------------ device recovery

    def _reopen_display(self, stop: Callable[[float], bool]) -> bool:
        """Reopen the display with backoff; ``stop(delay)`` waits and says whether to quit."""
        delay = self._retry_min_s
        logged = False
        while True:
            try:
                # the display's threads (its reader) must not inherit the loop's priority
                with opening_scheduling(self._open_scheduling):
                    self.display.connect()
                break
            except DeviceInitError as err:
                if not logged:
                    log.error("display %s cannot be opened: %s; retrying with backoff",
                              self.display.name, err)
                    logged = True
            if stop(delay):
                return False
            delay = min(self._retry_max_s, delay * 2.0)
        self._close_safe_episode(monotonic_s())  # the pins were safe while it was away
        self._set_pins(None, None)
        self.renderer.invalidate()
        self.periods.restart()
        return True

    def _display_failed(self, err: DeviceError, stop: Callable[[float], bool]) -> bool:
        self.counters.display_errors += 1
        # no command is current while the board is away (its own watchdog parks the pins):
        # published at once, and the outage counted as a safe episode (found by review:
        # the last command was shown as live until the board was back)
        self._set_pins(None, "display_lost")
        if self._safe_since_s is None:
            self._safe_since_s = monotonic_s()
            self.counters.safe_entries["display_lost"] = \
                self.counters.safe_entries.get("display_lost", 0) + 1
        if self.frames is not None:  # nothing renders until the display is back: an outage
            self.frames.rendering = False
        log.error("display failed: %s; reopening with backoff", err)
        try:
            self.display.disconnect()
        except DeviceError as close_err:
            log.debug("display disconnect after failure: %s", close_err)
        if stop(self._retry_min_s):
            return False
        ok = self._reopen_display(stop)
        if ok:
            self.counters.display_reconnects += 1
            log.info("display %s is back", self.display.name)
        return ok

    # ------------------------------------------------------------------ runners

    def run_in_thread(self, stop: threading.Event, nice: int = 0, realtime: int = 0) -> None:
        """Run at ``rate_hz`` until ``stop`` is set (blocking; call from a thread).

        The schedule is absolute (sleep overshoot does not accumulate); when an iteration
        is late by more than a period the schedule is re-anchored (counted as an overrun)
        rather than bursting. The thread always sleeps, never spins, so it cannot starve
        the other threads of the GIL.

        Args:
            stop: ends the loop when set.
            nice: this thread's nice value while the loop runs (0: unchanged; see
                :func:`thread_priority`); its previous value is restored on return.
            realtime: this thread's ``SCHED_FIFO`` priority while the loop runs (0:
                unchanged; see :func:`thread_realtime`); restored on return.
        """
        # the display is (re)opened with the scheduling the thread had before: its threads
        # must not inherit the loop's
        self._open_scheduling = read_thread_scheduling()
        with thread_priority(nice) as applied, thread_realtime(realtime) as rt_applied:
            self.priority_applied = applied
            self.realtime_applied = rt_applied
            self._run_in_thread(stop)

    def _run_in_thread(self, stop: threading.Event) -> None:
        if not self.display.is_connected and not self._reopen_display(stop.wait):
            return
        period = self.period_s
        next_t = time.perf_counter()
        if self.started_s is None:
            self.started_s = monotonic_s()
        while not stop.is_set():
            self.periods.tick(time.perf_counter())
            try:
                self.tick()
            except DeviceError as err:
                if not self._display_failed(err, stop.wait):
                    return
                next_t = time.perf_counter()
            next_t += period
            after = time.perf_counter()
            if next_t < after - period:
                next_t = after
                self.periods.overruns += 1
            remaining = next_t - time.perf_counter()
            if remaining > 0:
                time.sleep(remaining)

    async def run_async(self, stop: asyncio.Event) -> None:
        """Run at ``rate_hz`` as an asyncio task until ``stop`` is set.

        Same schedule as :meth:`run_in_thread`; display recovery runs in a worker thread.
        """
        def stop_wait(delay_s: float) -> bool:
            time.sleep(delay_s)
            return stop.is_set()

        if not self.display.is_connected and \
                not await asyncio.to_thread(self._reopen_display, stop_wait):
            return
        period = self.period_s
        next_t = time.perf_counter()
        if self.started_s is None:
            self.started_s = monotonic_s()
        while not stop.is_set():
            self.periods.tick(time.perf_counter())
            try:
                self.tick()
            except DeviceError as err:
                if not await asyncio.to_thread(self._display_failed, err, stop_wait):
                    return
                next_t = time.perf_counter()
            next_t += period
            after = time.perf_counter()
            if next_t < after - period:
                next_t = after
                self.periods.overruns += 1
            await asyncio.sleep(max(0.0, next_t - time.perf_counter()))

    def finish(self, reason: str = "shutdown") -> None:
        """Final safe state at shutdown (best effort; the display stays open)."""
        now_s = monotonic_s()
        if self.safe_reason is not None and self._safe_since_s is not None:
            self._close_safe_episode(now_s)  # counted up to now; still safe from here on
            self._safe_since_s = now_s
        if not self.display.is_connected:
            return
        # published before the board is told, and whether or not it hears: no reader may
        # show the last command as current after shutdown (the board's watchdog parks the
        # pins of a link that refused the frame)
        # (no safe episode opens here: the session's safe time and entries end with it)
        self._set_pins(None, reason)
        try:
            self.display.safe_state(self.safe_mode)
        except DeviceError as err:
            log.warning("safe state at shutdown failed: %s", err)
