"""The display loop in a process of its own: the station's side.

In the station's process the 1 kHz display loop shares the GIL with every other thread: the
event loop (the relay link, the uplink, the frames' decoding), the recorder, the live view.
Its period jitter there was measured as waits for the GIL (``docs/speed.md`` sections 19-20),
and a stand-in for a loop that shares its interpreter only with its device readers met the
0.5 ms jitter target in 5 of 6 runs (``benchmarks/bench_display_process_proxy.py``).

With ``local.agent.render_loop = "process"`` the station starts a child
(``python -m local_site.agent.display_child``, a fresh interpreter) that holds the display
driver, the renderer, the scene and the :class:`~local_site.agent.display_loop.DisplayLoop`
with all its safety rules. The platform is read in its own process as well
(:class:`~local_site.agent.platform_process.ProcessPlatformReader`); the display child reads
the newest sample from the same shared record. :class:`DisplayProcess` stands in the station
for the loop: it has the attributes the station, its status line, its summary and the live
view read (counters, periods, pin state, latency traces, the board's feedback), kept up to
date from the child's reports.

The two processes talk over a ``SOCK_SEQPACKET`` socket pair (one pickled message per
packet; both ends are this program):

* station -> child: each tactile frame as it arrives (``frame``), the link's state every
  :data:`HEARTBEAT_S` (``link``: since when it is down, the clock offsets and their bounds),
  and ``stop``;
* child -> station: a report every :data:`HEARTBEAT_S` (new loop periods, the loop's, the
  board link's and the renderer's counters, frames superseded in its hand-over, the pin
  state, the board's newest feedback, the frames the loop accepted and the hops of the frames
  it rendered; what a report refused by a busy socket carried goes with the next) and a
  final one when it stops. The pins are sampled for the station's recorder in the child, at
  the recorder's rate and stamped when the loop read them (:class:`~local_site.recording.
  PinsSampler`), and the samples travel with the reports. A report that would outgrow a
  packet (a station that took none for seconds) gives up the older half of what waits,
  counted (``shed``).

Safety, as in the station's own loop, and more (``docs/safety.md``, Watchdogs):

* the child judges every frame by its capture stamp on the station's clock (it adopts the
  station's wall-clock anchor), so a frame held anywhere is never rendered as fresh;
* with a relay, a station that goes silent (stopped, starved, dead) counts as a lost link in
  the child after two heartbeats: the pins go to their safe state within
  ``link_loss_timeout_s`` of that; the end of the socket (the station is gone) stops the
  child, which puts the pins in their safe state, closes the board and reports a last time;
  SIGINT and SIGTERM are left to the station, which stops the child in order;
* the station never waits for the child: frames and ``stop`` are sent without waiting (a
  frame the child's socket cannot take is dropped, counted as superseded), and a child that
  has not ended :data:`_CHILD_STOP_S` after ``stop`` is killed;
* a child that died, or made no progress for ``hang_timeout_s`` (its loop did not advance
  while its board was connected, or it did not report), is (killed and) started again with
  the device backoff; meanwhile the board's own watchdog holds the pins safe. The counts of
  the children that ended carry over;
* what the station shows of the pins is judged when it is read: while the child's loop has
  not been seen to advance for :data:`SILENCE_S`, no command is shown (:data:`NO_WORD`).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import errno
import json
import logging
import pickle
import select
import socket
import subprocess
import sys
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from local_site.agent.display_loop import DisplayLoopCounters, PinState
from local_site.agent.period_stats import PeriodStats
from local_site.display.base import DisplayStats, PinFeedback
from local_site.render import RendererConfig
from local_site.render.renderer import RenderStats
from shared.counters import add_counters
from shared.errors import ConfigError
from shared.freshness import ClockView
from shared.motion_to_touch import MotionToTouchLedger
from shared.protocol import Hop, TactileFrame
from shared.timebase import monotonic_s, wall_anchor_ns

__all__ = ["HEARTBEAT_S", "MAX_MESSAGE_BYTES", "NO_WORD", "SILENCE_S", "DisplayProcess",
           "LinkMirror", "LinkState", "fold_counters"]

log = logging.getLogger(__name__)

#: how often the station sends the link's state and the child reports
HEARTBEAT_S = 0.02
#: a child silent this long (stopped, starved) leaves the station's pin state unknown
SILENCE_S = 0.25
#: the safe-state reason shown while no child reports (none runs, or it is silent): the
#: pins' state is not known here, and the board's watchdog holds them safe
NO_WORD = "display_process"
#: the largest message either side reads (a tactile frame is tens of kB)
MAX_MESSAGE_BYTES = 1 << 20
#: frames kept after sending, to record and show the ones the loop accepts (the child takes
#: the newest at each tick and reports every 20 ms: a few are outstanding at a time)
_KEEP_SENT = 256
#: how long a stopping child may take (it puts the pins in their safe state, closes the board)
_CHILD_STOP_S = 6.0


@dataclass(frozen=True, slots=True)
class LinkState:
    """The relay link as the station saw it (sent to the child every heartbeat).

    Attributes:
        down_since_s: since when the link is down (monotonic clock; None: up).
        clock_view: the relay's clock offsets and their bounds (None: not yet known).
        offsets_us: the offsets the motion-to-touch ledger uses.
    """

    down_since_s: float | None
    clock_view: ClockView | None
    offsets_us: Mapping[str, int | None]


class LinkMirror:
    """The child's view of the station's link (a :class:`~local_site.agent.display_loop.
    LinkHealth`): what the station last sent, and the station's silence counted as a lost
    link (beyond ``grace_s``; also before the first word)."""

    def __init__(self, grace_s: float = 2 * HEARTBEAT_S) -> None:
        self._grace_s = grace_s
        self._state: LinkState | None = None
        self._heard_s = monotonic_s()

    def update(self, state: LinkState, now_s: float | None = None) -> None:
        """Take the station's newest word."""
        self._state = state
        self._heard_s = monotonic_s() if now_s is None else now_s

    def link_down_for_s(self, now_s: float | None = None) -> float:
        now = monotonic_s() if now_s is None else now_s
        state = self._state
        down = 0.0 if state is None or state.down_since_s is None \
            else now - state.down_since_s
        return max(0.0, down, now - self._heard_s - self._grace_s)

    @property
    def clock_offsets_us(self) -> Mapping[str, int | None]:
        state = self._state
        return {} if state is None else state.offsets_us

    @property
    def clock_view(self) -> ClockView | None:
        state = self._state
        return None if state is None else state.clock_view


