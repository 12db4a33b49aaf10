"""The display process's entry point: ``python -m local_site.agent.display_child``.

A module of its own, which the package does not import, so that ``-m`` runs it once (see
:mod:`local_site.agent.display_process` for what the child does and how it talks to the
station).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import errno
import json
import logging
import pickle
import signal
import socket
import sys
import threading
import time
from collections.abc import Iterable, Mapping
from typing import Any, Protocol

from local_site.agent.display_loop import (
    DisplayLoop,
    DisplayLoopCounters,
    FrameSlot,
    thread_realtime,
)
from local_site.agent.display_process import HEARTBEAT_S, MAX_MESSAGE_BYTES, LinkMirror
from local_site.agent.platform_process import RecordView, SampleRecord
from local_site.devices import open_display
from local_site.recording import PinsSample, PinsSampler
from local_site.render import Renderer, RendererConfig
from local_site.scenes import SceneSource, TactileFrameScene, open_scene
from shared.gil import switch_interval
from shared.memlock import memory_locked
from shared.motion_to_touch import MotionToTouchLedger, StageTrace, trace_hops
from shared.protocol import Hop
from shared.timebase import adopt_wall_anchor, monotonic_s

__all__ = ["main"]

log = logging.getLogger(__name__)

#: tries of the final report while the station's socket is busy (10 ms apart)
_FINAL_TRIES = 100
#: accepted frames and rendered frames' hops kept for a station that takes no report
_KEEP_PENDING = 256
#: halvings of what waits, at most, to fit one report into a packet
_MAX_SHEDS = 12


class _TappedLedger(MotionToTouchLedger):
    """The loop's ledger: each rendered frame's hops go to the station, whose ledger is the
    one the summary reads and accounts them (here they are only traced, for the loop)."""

    def __init__(self) -> None:
        super().__init__(window=1)
        self.rendered: collections.deque[tuple[tuple[Hop, ...], dict[str, Any], float]] = \
            collections.deque(maxlen=4096)

    def add_hops(self, hops: Iterable[Hop],
                 offsets_us: Mapping[str, float | None]) -> StageTrace:
        hops = tuple(hops)
        self.rendered.append((hops, dict(offsets_us), monotonic_s()))
        return trace_hops(hops, offsets_us)


class _PinsTap:
    """The loop's recorder in the child: it samples the pins for the station's recorder
    (at its rate, stamped when read) and keeps the samples for the next report; accepted
    frames go to the station through the reporter (:meth:`_Reporter.frame_accepted`)."""

    def __init__(self, rate_hz: float) -> None:
        self._sampler = PinsSampler(rate_hz)
        self.samples: collections.deque[PinsSample] = collections.deque(maxlen=4096)

    def add_frame(self, frame: Any, rx_us: int) -> None:
        """Nothing: the reporter tells the station of accepted frames."""

    def add_pins(self, commanded: Any, display: Any, safe_reason: str | None) -> None:
        sample = self._sampler.offer(commanded, display, safe_reason)
        if sample is not None:
            self.samples.append(sample)


def _drain(queue: collections.deque[Any]) -> list[Any]:
    out = []
    while queue:
        out.append(queue.popleft())
    return out


def _copy_counters(c: DisplayLoopCounters) -> DisplayLoopCounters:
    """A copy of the loop's counters (their dict and list too: the loop goes on meanwhile)."""
    return dataclasses.replace(c, safe_entries=dict(c.safe_entries),
                               link_loss_to_safe_ms=list(c.link_loss_to_safe_ms))


