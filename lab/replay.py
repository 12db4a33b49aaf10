"""Play a recording back (``teletouch replay``) and summarise one (``--summary``).

:class:`Replayer` publishes every message of a recording, in recorded order and at the
recorded pace scaled by ``speed``, to its subscribers (:class:`ReplayEvent`; a live view
subscribes with :meth:`Replayer.subscribe`). A local station's recording is also played
into a display through the local station's own path: the received tactile frames go into a
:class:`~local_site.agent.display_loop.DisplayLoop` (scene, safety rules, renderer, display
driver) at the recorded platform positions, on the simulated ArrayTac display by default.

:func:`summarize` gives the streams, message counts, rates, duration and the latency per
hop (p50/p99 from the stamps of the derived ``latency`` channel).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from local_site.agent.display_loop import DisplayLoop, FrameSlot, SameClockLink
from local_site.devices import open_display
from local_site.platform.base import PlatformSample
from local_site.render import Renderer
from local_site.scenes import TactileFrameScene
from shared.errors import ConfigError, InputDataError
from shared.protocol import Message, PlatformState, TactileCompact, TactileFrame, Welcome
from shared.protocol.tactile_codec import TactileDecoder
from shared.recording import McapRecording, RecordedMessage, RecordingFormatError
from shared.timebase import now_us

__all__ = ["PlaybackClock", "ReplayEvent", "ReplayResult", "Replayer", "format_summary",
           "latency_stages", "summarize"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class ReplayEvent:
    """One recorded message as it is replayed.

    Attributes:
        topic: its channel (``/local/rx/tactile_frame``, ``/local/pins``, ...).
        t_us: when it was recorded (wall clock of the recording station).
        message: the protocol message of a wire channel, else None.
        data: the object of a derived JSON channel, else None.
    """

    topic: str
    t_us: int
    message: Message | None
    data: dict[str, Any] | None


#: what :meth:`Replayer.subscribe` takes (called on the replay thread; must be quick)
Subscriber = Callable[[ReplayEvent], None]


@dataclass
class ReplayResult:
    """What a replay did."""

    published: int = 0
    duration_s: float = 0.0
    recorded_duration_s: float = 0.0
    frames_to_display: int = 0
    display: dict[str, Any] = field(default_factory=dict)
    subscriber_errors: int = 0
    #: messages whose payload does not decode (a wire message off the protocol, a derived
    #: one that is not a JSON object): skipped, the replay goes on
    undecodable: int = 0


class PlaybackClock:
    """The replay's position in recorded time, with pause and play (thread-safe).

    While playing, the position advances ``speed`` recorded microseconds per wall-clock
    microsecond from where it was last anchored; while paused it stands still. It never
    passes ``end_us``.

    Args:
        start_us: the recorded time the replay starts at.
        end_us: the recorded time of the last message.
        speed: playback speed (> 0).
        paused: start paused (:meth:`play` starts it).
    """

    def __init__(self, start_us: int, end_us: int, speed: float, *, paused: bool = False) -> None:
        self.start_us = int(start_us)
        self.end_us = max(int(end_us), self.start_us)
        self.speed = float(speed)
        self._cond = threading.Condition()
        self._anchor_us = float(start_us)
        self._anchor_s = time.perf_counter()
        self._paused = paused
        #: :meth:`start` was called (before it, the position stands at the start)
        self.started = False
        self.finished = False

    def _position(self, now_s: float) -> float:
        if self._paused or self.finished or not self.started:
            return self._anchor_us
        return self._anchor_us + (now_s - self._anchor_s) * 1e6 * self.speed

    def position_us(self) -> int:
        """The recorded time the replay has reached now."""
        with self._cond:
            return int(min(self._position(time.perf_counter()), self.end_us))

    @property
    def paused(self) -> bool:
        """True while paused."""
        return self._paused

    def start(self) -> None:
        """Start counting from now (from the start position; a paused clock waits for
        :meth:`play`)."""
        with self._cond:
            self._anchor_us = float(self.start_us)
            self._anchor_s = time.perf_counter()
            self.started = True
            self.finished = False
            self._cond.notify_all()

    def pause(self) -> None:
        """Stop the position where it is (idempotent)."""
        with self._cond:
            if not self._paused:
                self._anchor_us = min(self._position(time.perf_counter()), self.end_us)
                self._paused = True
                self._cond.notify_all()

    def play(self) -> None:
        """Go on from where it stands (idempotent)."""
        with self._cond:
            if self._paused:
                self._anchor_s = time.perf_counter()
                self._paused = False
                self._cond.notify_all()

    def finish(self) -> None:
        """The replay ended: the position stands at the end from now on."""
        with self._cond:
            self._anchor_us = float(self.end_us)
            self.finished = True
            self._cond.notify_all()

    def wait_until(self, t_us: int, stop: threading.Event) -> bool:
        """Block until the position reaches ``t_us`` (recorded time).

        Returns:
            False when ``stop`` was set first.
        """
        with self._cond:
            while not stop.is_set():
                now_s = time.perf_counter()
                if not self._paused and self._position(now_s) >= t_us:
                    return True
                # paused: poll the stop event now and then; playing: sleep until due
                wait = 0.1 if self._paused else min(
                    0.1, (t_us - self._position(now_s)) / 1e6 / self.speed)
                self._cond.wait(wait)
        return False


class Replayer:
    """Replays one recording (see the module docstring).

    Args:
        recording: the recording (:func:`shared.recording.read_mcap`).
        speed: playback speed (2.0: twice as fast); > 0.
        display: display spec for a local recording (``sim``; ``none``: publish only).
        stale_timeout_s: the display loop's stale-frame rule at speed 1 (scaled by 1/speed).
        start_paused: wait for :meth:`PlaybackClock.play` (``replayer.clock.play()``) before
            the first message.

    Raises:
        ConfigError: a bad speed or display spec.
    """

    def __init__(self, recording: McapRecording, *, speed: float = 1.0, display: str = "sim",
                 stale_timeout_s: float = 0.1, start_paused: bool = False) -> None:
        if not (np.isfinite(speed) and speed > 0):
            raise ConfigError(f"replay speed must be > 0, got {speed}")
        self.recording = recording
        self.speed = float(speed)
        self.display_spec = display
        self.stale_timeout_s = stale_timeout_s / self.speed
        self._subscribers: list[Subscriber] = []
        self.loop: DisplayLoop | None = None
        self._messages = sorted(recording.messages, key=lambda m: m.t_us)
        first = self._messages[0].t_us if self._messages else 0
        last = self._messages[-1].t_us if self._messages else 0
        #: the replay's position in recorded time; pause() / play() from any thread
        self.clock = PlaybackClock(first, last, self.speed, paused=start_paused)

    def subscribe(self, fn: Subscriber) -> None:
        """Call ``fn`` with every replayed event (a live view plugs in here)."""
        self._subscribers.append(fn)

    @staticmethod
    def event(m: RecordedMessage) -> ReplayEvent:
        """The event of one recorded message (decoded).

        Raises:
            RecordingFormatError: a payload does not decode.
        """
        if m.wire is not None:
            return ReplayEvent(m.topic, m.t_us, m.decode(), None)
        data = m.json() if m.encoding == "json" else None
        return ReplayEvent(m.topic, m.t_us, None, data)

    def _build_loop(self) -> tuple[DisplayLoop, FrameSlot, list[PlatformSample | None]]:
        position: list[PlatformSample | None] = [None]
        scene = TactileFrameScene()
        slot = FrameSlot(prepare=scene.prepare)
        display = open_display(self.display_spec, connect=False)
        loop = DisplayLoop(display, Renderer(), scene,
                           positions=lambda: position[0], platform_ok=lambda: True,
                           frames=slot, link=SameClockLink(),
                           stale_timeout_s=self.stale_timeout_s)
        return loop, slot, position

    def run(self, stop: threading.Event | None = None) -> ReplayResult:
        """Replay to the end (or until ``stop`` is set); blocking. A message whose payload
        does not decode is skipped and counted (``undecodable``; the first is logged).

        Raises:
            DeviceError: the display cannot be opened.
        """
        stop = stop or threading.Event()
        messages = self._messages
        result = ReplayResult()
        if not messages:
            self.clock.finish()
            return result
        t0 = messages[0].t_us
        result.recorded_duration_s = (messages[-1].t_us - t0) / 1e6
        local = self.recording.station == "local" and self.display_spec != "none"
        loop_stop = threading.Event()
        thread: threading.Thread | None = None
        slot: FrameSlot | None = None
        position: list[PlatformSample | None] = [None]
        if local:
            self.loop, slot, position = self._build_loop()
            self.loop.display.connect()
            thread = threading.Thread(target=self.loop.run_in_thread, args=(loop_stop,),
                                      name="replay-display", daemon=True)
            thread.start()
        start = time.perf_counter()
        clock = self.clock
        clock.start()  # the pace counts from here, not from construction
        decoder = TactileDecoder()
        try:
            for m in messages:
                if not clock.wait_until(m.t_us, stop):
                    break
                try:
                    ev = self.event(m)
                except RecordingFormatError as err:  # one bad payload must not end it
                    result.undecodable += 1
                    if result.undecodable == 1:
                        log.warning("replay: %s (skipped; more are counted)", err)
                    continue
                frame = ev.message
                if isinstance(frame, Welcome):  # a new link session, as the station did
                    decoder.reset()
                if isinstance(frame, TactileCompact) and m.topic.endswith("/rx/tactile_compact"):
                    try:  # in order, as the station decoded them
                        frame = decoder.decode(frame)
                    except InputDataError:
                        frame = None
                if slot is not None and isinstance(frame, TactileFrame) \
                        and m.topic.endswith(("/rx/tactile_frame", "/rx/tactile_compact")):
                    # captured "now" in replay time: the recorded capture stamps are on
                    # another clock and from another day; the loop's age rule must judge
                    # the replay's pacing, not the recording's date
                    t = now_us()
                    slot.put(dataclasses.replace(frame, ts_us=t), t)
                    result.frames_to_display += 1
                elif isinstance(ev.message, PlatformState) and \
                        m.topic.endswith("/tx/platform_state"):
                    position[0] = PlatformSample(position_mm=ev.message.position_mm,
                                                 velocity_mm_s=ev.message.velocity_mm_s,
                                                 t_us=now_us(), seq=ev.message.seq,
                                                 board_t_us=ev.message.ts_us)
                for fn in self._subscribers:
                    try:
                        fn(ev)
                    except Exception as err:  # a subscriber must not end the replay
                        result.subscriber_errors += 1
                        if result.subscriber_errors == 1:
                            log.warning("replay subscriber failed: %s", err)
                result.published += 1
        finally:
            clock.finish()
            loop_stop.set()
            if thread is not None and self.loop is not None:
                thread.join()
                self.loop.finish("replay_end")
                c = self.loop.counters
                result.display = {"frames_accepted": c.frames_accepted,
                                  "frames_rendered": c.frames_rendered,
                                  "frames_rejected": c.frames_rejected,
                                  "commands_sent": c.commands_sent,
                                  "safe_entries": dict(c.safe_entries),
                                  **self.loop.periods.summary()}
                self.loop.display.disconnect()
        result.duration_s = time.perf_counter() - start
        return result


def latency_stages(obj: dict[str, Any]) -> tuple[dict[str, float | None], int]:
    """The stages of a ``latency`` message, ``end_to_end`` last, and how many values were
    left out as malformed (a value neither a finite number nor null, or ``stages_ms`` not
    an object: the file is input; a string there must not stop the summary)."""
    stages = obj.get("stages_ms")
    items = list(stages.items()) if isinstance(stages, dict) else []
    bad = 0 if stages is None or isinstance(stages, dict) else 1
    out: dict[str, float | None] = {}
    for name, v in [*items, ("end_to_end", obj.get("end_to_end_ms"))]:
        if v is None:
            out[str(name)] = None
        elif isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v):
            out[str(name)] = float(v)
        else:
            bad += 1
    return out, bad


def _pcts(values: list[float | None]) -> dict[str, float | int | None]:
    arr = np.asarray([v for v in values if v is not None], dtype=float)
    if arr.size == 0:
        return {"count": 0, "p50": None, "p99": None, "max": None}
    return {"count": int(arr.size), "p50": float(np.percentile(arr, 50)),
            "p99": float(np.percentile(arr, 99)), "max": float(arr.max())}


def summarize(recording: McapRecording) -> dict[str, Any]:
    """Streams, counts, rates, duration and per-hop latency of a recording (JSON-able)."""
    msgs = recording.messages
    t = np.asarray([m.t_us for m in msgs], dtype=np.int64)
    duration_s = float(t.max() - t.min()) / 1e6 if t.size > 1 else 0.0
    streams: dict[str, dict[str, Any]] = {}
    for topic in sorted(recording.topics()):
        tt = np.asarray([m.t_us for m in recording.on(topic)], dtype=np.int64)
        span = float(tt.max() - tt.min()) / 1e6 if tt.size > 1 else 0.0
        first = next(recording.on(topic))
        streams[topic] = {"count": int(tt.size), "encoding": first.encoding,
                          "rate_hz": (tt.size - 1) / span if span > 0 else None}
    latency: dict[str, dict[str, dict[str, Any]]] = {}
    malformed = 0
    for topic in streams:
        if not topic.endswith("/latency"):
            continue
        per: dict[str, dict[str, list[float | None]]] = {}
        for m in recording.on(topic):
            try:
                obj = m.json()
            except RecordingFormatError:  # not a JSON object: left out, counted
                malformed += 1
                continue
            stages = per.setdefault(str(obj.get("type")), {})
            values, bad = latency_stages(obj)
            malformed += bad
            for name, v in values.items():
                stages.setdefault(name, []).append(v)
        for msg_type, stages in per.items():
            latency[f"{topic} {msg_type}"] = {k: _pcts(v) for k, v in stages.items()}
    return {"path": str(recording.path), "station": recording.station,
            "complete": recording.complete, "stop_reason": recording.stop_reason,
            "skipped_chunks": recording.skipped_chunks,
            "skipped_reason": recording.skipped_reason,
            "unreadable_messages": recording.unreadable_messages,
            "messages": len(msgs), "duration_s": duration_s, "streams": streams,
            "latency_ms": latency, "latency_malformed_values": malformed,
            "end": recording.end.get("counts", {})}


def _f(v: Any, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def format_summary(s: dict[str, Any]) -> str:
    """The human-readable summary."""
    state = "complete" if s["complete"] else f"INCOMPLETE ({s['stop_reason']}): read up to " \
        "the last complete chunk"
    lines = [f"{s['path']}: {s['station']} station, {s['messages']} messages over "
             f"{s['duration_s']:.2f} s, {state}"]
    if s.get("skipped_chunks"):
        lines.append(f"  CORRUPT: {s['skipped_chunks']} chunks skipped, their messages are "
                     f"missing ({s['skipped_reason']})"
                     + (f"; {s['unreadable_messages']} more on channels defined only there"
                        if s.get("unreadable_messages") else ""))
    end = s["end"]
    dropped = end.get("dropped_queue_full")
    if dropped is not None:
        lost = end.get("messages_lost")  # not counted by recordings made before it was
        lines.append(f"  recorder: {end.get('messages_written')} written, {dropped} "
                     f"dropped (queue full), {end.get('write_errors', 0)} write errors"
                     + ("" if lost is None else f", {lost} lost (write failed)"))
        if end.get("write_errors") or lost:
            lines.append("  WARNING: the recorder could not write everything: messages are "
                         "missing from this file")
    lines.append(f"  {'stream':<34} {'encoding':<8} {'count':>7} {'rate Hz':>9}")
    for topic, st in s["streams"].items():
        lines.append(f"  {topic:<34} {st['encoding']:<8} {st['count']:>7} "
                     f"{_f(st['rate_hz'], 1):>9}")
    if s.get("latency_malformed_values"):
        lines.append(f"  latency: {s['latency_malformed_values']} malformed values (not a "
                     "number, or a message not a JSON object) left out")
    for name, stages in s["latency_ms"].items():
        lines.append(f"  latency (ms) {name}:{'':<10}{'count':>7} {'p50':>8} {'p99':>8}")
        for stage, fig in stages.items():
            lines.append(f"    {stage:<40} {fig['count']:>7} {_f(fig['p50']):>8} "
                         f"{_f(fig['p99']):>8}")
    return "\n".join(lines)