def fold_counters(base: DisplayLoopCounters, more: DisplayLoopCounters) -> DisplayLoopCounters:
    """The counters of two runs of the loop (an ended child's and the next one's)."""
    out = DisplayLoopCounters()
    for f in dataclasses.fields(DisplayLoopCounters):
        a, b = getattr(base, f.name), getattr(more, f.name)
        if f.name == "rendered_frame_age_max_ms":
            value: Any = max(a, b)
        elif f.name == "last_reject_reason":
            value = b if b is not None else a
        elif isinstance(a, dict):
            value = {k: a.get(k, 0) + b.get(k, 0) for k in {*a, *b}}
        else:
            value = a + b  # counts, seconds, lists
        setattr(out, f.name, value)
    return out


@dataclass(frozen=True)
class _Totals:
    """What one child (or all the children that ended) counted."""

    counters: DisplayLoopCounters = dataclasses.field(default_factory=DisplayLoopCounters)
    display: DisplayStats = dataclasses.field(default_factory=DisplayStats)
    render: RenderStats = dataclasses.field(default_factory=RenderStats)
    superseded: int = 0
    iterations: int = 0
    overruns: int = 0
    #: reported items given up because a report no longer fitted a packet
    shed: int = 0

    def plus(self, other: _Totals) -> _Totals:
        return _Totals(fold_counters(self.counters, other.counters),
                       add_counters(self.display, other.display),
                       add_counters(self.render, other.render),
                       self.superseded + other.superseded, self.iterations + other.iterations,
                       self.overruns + other.overruns, self.shed + other.shed)


class _DisplayMirror:
    """The board as the station sees it through the child's reports (for the view, the
    recorder and the summary)."""

    def __init__(self, owner: DisplayProcess, name: str) -> None:
        self._owner = owner
        self.name = name
        self.is_connected = False
        self._feedback: PinFeedback | None = None

    def latest_feedback(self) -> PinFeedback | None:
        return self._feedback

    def stats(self) -> DisplayStats:
        """The board link's counters, those of the children that ended included."""
        return self._owner.totals.display

    def disconnect(self) -> None:
        """The child closed the board when it stopped; its last feedback stays readable."""
        self.is_connected = False