class _Reporter:
    """What the station reads, sent every heartbeat (and once more at the end). What a report
    carries once (new periods, accepted frames, rendered hops, new feedback) is given up only
    when the report went out: a report the station's busy socket refused is not a loss."""

    def __init__(self, loop: DisplayLoop, ledger: _TappedLedger, sock: socket.socket,
                 frames: FrameSlot | None, pins: _PinsTap | None = None) -> None:
        self.loop = loop
        self.ledger = ledger
        self.pins = pins
        self.sock = sock
        self.frames = frames
        self.accepted: collections.deque[tuple[int, int]] = collections.deque(maxlen=4096)
        self._recorded = 0
        self._feedback: Any = None
        self._lock = threading.Lock()
        self._accepted: list[tuple[int, int]] = []
        self._rendered: list[Any] = []
        self._pins_samples: list[PinsSample] = []
        #: reports the station's socket did not take (busy or gone)
        self.dropped = 0
        #: items given up because a report no longer fitted a packet
        self.shed = 0
        self._shed_warned = False

    def frame_accepted(self, frame: Any, rx_us: int) -> None:
        self.accepted.append((frame.seq, rx_us))

    def send(self, final: bool = False, connected: bool | None = None) -> None:
        """Report (``final``: the last one, sent even when the station's socket is busy for
        a while; ``connected``: whether the board was connected, read before it was
        closed)."""
        loop = self.loop
        with self._lock:
            if connected is None:
                connected = loop.display.is_connected
            feedback = loop.display.latest_feedback() if connected else None
            self._accepted += _drain(self.accepted)
            self._rendered += [(tuple((h.clock, h.stage, h.t_us) for h in hops), offsets, at)
                               for hops, offsets, at in _drain(self.ledger.rendered)]
            if self.pins is not None:
                self._pins_samples += _drain(self.pins.samples)
            # a station that takes nothing for long gets the newest (a report fits a packet)
            del self._accepted[:-_KEEP_PENDING], self._rendered[:-_KEEP_PENDING]
            del self._pins_samples[:-_KEEP_PENDING]
            tries = _FINAL_TRIES if final else 1
            sheds = 0
            while tries > 0:
                tries -= 1
                recorded, periods = loop.periods.since(self._recorded)
                report = {"periods": periods,
                          "loops": (loop.periods.iterations, loop.periods.overruns),
                          "counters": _copy_counters(loop.counters),
                          "render_stats": dataclasses.replace(loop.renderer.stats),
                          "display_stats": loop.display.stats(),
                          "superseded": 0 if self.frames is None else self.frames.superseded,
                          "priority": (loop.priority_applied, loop.realtime_applied),
                          "connected": connected,
                          "feedback": feedback if feedback is not self._feedback else None,
                          "pins": loop.pin_state,
                          # the open safe episode (the final report's is counted already)
                          "safe_since_s": None if final else loop.safe_since_s,
                          "started_s": loop.started_s,
                          "accepted": self._accepted,
                          "rendered": self._rendered, "pins_samples": self._pins_samples,
                          "shed": self.shed, "final": final}
                try:
                    self.sock.send(pickle.dumps(("report", report), protocol=5),
                                   socket.MSG_DONTWAIT)
                except BlockingIOError:  # the station is busy: the next report carries it
                    if tries:
                        time.sleep(0.01)
                    continue
                except OSError as err:
                    if err.errno != errno.EMSGSIZE:
                        break  # the station is gone (the receiver stops us)
                    self._shed(recorded)  # too much kept for one packet: the oldest go
                    if sheds < _MAX_SHEDS:
                        sheds += 1
                        tries += 1  # at once, smaller
                    continue
                self._recorded = recorded
                self._feedback = feedback
                self._accepted, self._rendered, self._pins_samples = [], [], []
                return
            self.dropped += 1

    def _shed(self, recorded: int) -> None:
        """Give up the older half of what waits to be reported, and the loop periods not yet
        reported (counted in :attr:`shed`): a report that no longer fits one packet."""
        for pending in (self._accepted, self._rendered, self._pins_samples):
            n = (len(pending) + 1) // 2
            self.shed += n
            del pending[:n]
        self.shed += recorded - self._recorded
        self._recorded = recorded
        if not self._shed_warned:
            self._shed_warned = True
            log.warning("display process: a report too large for a packet; the oldest "
                        "accepted frames, pins samples and loop periods were given up")

    def run(self, stop: threading.Event) -> None:
        while not stop.wait(HEARTBEAT_S):
            self.send()


#: the thread named in the log when its real-time priority is refused
_RECEIVING_THREAD = "display process: its receiving thread"


class _Loop(Protocol):
    """What the receiving thread reads of the display loop."""

    started_s: float | None
    realtime_applied: int | None


def _follow_the_loop(loop: _Loop, scheduling: contextlib.ExitStack) -> bool:
    """Once the loop runs (its scheduling decided), run this thread ``SCHED_FIFO`` one below
    the loop's real-time priority, if it has one above 1, until ``scheduling`` closes;
    return whether that is decided."""
    if loop.started_s is None:
        return False
    priority = (loop.realtime_applied or 0) - 1
    if priority >= 1:  # else an ordinary loop (or at the lowest level): an ordinary thread
        scheduling.enter_context(thread_realtime(priority, who=_RECEIVING_THREAD))
    return True


