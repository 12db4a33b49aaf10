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
* child -> station: a report every :data:`HEARTBEAT_S` (new loop periods, counters, the pin
  state when it changed, the board's newest feedback, the frames the loop accepted and the
  hops of the frames it rendered) and a final one when it stops.

Safety, as in the station's own loop, and more:

* the child judges every frame by its capture stamp on the station's clock (it adopts the
  station's wall-clock anchor), so a frame held anywhere is never rendered as fresh;
* a station that goes silent (stopped, starved, dead) counts as a lost link in the child after
  two heartbeats: the pins go to their safe state within ``link_loss_timeout_s`` of that;
  the end of the socket (the station is gone) stops the child, which puts the pins in their
  safe state and closes the board;
* the station sends frames without waiting: a child that does not take them loses frames
  (counted as superseded), never the station's event loop;
* a child that died or whose reports stopped for ``hang_timeout_s`` is (killed and) started
  again with the device backoff; meanwhile the board's own watchdog holds the pins safe. The
  counters of the children that ended carry over.
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

from local_site.agent.display_loop import DisplayLoopCounters, PinState
from local_site.agent.period_stats import PeriodStats
from local_site.display.base import DisplayStats, PinFeedback
from local_site.render import RendererConfig
from local_site.render.renderer import RenderStats
from shared.errors import ConfigError
from shared.freshness import ClockView
from shared.motion_to_touch import MotionToTouchLedger
from shared.protocol import TactileFrame
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
#: frames kept after sending, to record and show the ones the loop accepts
_KEEP_SENT = 64
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