class _RendererMirror:
    def __init__(self, owner: DisplayProcess) -> None:
        self._owner = owner

    @property
    def stats(self) -> RenderStats:
        """The renderer's counters, those of the children that ended included."""
        return self._owner.totals.render


class _Frames:
    """The station's frame hand-over to the child (the ``FrameSlot`` it replaces: ``put``,
    ``put_count``, ``superseded``). Never waits: a frame the child's socket cannot take now
    is dropped and counted as superseded. It hands no start on (unlike the frame slot while
    the loop renders, ``shared.protocol.carry_motion``): the socket holds several frames, so
    a full one means a child that has not read for several frame periods (starting, hung):
    an outage of the touch path rather than a latency."""

    def __init__(self, owner: DisplayProcess) -> None:
        self._owner = owner
        self.sock: socket.socket | None = None
        self.put_count = 0
        #: frames not handed to the child (no child, its socket full or gone, too large)
        self.dropped = 0
        self.too_large = 0
        self._lock = threading.Lock()
        self._sent: collections.OrderedDict[tuple[int, int], TactileFrame] = \
            collections.OrderedDict()

    @property
    def superseded(self) -> int:
        """Frames replaced before the loop took them: dropped here, or in the children's
        hand-over (a newer frame came first)."""
        return self.dropped + self._owner.totals.superseded

    def put(self, frame: TactileFrame, rx_us: int) -> None:
        self.put_count += 1
        sock = self.sock
        key = (frame.seq, rx_us)
        # kept before it is sent: the child's report that accepts it may come at once
        with self._lock:
            self._sent[key] = frame
            while len(self._sent) > _KEEP_SENT:
                self._sent.popitem(last=False)
        try:
            if sock is None:
                raise BlockingIOError("no display process")
            sock.send(pickle.dumps(("frame", frame, rx_us), protocol=5), socket.MSG_DONTWAIT)
        except OSError as err:  # busy, gone (the supervisor starts it again) or too big
            with self._lock:
                self._sent.pop(key, None)
            self.dropped += 1
            if err.errno == errno.EMSGSIZE:
                self.too_large += 1
                if self.too_large == 1:
                    log.warning("a tactile frame too large for the display process: %s", err)

    def accepted(self, seq: int, rx_us: int) -> TactileFrame | None:
        """The frame the child accepted (None when it is no longer kept)."""
        with self._lock:
            return self._sent.pop((seq, rx_us), None)