def _receive(sock: socket.socket, frames: FrameSlot | None, link: LinkMirror | None,
             stop: threading.Event, loop: _Loop | None = None) -> None:
    """Frames, the link's state and ``stop`` from the station; the end of the socket (the
    station is gone) stops the loop too.

    ``loop``: once it runs under ``SCHED_FIFO`` (the priority it was actually given, above
    1), this thread runs one level below it. A frame then reaches the loop as soon as it
    arrives, not when the scheduler next runs an ordinary thread on a busy machine; the work
    per message is small (a receive, an unpickle, the hand-over) and the station, not a
    device, is the only sender.
    """
    following = loop
    with contextlib.ExitStack() as scheduling:
        try:
            while not stop.is_set():
                data = sock.recv(MAX_MESSAGE_BYTES)
                if not data:
                    break
                if following is not None and _follow_the_loop(following, scheduling):
                    following = None
                message = pickle.loads(data)
                kind = message[0]
                if kind == "frame" and frames is not None:
                    frames.put(message[1], message[2])
                elif kind == "link" and link is not None:
                    link.update(message[1])
                elif kind == "stop":
                    break
        except OSError as err:
            log.info("display process: the station's socket failed: %s", err)
        finally:
            stop.set()


def _scene(settings: dict[str, Any]) -> SceneSource:
    order = int(settings["order"])
    if settings["remote"]:
        return TactileFrameScene(order=order)
    return open_scene(settings["scene"], interpolation_order=order)


def main(argv: list[str] | None = None) -> int:  # pragma: no cover - runs in the child
    """The child: open the board, run the display loop until ``stop``, the end of the
    station's socket, or the station's death; then the pins' safe state and a final report.

    Args:
        argv: ``[settings JSON]`` (written by :class:`~local_site.agent.display_process.
            DisplayProcess`).

    Returns:
        0.
    """
    settings = json.loads((sys.argv[1:] if argv is None else argv)[0])
    adopt_wall_anchor(int(settings["anchor_ns"]))  # stamps on the station's clock
    logging.basicConfig(level=int(settings["log_level"]),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # the station stops us through the socket (a Ctrl-C at the terminal, or systemd's SIGTERM
    # to the whole unit, reaches the station, which parks the pins through us)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    sock = socket.socket(fileno=int(settings["sock_fd"]))
    platform = RecordView(SampleRecord(int(settings["record_fd"])),
                          float(settings["read_timeout_s"]))
    display = open_display(settings["display"], connect=False, **settings["display_options"])
    remote = bool(settings["remote"])
    link = LinkMirror() if remote else None
    frames = FrameSlot() if remote else None  # prepared in the loop: no second busy thread
    ledger = _TappedLedger()
    pins_rate_hz = settings["pins_rate_hz"]
    pins = None if pins_rate_hz is None else _PinsTap(float(pins_rate_hz))
    loop = DisplayLoop(display, Renderer(RendererConfig(**settings["render"])),
                       _scene(settings), positions=lambda: platform.latest,
                       platform_ok=lambda: platform.healthy, frames=frames, link=link,
                       ledger=ledger, recorder=pins, **settings["loop"])
    reporter = _Reporter(loop, ledger, sock, frames, pins)
    loop.frame_listener = reporter.frame_accepted
    stop = threading.Event()
    # frames to the loop at once: real-time just below the loop, once it is real-time
    threads = [threading.Thread(target=_receive, args=(sock, frames, link, stop, loop),
                                name="display-receive", daemon=True),
               threading.Thread(target=reporter.run, args=(stop,), name="display-report",
                                daemon=True)]
    for thread in threads:
        thread.start()
    with contextlib.ExitStack() as process_settings:
        process_settings.enter_context(switch_interval(float(settings["gil_switch_interval_s"])))
        process_settings.enter_context(memory_locked(bool(settings["lock_memory"])))
        try:
            loop.run_in_thread(stop, int(settings["nice"]), int(settings["realtime"]))
        finally:
            stop.set()
            threads[1].join()
            loop.finish("shutdown")
            connected = display.is_connected
            with contextlib.suppress(Exception):
                display.disconnect()
            # the board's counters, its last feedback (kept by the driver) and the pins' state
            reporter.send(final=True, connected=connected)
    return 0


if __name__ == "__main__":
    sys.exit(main())
