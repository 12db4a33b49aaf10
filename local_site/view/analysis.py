"""The palpation analysis, re-run in a separate process on what the station has received so far.

The live view shows the relief and stiffness maps and the current findings while the operator
palpates. Building the maps takes a Python loop over every contact frame received, so it runs
in a child process (lowered priority, ``os.nice``) and never in the display loop or the view's
thread: :class:`LiveAnalysis` hands it batches of accepted frames through a
``multiprocessing`` queue (non-blocking for the caller) and collects results the same way.

The child runs :func:`local_site.palpation.maps_and_findings` (maps and
find_tumors; the same code as the demo's final report) at most
every ``interval_s``, and not more often than twice its own last run time, so the analysis
costs at most about a third of a core.

**Confidence** of a finding is its persistence: the share of the last ``history`` analyses
(re-runs on a growing data set) that found a finding within ``max(3 mm, its radius)`` of it.
A tumor seen once after a few frames starts at ``1/history``; one seen in every recent run has
1.0. It says how stable the detection is, not a calibrated probability.
"""

from __future__ import annotations

import base64
import contextlib
import logging
import math
import multiprocessing as mp
import os
import queue
import signal
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from shared.protocol import TactileFrame
from shared.workspace import WorkspaceConfig

__all__ = ["LiveAnalysis", "LiveAnalysisConfig", "encode_map"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LiveAnalysisConfig:
    """Settings of the live analysis.

    Attributes:
        interval_s: shortest time between two runs.
        max_frames: frames kept for the analysis (then new ones are counted, not kept).
        history: runs over which a finding's persistence (confidence) is counted.
        nice: priority increment of the child process (0: unchanged).
    """

    interval_s: float = 2.0
    max_frames: int = 20_000
    history: int = 5
    nice: int = 10


def encode_map(values: NDArray[np.floating]) -> dict[str, Any]:
    """A map as base64 bytes: 0 = no data (NaN), 1..255 = lo..hi linearly.

    Returns:
        ``{"w", "h", "lo", "hi", "data"}`` (row 0 first; lo/hi None when nothing is finite).
    """
    arr = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(arr)
    out = np.zeros(arr.shape, np.uint8)
    lo = hi = None
    if finite.any():
        lo, hi = (float(v) for v in np.percentile(arr[finite], [1.0, 99.0]))
        span = hi - lo if hi > lo else 1.0
        scaled = np.clip((arr[finite] - lo) / span, 0.0, 1.0)
        out[finite] = (1 + np.rint(scaled * 254)).astype(np.uint8)
    return {"w": int(arr.shape[1]), "h": int(arr.shape[0]), "lo": lo, "hi": hi,
            "data": base64.b64encode(out.tobytes()).decode("ascii")}


def _confidence(findings: list[dict[str, Any]], past: list[list[dict[str, Any]]],
                history: int) -> None:
    for f in findings:
        x, y = f["center_mm"]
        radius = max(3.0, float(f["equivalent_radius_mm"]))
        seen = sum(1 for run in past if any(
            math.hypot(g["center_mm"][0] - x, g["center_mm"][1] - y) <= radius for g in run))
        f["confidence"] = seen / history


def _worker(inbox: Any, outbox: Any, workspace: WorkspaceConfig,
            config: LiveAnalysisConfig) -> None:  # pragma: no cover - runs in the child
    from local_site.palpation import maps_and_findings
    from local_site.recording import Recording
    from shared.errors import InputDataError
    from shared.workspace import WorkspaceMap

    # Ctrl-C at a terminal reaches the whole process group: the parent stops this process
    # (None in the inbox) and it exits by itself when the parent dies; a KeyboardInterrupt
    # here would only print a traceback over the parent's clean exit
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if config.nice:
        with contextlib.suppress(OSError):
            os.nice(config.nice)
    wmap = WorkspaceMap(workspace)
    cols: dict[str, list[Any]] = {k: [] for k in ("center", "pitch", "contact", "force",
                                                  "indentation", "height")}
    shape: tuple[int, ...] | None = None
    dropped = 0
    past: list[list[dict[str, Any]]] = []
    last_run = -math.inf
    last_cost = 0.0
    runs = 0
    dirty = False
    parent = mp.parent_process()
    while True:
        try:
            batch = inbox.get(timeout=0.2)
        except queue.Empty:
            batch = {}
            if parent is not None and not parent.is_alive():
                return  # the station died (SIGKILL): no one will send the end; do not linger
        if batch is None:
            return
        for item in batch.get("frames", ()):
            h = item[5]
            if shape is None:
                shape = h.shape
            if h.shape != shape or len(cols["height"]) >= config.max_frames:
                dropped += 1
                continue
            for key, value in zip(cols, item, strict=True):
                cols[key].append(value)
            dirty = True
        now = time.monotonic()
        if not dirty or now - last_run < max(config.interval_s, 2.0 * last_cost):
            continue
        dirty = False
        last_run = now
        n = len(cols["height"])
        rec = Recording(
            platform_t_us=np.zeros(0, np.int64), platform_mm=np.zeros((0, 3)),
            frame_center_mm=np.asarray(cols["center"], np.float64).reshape(n, 2),
            frame_pitch_mm=np.asarray(cols["pitch"], np.float64),
            frame_contact=np.asarray(cols["contact"], bool),
            frame_force_n=np.asarray(cols["force"], np.float64),
            frame_indentation_mm=np.asarray(cols["indentation"], np.float64),
            frame_height_mm=np.stack(cols["height"]).astype(np.float32))
        result: dict[str, Any] = {"run": runs + 1, "frames": n, "frames_dropped": dropped}
        try:
            maps, found = maps_and_findings(rec, wmap)
            findings = [f.to_dict() for f in found]
        except InputDataError as err:
            result.update(state="waiting", reason=str(err), findings=[])
        else:
            past = ([*past, findings])[-config.history:]
            _confidence(findings, past, config.history)
            cell = maps.cell_mm
            result.update(
                state="ok", findings=findings, frames_used=maps.frames_used,
                grid={"x0_mm": float(maps.x_mm[0]), "y0_mm": float(maps.y_mm[0]),
                      "cell_mm": cell},
                relief=encode_map(maps.relief),
                stiffness_n_per_mm=encode_map(maps.stiffness_n_per_mm),
                background_stiffness_n_per_mm=maps.background_stiffness_n_per_mm)
        last_cost = time.monotonic() - now
        runs += 1
        result["run"] = runs
        result["seconds"] = last_cost
        result["cpu_s_total"] = time.process_time()
        outbox.put(result)


class LiveAnalysis:
    """Feeds accepted frames to the analysis process and keeps its newest result.

    Call :meth:`add` and :meth:`poll` from one thread (the view's); :meth:`close` at the end.

    Args:
        workspace: the platform <-> phantom map the session uses.
        config: settings.
    """

    def __init__(self, workspace: WorkspaceConfig,
                 config: LiveAnalysisConfig | None = None) -> None:
        self.config = config or LiveAnalysisConfig()
        ctx = mp.get_context("spawn")
        self._inbox = ctx.Queue()
        self._outbox = ctx.Queue()
        self._proc = ctx.Process(target=_worker, name="teletouch-view-analysis",
                                 args=(self._inbox, self._outbox, workspace, self.config),
                                 daemon=True)
        # started with SIGINT blocked (the mask is inherited through fork and exec): a
        # terminal's Ctrl-C reaches the whole process group, and a child still importing
        # would die of it with a traceback, leaving its queue unread. Here a Ctrl-C
        # meanwhile stays pending and is delivered when the mask is restored: not lost.
        old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            self._proc.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        self._pending: list[tuple[Any, ...]] = []
        self.version = 0
        self.result: dict[str, Any] | None = None
        self.frames_sent = 0

    def add(self, frame: TactileFrame) -> None:
        """Queue one accepted frame (sent with the next :meth:`poll`)."""
        height = frame.layers.get("height_mm")
        if not isinstance(height, np.ndarray) or height.ndim != 2:
            return
        self._pending.append((tuple(float(c) for c in frame.center_mm), float(frame.pitch_mm),
                              bool(frame.contact), float(frame.force_n),
                              float(frame.indentation_mm), height.astype(np.float32)))

    def poll(self) -> bool:
        """Send queued frames, take a new result if any.

        Returns:
            True when a new result arrived (:attr:`result`, :attr:`version`).
        """
        if self._pending:
            self.frames_sent += len(self._pending)
            self._inbox.put({"frames": self._pending})
            self._pending = []
        fresh = False
        while True:
            try:
                self.result = self._outbox.get_nowait()
            except queue.Empty:
                break
            self.version += 1
            fresh = True
        return fresh

    @property
    def alive(self) -> bool:
        """The analysis process is running."""
        return self._proc.is_alive()

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop the process and release the queues (idempotent).

        The child finishes a run before it reads the stop request, and a run can take
        seconds on a loaded machine: after ``timeout_s`` it is terminated (it keeps nothing
        worth saving), so a station's shutdown is never held up by its view.
        """
        if self._proc.is_alive():
            with contextlib.suppress(ValueError, OSError):
                self._inbox.put(None)
            deadline = time.monotonic() + timeout_s
            while self._proc.is_alive() and time.monotonic() < deadline:
                self._drain()  # a child blocked writing its last result cannot exit
                self._proc.join(0.05)
            if self._proc.is_alive():
                log.info("the view's analysis process is busy; terminating it")
                self._proc.terminate()
                self._proc.join(5.0)
        elif self._proc.exitcode not in (None, 0):
            log.info("the view's analysis process ended with code %s", self._proc.exitcode)
        # the child is gone (stopped, terminated, or dead of its own: killed, crashed while
        # starting): no one reads the inbox any more. Batches it never read fill the pipe
        # and block the queue's feeder thread in its write, and joining that thread would
        # hang this process for ever (issue 9: a replay's Ctrl-C). Read back what is there,
        # then do not wait for the feeder.
        self._inbox.cancel_join_thread()
        with contextlib.suppress(queue.Empty, OSError, ValueError, EOFError):
            while True:
                self._inbox.get(timeout=0.05)
        # The outbox is read back only after a clean exit: a child terminated (or dead) in
        # the middle of writing a result leaves half a message in the pipe, and reading it
        # would wait for ever for the rest (this process holds the pipe's write end too, so
        # no end-of-file comes). What is there is discarded anyway.
        if self._proc.exitcode == 0:
            self._drain()
        for q in (self._inbox, self._outbox):
            q.close()
            q.join_thread()

    def _drain(self) -> None:
        with contextlib.suppress(queue.Empty, OSError, ValueError, EOFError):
            while True:
                self._outbox.get_nowait()