class _DisplayMirror:
    """The board as the station sees it through the child's reports (for the view, the
    recorder and the summary)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.is_connected = False
        self._feedback: PinFeedback | None = None
        self._stats = DisplayStats()

    def latest_feedback(self) -> PinFeedback | None:
        return self._feedback

    def stats(self) -> DisplayStats:
        return self._stats

    def disconnect(self) -> None:
        """The child closed the board when it stopped; its last feedback stays readable."""
        self.is_connected = False


class _RendererMirror:
    def __init__(self) -> None:
        self.stats = RenderStats()


class _Frames:
    """The station's frame hand-over to the child (the ``FrameSlot`` it replaces: ``put``,
    ``put_count``, ``superseded``). Never waits: a frame the child's socket cannot take now
    is dropped and counted as superseded."""

    prepare = None

    def __init__(self) -> None:
        self.sock: socket.socket | None = None
        self.put_count = 0
        self.superseded = 0
        self.too_large = 0
        self._lock = threading.Lock()
        self._sent: collections.OrderedDict[tuple[int, int], TactileFrame] = \
            collections.OrderedDict()

    def put(self, frame: TactileFrame, rx_us: int) -> None:
        self.put_count += 1
        sock = self.sock
        try:
            if sock is None:
                raise BlockingIOError("no display process")
            sock.send(pickle.dumps(("frame", frame, rx_us), protocol=5), socket.MSG_DONTWAIT)
        except BlockingIOError:
            self.superseded += 1
            return
        except OSError as err:  # the child is gone (the supervisor starts it again) or too big
            self.superseded += 1
            if err.errno == errno.EMSGSIZE:
                self.too_large += 1
                if self.too_large == 1:
                    log.warning("a tactile frame too large for the display process: %s", err)
            return
        with self._lock:
            self._sent[(frame.seq, rx_us)] = frame
            while len(self._sent) > _KEEP_SENT:
                self._sent.popitem(last=False)

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
        hang_timeout_s: a child whose reports stopped this long is killed and started again.
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
        self.frames = _Frames()
        self.display = _DisplayMirror(display)
        self.renderer = _RendererMirror()
        self.periods = PeriodStats(1.0 / rate_hz)
        self.pin_state = PinState()
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
        #: the counters, iterations and overruns of the children that ended
        self._base = DisplayLoopCounters()
        self._base_iterations = 0
        self._base_overruns = 0
        self._child_counters = DisplayLoopCounters()
        self._child_loops = (0, 0)
        self._child_pins_seq = -1
        self._last_report_s = 0.0
        self._final = False

    # ------------------------------------------------------------------ loop-like reads

    @property
    def counters(self) -> DisplayLoopCounters:
        """The loop's counters, those of ended children included."""
        return fold_counters(self._base, self._child_counters)

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
        self._last_report_s = monotonic_s()
        _, periods = report["periods"]
        iterations, overruns = report["loops"]
        self._child_loops = (iterations, overruns)
        self.periods.extend(periods, self._base_iterations + iterations,
                            self._base_overruns + overruns)
        self._child_counters = report["counters"]
        self.renderer.stats = report["render_stats"]
        self.priority_applied, self.realtime_applied = report["priority"]
        display = self.display
        display.is_connected = report["connected"]
        if report["feedback"] is not None:
            display._feedback = report["feedback"]
        if report.get("display_stats") is not None:
            display._stats = report["display_stats"]
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
            trace = self.ledger.add_hops(hops, offsets)
            if trace.end_to_end_us is not None:
                self.recent_e2e_ms.append(trace.end_to_end_us / 1e3)
            self.last_trace = (trace.stages_us, trace.end_to_end_us, at_s)
        pins: PinState = report["pins"]
        if pins.seq != self._child_pins_seq or self.pin_state.safe_reason == NO_WORD:
            self._child_pins_seq = pins.seq
            self.pin_state = PinState(pins.command, pins.safe_reason, self.pin_state.seq + 1)
        if self.recorder is not None:
            state = self.pin_state
            self.recorder.add_pins(state.command, display, state.safe_reason)
        if report["final"]:
            self._final = True

    def _silent(self) -> None:
        """No report for :data:`SILENCE_S`: what the station shows of the pins is not known
        now, so no command is shown as on them (never an old state as the current one)."""
        if self.pin_state.safe_reason != NO_WORD and not self._final:
            self.pin_state = PinState(None, NO_WORD, self.pin_state.seq + 1)

    def _retire(self) -> None:
        """An ended child's counters become the base of the next one's."""
        self._base = self.counters
        self._base_iterations += self._child_loops[0]
        self._base_overruns += self._child_loops[1]
        self._child_counters = DisplayLoopCounters()
        self._child_loops = (0, 0)
        self._child_pins_seq = -1
        self._no_child()

    def _no_child(self) -> None:
        """No child drives the board now: no command is shown as on the pins (the board's
        watchdog, or the child's last act, put them in their safe state)."""
        if not self._final:
            self.display.is_connected = False
            self.pin_state = PinState(None, NO_WORD, self.pin_state.seq + 1)

    # ------------------------------------------------------------------ the child

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
                stdin=subprocess.DEVNULL,
                pass_fds=(theirs.fileno(), record_fd), process_group=0)
        except OSError as err:
            ours.close()
            self._spawn_error = f"could not start: {err}"
            return None
        finally:
            theirs.close()
        return process, ours

    def run_in_thread(self, stop: threading.Event, nice: int = 0, realtime: int = 0) -> None:
        """Start the child and serve it until ``stop`` is set; start it again, with backoff,
        when it ends unasked or hangs (a station never gives up). Blocking: call from a
        thread. ``nice`` and ``realtime`` are applied to the child's loop thread."""
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

    _spawned_s = 0.0
    _spawn_error = "could not start"
    #: the child's command after the interpreter (an instrumented child may replace it)
    child_argv: tuple[str, ...] = ("-m", "local_site.agent.display_child")

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
        unasked, or None when ``stop`` ended it."""
        self._spawned_s = monotonic_s()
        self._last_report_s = 0.0
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
            if ready and not self._drain(sock):
                process.wait()
                return f"exited with {process.returncode}"
            if process.poll() is not None:
                return f"exited with {process.returncode}"
            beat = max(self._last_report_s, self._spawned_s)
            if monotonic_s() - beat > SILENCE_S:
                self._silent()
            if monotonic_s() - beat > self._hang_timeout_s:
                process.kill()
                process.wait()
                return f"hung (no report for {monotonic_s() - beat:.1f} s): killed"

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
            self._take(pickle.loads(data))

    def _stop_child(self, process: subprocess.Popen[bytes], sock: socket.socket) -> None:
        """Ask the child to stop (it puts the pins in their safe state and closes the board)
        and take its final report."""
        with contextlib.suppress(OSError):
            sock.send(pickle.dumps(("stop", None)))
        end = monotonic_s() + _CHILD_STOP_S
        while monotonic_s() < end:
            ready, _, _ = select.select([sock], [], [], max(0.0, end - monotonic_s()))
            if ready and not self._drain(sock):
                break
        try:
            process.wait(max(0.1, end - monotonic_s()))
        except subprocess.TimeoutExpired:
            log.warning("display process did not stop in %.1f s: killed", _CHILD_STOP_S)
            process.kill()
            process.wait()
        self._no_child()