class DisplayProcess:
    """The display loop in a child process (see the module docstring).

    It has the attributes the station reads from a
    :class:`~local_site.agent.display_loop.DisplayLoop` (``counters``, ``periods``,
    ``pin_state``, ``safe_reason``, ``recent_e2e_ms``, ``last_trace``, ``display``,
    ``renderer.stats``, ``frame_listener``, ``finish``) and :meth:`run_in_thread`, which starts
    the child and serves it until stopped.

    Args:
        display: the display spec (``open_display``).
        display_options: its options (JSON values: they cross to the child).
        render_config: the renderer's settings.
        scene: the scene spec (``remote`` for the tactile stream; else ``open_scene``'s).
        interpolation_order: the scene's interpolation order.
        platform: the platform reader in its own process (its shared record is read by the
            child).
        loop_args: the loop's settings (``DisplayLoop``'s keyword arguments: rate, safe mode,
            timeouts, retry delays).
        link: the relay link (None: a local scene).
        recorder: records accepted frames and the pins (optional).
        ledger: motion-to-touch accounting of the rendered frames (optional).
        hang_timeout_s: a child that made no progress this long (its loop did not advance
            while its board was connected, or it did not report at all) is killed and
            started again; it also covers the child's start-up.
        retry_min_s: first delay before starting an ended child again.
        retry_max_s: largest such delay.
        gil_switch_interval_s: the child's ``sys.setswitchinterval``.
        lock_memory: the child locks its memory (:mod:`shared.memlock`).

    Raises:
        ConfigError: options that are not JSON, or a platform not read in a process.
    """

    def __init__(self, *, display: str, display_options: Mapping[str, Any],
                 render_config: RendererConfig, scene: str, interpolation_order: int,
                 platform: Any, loop_args: Mapping[str, Any], link: Any = None,
                 recorder: Any = None, ledger: MotionToTouchLedger | None = None,
                 hang_timeout_s: float = 15.0, retry_min_s: float = 0.2,
                 retry_max_s: float = 5.0, gil_switch_interval_s: float = 0.0,
                 lock_memory: bool = False) -> None:
        if not hasattr(platform, "record_fd") or not hasattr(platform, "read_timeout_s"):
            raise ConfigError("the display loop in its own process reads the platform from "
                              "its process's shared record (a ProcessPlatformReader)")
        self._settings: dict[str, Any] = {
            "display": display, "display_options": dict(display_options),
            "render": dataclasses.asdict(render_config), "scene": scene,
            "order": interpolation_order, "loop": dict(loop_args), "remote": link is not None,
            "read_timeout_s": platform.read_timeout_s,
            # the child samples the pins for the recorder, at its rate, when they are read
            "pins_rate_hz": None if recorder is None else recorder.pins_sampler.rate_hz,
            "gil_switch_interval_s": gil_switch_interval_s, "lock_memory": lock_memory}
        try:
            json.dumps(self._settings)
        except (TypeError, ValueError) as err:
            raise ConfigError("display options must be JSON values to cross to the display "
                              f"process: {err}") from err
        rate_hz = float(loop_args.get("rate_hz", 1000.0))
        self.platform = platform
        self.link = link
        self.recorder = recorder
        self.ledger = ledger
        self._hang_timeout_s = hang_timeout_s
        self._retry_min_s = retry_min_s
        self._retry_max_s = retry_max_s
        self.frames = _Frames(self)
        self.display = _DisplayMirror(self, display)
        self.renderer = _RendererMirror(self)
        self.periods = PeriodStats(1.0 / rate_hz)
        self.recent_e2e_ms: collections.deque[float] = collections.deque(maxlen=2000)
        self.last_trace: tuple[tuple[tuple[str, float], ...], float | None, float] | None = None
        self.frame_listener: Any = None
        self.priority_applied: int | None = None
        self.realtime_applied: int | None = None
        #: times a child was started again after it ended unasked or hung
        self.restarts = 0
        #: the running child's process id (None: none runs)
        self.child_pid: int | None = None
        #: why the last child ended unasked (None: none did)
        self.child_error: str | None = None
        #: (what the children that ended counted, what the running one counted so far):
        #: replaced whole, so a reader in another thread never adds one child twice
        self._counts = (_Totals(), _Totals())
        self._pins = PinState()
        self._child_pins_seq = -1
        #: when the child's loop was last seen to advance (monotonic s; reports that do not
        #: advance it do not count: a wedged loop's reporter still reports)
        self._loop_seen_s = 0.0
        #: when the child was last seen alive: its loop advanced, or it reported while it
        #: waits to reopen its board
        self._alive_s = 0.0
        self._final = False
        #: safe time no child's counters hold: (what is counted so far: ended children's
        #: open episodes and gaps, s; the running child's open episode's start, monotonic s,
        #: or None; since when no child drives the board, or None). Replaced whole, so a
        #: reader in another thread never counts one stretch twice
        self._untold: tuple[float, float | None, float | None] = (0.0, None, None)
        self._spawned_s = 0.0
        self._spawn_error = "could not start"

    # ------------------------------------------------------------------ loop-like reads

    @property
    def totals(self) -> _Totals:
        """Everything counted so far, by every child."""
        ended, live = self._counts
        return ended.plus(live)

    @property
    def counters(self) -> DisplayLoopCounters:
        """The loop's counters, those of ended children included. ``safe_time_s`` also
        counts what no child's counters hold: the running child's open safe episode, a
        child that ended unasked from its open episode (or its loop's last progress) on, and
        the time no child drove the board (the board's watchdog holds the pins safe). That
        gap is counted up to the read until the next child's first report says when its loop
        first ticked: the figure may then step back by up to a heartbeat, never count a
        stretch twice."""
        counters = self.totals.counters
        extra = self._safe_untold_s(monotonic_s())
        if extra <= 0.0:
            return counters
        return dataclasses.replace(counters, safe_time_s=counters.safe_time_s + extra)

    def _safe_untold_s(self, now_s: float) -> float:
        counted, open_since, gap_since = self._untold
        if open_since is not None:
            counted += max(0.0, now_s - open_since)
        if gap_since is not None:
            counted += max(0.0, now_s - gap_since)
        return counted

    @property
    def pin_state(self) -> PinState:
        """The pins' state as the child last reported it; while its loop has not been seen
        to advance for :data:`SILENCE_S` (stopped, starved, hung, or none runs), none is
        known here: no command, safe reason :data:`NO_WORD` (judged on each read, so a
        reader never shows an old state as current, whatever the supervisor is doing)."""
        pins = self._pins
        if self._final or monotonic_s() - self._loop_seen_s <= SILENCE_S:
            return pins
        return PinState(None, NO_WORD, pins.seq)

    @property
    def last_command(self) -> Any:
        return self.pin_state.command

    @property
    def safe_reason(self) -> str | None:
        return self.pin_state.safe_reason

    def finish(self, reason: str = "shutdown") -> None:
        """Nothing to do: the child put the pins in their safe state when it stopped (its
        final report says so), or the board's watchdog did when a child ended unasked."""

    # ------------------------------------------------------------------ the child's reports

    def _take(self, message: Any) -> None:
        """Fold one report of the child into what the station reads."""
        kind, report = message
        if kind != "report":
            return
        now = monotonic_s()
        iterations, overruns = report["loops"]
        ended, live = self._counts
        counted, _, gap_since = self._untold
        if iterations > live.iterations or report["final"]:
            self._loop_seen_s = self._alive_s = now
            if gap_since is not None:  # a child drives the board again, since its first
                # tick (its own counters count safe time from then: not twice)
                started = report["started_s"]
                end = now if started is None else min(now, max(gap_since, started))
                counted += max(0.0, end - gap_since)
                gap_since = None
        elif not report["connected"]:
            self._alive_s = now  # its loop waits for the board to come back: not hung
        self._untold = (counted, report["safe_since_s"], gap_since)
        self._counts = (ended, _Totals(report["counters"], report["display_stats"],
                                       report["render_stats"], report["superseded"],
                                       iterations, overruns, report["shed"]))
        self.periods.extend(report["periods"], ended.iterations + iterations,
                            ended.overruns + overruns)
        self.priority_applied, self.realtime_applied = report["priority"]
        display = self.display
        display.is_connected = report["connected"]
        if report["feedback"] is not None:
            display._feedback = report["feedback"]
        for seq, rx_us in report["accepted"]:
            frame = self.frames.accepted(seq, rx_us)
            if frame is None:
                continue
            if self.recorder is not None:
                self.recorder.add_frame(frame, rx_us)
            listener = self.frame_listener
            if listener is not None:
                listener(frame, rx_us)
        for hops, offsets, at_s in report["rendered"]:
            if self.ledger is None:
                break
            trace = self.ledger.add_hops([Hop(*h) for h in hops], offsets)
            if trace.end_to_end_us is not None:
                self.recent_e2e_ms.append(trace.end_to_end_us / 1e3)
            self.last_trace = (trace.stages_us, trace.end_to_end_us, at_s)
        pins: PinState = report["pins"]
        if pins.seq != self._child_pins_seq:
            self._child_pins_seq = pins.seq
            self._pins = PinState(pins.command, pins.safe_reason, self._pins.seq + 1)
        if self.recorder is not None:
            for sample in report["pins_samples"]:
                self.recorder.record_pins(*sample)
        if report["final"]:
            self._final = True

    def _retire(self) -> None:
        """An ended child's counts join those of the children before it (one assignment);
        its open safe episode, or the time since its loop last advanced, and the time until
        the next child drives the board count as safe time."""
        now = monotonic_s()
        counted, open_since, gap_since = self._untold
        if gap_since is None and self._spawned_s > 0:
            if not self._final:  # a final report's counters hold its episode already
                since = open_since if open_since is not None \
                    else (self._loop_seen_s or self._spawned_s)
                counted += max(0.0, now - since)
            gap_since = now
        self._untold = (counted, None, gap_since)
        ended, live = self._counts
        self._counts = (ended.plus(live), _Totals())
        self._child_pins_seq = -1
        self._no_child()

    def _no_child(self) -> None:
        """No child drives the board now: no command is shown as on the pins (the board's
        watchdog, or the child's last act, put them in their safe state)."""
        if not self._final:
            self.display.is_connected = False
            self._pins = PinState(None, NO_WORD, self._pins.seq + 1)

    # ------------------------------------------------------------------ the child

    #: the child's command after the interpreter (an instrumented child may replace it)
    child_argv: tuple[str, ...] = ("-m", "local_site.agent.display_child")

    def _spawn(self, nice: int, realtime: int) -> tuple[subprocess.Popen[bytes],
                                                        socket.socket] | None:
        record_fd = self.platform.record_fd
        if record_fd is None:
            self._spawn_error = "not started: the platform's record is not there yet"
            return None
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        settings = {**self._settings, "sock_fd": theirs.fileno(), "record_fd": record_fd,
                    "anchor_ns": wall_anchor_ns(), "nice": nice, "realtime": realtime,
                    "log_level": logging.getLogger().getEffectiveLevel()}
        try:
            process = subprocess.Popen(
                [sys.executable, "-P", *self.child_argv, json.dumps(settings)],
                stdin=subprocess.DEVNULL, pass_fds=(theirs.fileno(), record_fd),
                process_group=0)
        except OSError as err:
            ours.close()
            self._spawn_error = f"could not start: {err}"
            return None
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        return process, ours

    def run_in_thread(self, stop: threading.Event, nice: int = 0, realtime: int = 0) -> None:
        """Start the child and serve it until ``stop`` is set; start it again, with backoff,
        when it ends unasked or hangs (a station never gives up). Blocking: call from a
        thread. ``nice`` and ``realtime`` are applied to the child's loop thread."""
        try:
            self._supervise(stop, nice, realtime)
        finally:  # stopped: what is untold stops growing (a gap, a killed child's episode)
            self._untold = (self._safe_untold_s(monotonic_s()), None, None)

    def _supervise(self, stop: threading.Event, nice: int, realtime: int) -> None:
        delay = self._retry_min_s
        while not stop.is_set():
            child = self._spawn(nice, realtime)
            why = self._spawn_error
            if child is not None:
                process, sock = child
                self.frames.sock = sock
                self.child_pid = process.pid
                try:
                    ended = self._serve(process, sock, stop)
                except BaseException:
                    _reap(process, 0.0)  # never leave a child behind
                    raise
                finally:
                    self.frames.sock = None
                    self.child_pid = None
                    sock.close()
                if ended is None:
                    return
                why = ended
                if monotonic_s() - self._spawned_s > 10 * self._retry_max_s:
                    delay = self._retry_min_s  # it ran long: a new fault, not the same one
            self.child_error = f"display process {why}"
            log.error("%s; starting it again in %.1f s", self.child_error, delay)
            self._retire()
            if stop.wait(delay):
                return
            delay = min(self._retry_max_s, delay * 2.0)
            self.restarts += 1

    def _link_state(self) -> LinkState | None:
        link = self.link
        if link is None:
            return None
        down_s = link.link_down_for_s()
        now = monotonic_s()
        return LinkState(None if down_s <= 0 else now - down_s, link.clock_view,
                         dict(link.clock_offsets_us))

    def _serve(self, process: subprocess.Popen[bytes], sock: socket.socket,
               stop: threading.Event) -> str | None:
        """Serve one child: the link's state out, its reports in. Returns why it ended
        unasked, or None when ``stop`` ended it. Never blocks on the child."""
        self._spawned_s = monotonic_s()
        self._loop_seen_s = self._alive_s = 0.0
        self._final = False
        next_beat = 0.0
        while True:
            now = monotonic_s()
            if stop.is_set():
                self._stop_child(process, sock)
                return None
            if now >= next_beat:
                next_beat = now + HEARTBEAT_S
                state = self._link_state()
                if state is not None:
                    with contextlib.suppress(OSError):  # busy or gone: found below
                        sock.send(pickle.dumps(("link", state), protocol=5),
                                  socket.MSG_DONTWAIT)
            ready, _, _ = select.select([sock], [], [], max(0.0, next_beat - monotonic_s()))
            try:
                drained = not ready or self._drain(sock)
            except _BadReport as err:
                # the child's fault, not the station's: it is ended (the end of its socket
                # makes it park the pins) and started again (found by audit: the station
                # stopped, exit 1, and the child was killed before it could park them)
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
                return f"sent a report the station cannot read ({err}): ended (exit " \
                    f"{_reap(process, _CHILD_STOP_S)})"
            if not drained:
                return f"exited with {_reap(process, _CHILD_STOP_S)}"
            if process.poll() is not None:
                return f"exited with {process.returncode}"
            alive = max(self._alive_s, self._spawned_s)
            if monotonic_s() - alive > self._hang_timeout_s:
                _reap(process, 0.0)
                return f"hung (no progress for {monotonic_s() - alive:.1f} s): killed"

    def _drain(self, sock: socket.socket) -> bool:
        """Take every report waiting; False at the end of the socket (the child is gone)."""
        while True:
            try:
                data = sock.recv(MAX_MESSAGE_BYTES, socket.MSG_DONTWAIT)
            except BlockingIOError:
                return True
            except OSError:
                return False
            if not data:
                return False
            # a report is checked whole before any of it is taken: the child's fault ends the
            # child; a fault in what takes it (the recorder, the view) is the station's own
            # and is not blamed on a child (found by review: it restarted children for ever)
            self._take(_checked_report(data))

    def _stop_child(self, process: subprocess.Popen[bytes], sock: socket.socket) -> None:
        """Ask the child to stop (it puts the pins in their safe state and closes the board)
        and take its final report; one that does not stop within :data:`_CHILD_STOP_S` (or
        cannot even be told: its socket is full) is killed."""
        with contextlib.suppress(OSError):
            sock.send(pickle.dumps(("stop", None)), socket.MSG_DONTWAIT)
        end = monotonic_s() + _CHILD_STOP_S
        while monotonic_s() < end and not self._final:
            ready, _, _ = select.select([sock], [], [], max(0.0, end - monotonic_s()))
            try:
                if ready and not self._drain(sock):
                    break
            except _BadReport as err:
                log.warning("display process sent a report the station cannot read at its "
                            "stop: %s", err)
                break
        code = _reap(process, max(0.1, end - monotonic_s()))
        if not self._final:
            log.warning("display process did not stop cleanly (exit %s)", code)
        self._no_child()


class _BadReport(Exception):
    """A report from the display child that the station cannot read or fold in."""


def _is_int(value: Any) -> bool:
    return type(value) is int


def _pairs_of_ints(value: Any) -> bool:
    return isinstance(value, list) and all(
        isinstance(p, tuple) and len(p) == 2 and _is_int(p[0]) and _is_int(p[1])
        for p in value)


#: each field of a report and what it must be (see ``display_child``)
_REPORT_FIELDS: dict[str, Any] = {
    "periods": lambda v: isinstance(v, np.ndarray) and v.ndim == 1
    and np.issubdtype(v.dtype, np.floating),
    "loops": lambda v: isinstance(v, tuple) and len(v) == 2 and all(map(_is_int, v)),
    "counters": lambda v: isinstance(v, DisplayLoopCounters),
    "render_stats": lambda v: isinstance(v, RenderStats),
    "display_stats": lambda v: isinstance(v, DisplayStats),
    "superseded": _is_int,
    "priority": lambda v: isinstance(v, tuple) and len(v) == 2,
    "connected": lambda v: type(v) is bool,
    "feedback": lambda v: v is None or isinstance(v, PinFeedback),
    "pins": lambda v: isinstance(v, PinState),
    "safe_since_s": lambda v: v is None or type(v) is float,
    "started_s": lambda v: v is None or type(v) is float,
    "accepted": _pairs_of_ints,
    "rendered": lambda v: isinstance(v, list) and all(
        isinstance(r, tuple) and len(r) == 3 for r in v),
    "pins_samples": lambda v: isinstance(v, list) and all(isinstance(s, tuple) for s in v),
    "shed": _is_int,
    "final": lambda v: type(v) is bool,
}


def _checked_report(data: bytes) -> tuple[str, Any]:
    """One message of the display child, unpickled and checked whole (a report: every field
    present and of its type) before anything of it is taken.

    Raises:
        _BadReport: it does not unpickle, or is no message, or a report is malformed.
    """
    try:
        message = pickle.loads(data)
    except Exception as err:  # whatever a corrupt pickle raises
        raise _BadReport(f"{type(err).__name__}: {err}") from err
    if not (isinstance(message, tuple) and len(message) == 2 and isinstance(message[0], str)):
        raise _BadReport(f"not a (kind, body) message: {type(message).__name__}")
    kind, report = message
    if kind == "report":
        if not isinstance(report, dict):
            raise _BadReport(f"a report that is a {type(report).__name__}, not a dict")
        bad = [name for name, ok in _REPORT_FIELDS.items()
               if name not in report or not ok(report[name])]
        if bad:
            raise _BadReport(f"a report with missing or malformed {', '.join(bad)}")
    return message


def _reap(process: subprocess.Popen[bytes], timeout_s: float) -> int:
    """Wait up to ``timeout_s`` for ``process`` to end, then kill it; its exit code."""
    if timeout_s > 0:
        try:
            return process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            pass
    process.kill()
    return process.wait()
