"""The local station agent: platform -> relay, tactile frames -> pins, safely.

:class:`LocalAgent` wires the parts together and runs them until a stop condition:

* a :class:`~local_site.agent.platform_reader.PlatformReader` thread takes every platform
  sample (the driver streams at the board rate, >= 500 Hz);
* the *uplink* task sends the newest sample as a ``platform_state`` at
  ``platform_send_rate_hz`` (latest wins), stamped ``Hop("local", "capture", ts)`` after
  ``Hop("local", "motion", previous ts)`` (the previous message's sample);
* the *receive* task takes ``tactile_frame`` (handed to the display loop), ``arm_state``,
  ``stats`` (kept by the link for clock offsets) and ``error`` messages;
* the :class:`~local_site.agent.display_loop.DisplayLoop` renders at the refresh rate in a
  thread (default), a task, or a process of its own with the board link
  (:mod:`local_site.agent.display_process`, ``render_loop = "process"``; the platform is then
  read in a process of its own too), with the safe-state rules;
* a status task redraws the terminal status line.

Without a relay (``scene`` set), the same loop renders a local shape or layer file.
Stop conditions: ``duration_s``, the scripted motion finished (``until_motion_done``),
SIGTERM/SIGINT (when ``handle_signals``), :meth:`LocalAgent.request_stop`, or a final
refusal by the relay (exit code 1). On stop: the display goes to its safe state and is
closed, the platform is closed, the link says bye, then the record and summary are written.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import os
import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from local_site.agent.config import LocalAgentConfig
from local_site.agent.display_loop import DisplayLoop, FrameSlot
from local_site.agent.display_process import DisplayProcess
from local_site.agent.platform_process import ProcessPlatformReader
from local_site.agent.platform_reader import PlatformReader, stale_since_s
from local_site.devices import open_display, open_platform
from local_site.platform.base import XYZPlatform
from local_site.recording import SessionRecorder
from local_site.render import Renderer, RendererConfig
from local_site.scenes import SceneSource, TactileFrameScene, open_scene, parse_shape_spec
from local_site.scenes.factory import REMOTE_SPECS
from local_site.view import StationView
from shared.client import StationLink, StationLinkConfig
from shared.errors import (
    AuthError,
    ConfigError,
    DeviceError,
    InputDataError,
    LocalProtocolError,
    RoleTakenError,
    SessionError,
)
from shared.gil import switch_interval
from shared.loop_watchdog import loop_watchdog
from shared.memlock import MemoryLock, memory_locked
from shared.motion_to_touch import MotionToTouchLedger
from shared.protocol import (
    ArmState,
    Bye,
    Error,
    Hop,
    PlatformState,
    TactileCompact,
    TactileFrame,
)
from shared.protocol.tactile_codec import TactileDecoder
from shared.report import StatusLine, to_jsonable
from shared.sd_notify import service
from shared.timebase import monotonic_s, now_us
from shared.view import ViewAddress, ViewServer, ViewServerConfig
from shared.workspace import WorkspaceConfig

__all__ = ["LocalAgent", "place_shape_spec"]

log = logging.getLogger(__name__)

_VELOCITY_LIMIT_MM_S = 1e5  # the wire's bound for platform_state.velocity_mm_s


def place_shape_spec(spec: str, center_mm: tuple[float, float]) -> str:
    """Put a shape without an explicit centre at ``center_mm`` (platform frame).

    Shapes are defined around the origin, a corner of the platform's travel; the operator
    could not reach most of them. Layer files and specs with ``x_mm``/``y_mm`` are returned
    unchanged.

    Raises:
        ConfigError: a malformed shape spec.
    """
    text = spec.strip()
    if text.lower().endswith(".npz") or os.path.isfile(text) or text.lower() in REMOTE_SPECS:
        return text
    name, params = parse_shape_spec(text)
    params.setdefault("x_mm", float(center_mm[0]))
    params.setdefault("y_mm", float(center_mm[1]))
    return name + ":" + ",".join(f"{k}={v!r}" for k, v in params.items())


def _percentiles_ms(values: list[float] | np.ndarray) -> dict[str, float | int | None]:
    arr = np.asarray(values, dtype=float)
    if arr.size == 0:
        return {"p50": None, "p99": None, "max": None, "count": 0}
    return {"p50": float(np.percentile(arr, 50)), "p99": float(np.percentile(arr, 99)),
            "max": float(arr.max()), "count": int(arr.size)}


class LocalAgent:
    """The local haptic station (see the module docstring).

    Args:
        config: agent settings.
        link_config: relay link settings (required unless ``config.scene`` is set).
        render_config: renderer settings (defaults when None).
        workspace: workspace settings written into the recording's metadata.
        duration_s: stop after this long (None: run until stopped).
        until_motion_done: stop once the simulated platform's scripted motion finished
            (plus ``config.motion_done_grace_s``).
        record_path: record the session to this MCAP file (None: no recording).
        summary_path: write the summary JSON here at exit (None: none).
        status: live status line (None: no status output).
        handle_signals: stop cleanly on SIGTERM/SIGINT (main thread only).
        platform_options: extra keyword arguments for ``open_platform``.
        display_options: extra keyword arguments for ``open_display``.
        view: serve the live view in the browser on ``HOST:PORT`` (None: no view).
        view_config: the view's rates and limits.
        view_ready: called with the view's URL once it listens.

    Raises:
        ConfigError: bad specs or settings (raised by :meth:`open` / :meth:`run`).
    """

    def __init__(self, config: LocalAgentConfig, *,
                 link_config: StationLinkConfig | None = None,
                 render_config: RendererConfig | None = None,
                 workspace: WorkspaceConfig | None = None, duration_s: float | None = None,
                 until_motion_done: bool = False, record_path: str | Path | None = None,
                 summary_path: str | Path | None = None, status: StatusLine | None = None,
                 handle_signals: bool = False,
                 platform_options: dict[str, Any] | None = None,
                 display_options: dict[str, Any] | None = None,
                 view: ViewAddress | None = None, view_config: ViewServerConfig | None = None,
                 view_ready: Callable[[str], None] | None = None) -> None:
        if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
            raise ConfigError(f"duration must be > 0 s, got {duration_s}")
        self.config = config
        self.remote_mode = not config.scene.strip() or config.scene.strip().lower() in REMOTE_SPECS
        if self.remote_mode and link_config is None:
            raise ConfigError("the local agent needs a relay link (--relay) or a --scene")
        self.link_config = link_config
        self.render_config = render_config or RendererConfig()
        self.workspace = workspace or WorkspaceConfig()
        self.duration_s = duration_s
        self.until_motion_done = until_motion_done
        self.record_path = Path(record_path) if record_path is not None else None
        self.summary_path = Path(summary_path) if summary_path is not None else None
        self.status = status
        self.handle_signals = handle_signals
        self._platform_options = dict(platform_options or {})
        self._display_options = dict(display_options or {})
        self.recorder: SessionRecorder | None = None
        self.ledger = MotionToTouchLedger()
        self.frames = FrameSlot()
        #: key frame state of the compact tactile codec (protocol v2)
        self.tactile_decoder = TactileDecoder()
        #: the link session (``connects``) the decoder's key frame belongs to
        self._decoder_connects = 0
        self.link: StationLink | None = None
        self.reader: PlatformReader | ProcessPlatformReader | None = None
        self.loop: DisplayLoop | DisplayProcess | None = None
        self.scene: SceneSource | None = None
        self.exit_reason: str | None = None
        self.exit_code = 0
        self.summary: dict[str, Any] | None = None
        self.platform_states_sent = 0
        self.platform_states_skipped_link_down = 0
        self.platform_states_skipped_stale = 0
        #: whether :meth:`run` locked the process's memory (None before it runs)
        self.memory_lock: MemoryLock | None = None
        self.send_errors = 0
        self.arm_states_received = 0
        self.relay_errors = 0
        self.last_arm_state: ArmState | None = None
        self._stop: asyncio.Event | None = None
        self._thread_stop = threading.Event()
        self._started_s: float | None = None
        self._motion_done_at_s: float | None = None
        self.view_address = view
        self._view_config = view_config
        self._view_ready = view_ready
        self.view: StationView | None = None
        self.view_server: ViewServer | None = None
        #: the live view's URL once it listens
        self.view_url: str | None = None

    # ------------------------------------------------------------------ building

    def open(self) -> None:
        """Build the devices (not yet connected), the scene, renderer, link and loop.

        Raises:
            ConfigError: a bad platform/display/scene/motion spec or option.
        """
        cfg = self.config
        platform_opts = dict(self._platform_options)
        if cfg.motion.strip():
            platform_opts["motion"] = cfg.motion  # parsed by the sim backend
        platform: XYZPlatform | None = open_platform(cfg.platform, connect=False,
                                                     **platform_opts)
        motion = getattr(platform, "motion", None)
        motion_duration_s = getattr(motion, "duration_s", None)
        if cfg.platform_process or cfg.render_loop == "process":
            platform = None  # opened again in the reader's process, from the same spec
        if self.until_motion_done and motion_duration_s is None:
            raise ConfigError("--until-motion-done needs a platform with a scripted motion of "
                              "finite length (the sim platform with raster, hold, replay, or "
                              "random with a duration)")
        display_opts: dict[str, Any] = dict(
            keepalive_interval_s=cfg.display_keepalive_interval_s,
            watchdog_ms=cfg.display_watchdog_ms, watchdog_mode=cfg.safe_state,
            disconnect_mode=cfg.safe_state, feedback_timeout_s=cfg.display_feedback_timeout_s)
        display_opts.update(self._display_options)
        display = open_display(cfg.display, connect=False, **display_opts)
        if self.remote_mode:
            scene = TactileFrameScene(order=cfg.interpolation_order)
            self.scene = scene
            # each frame is validated and gridded where it arrives, not in the display loop
            self.frames.prepare = scene.prepare
            if self.link_config is None:
                raise ConfigError("the local agent needs a relay link (--relay) or a --scene")
            self.link = StationLink.from_config(self.link_config, "local")
        else:
            spec = place_shape_spec(cfg.scene, (cfg.scene_center_x_mm, cfg.scene_center_y_mm))
            self.scene = open_scene(spec, interpolation_order=cfg.interpolation_order)
        reader_args: dict[str, Any] = dict(
            read_timeout_s=cfg.platform_read_timeout_s,
            reopen_after_s=cfg.platform_reopen_after_s,
            retry_min_s=cfg.device_retry_min_s, retry_max_s=cfg.device_retry_max_s,
            motion_duration_s=motion_duration_s if self.until_motion_done else None)
        self.reader = PlatformReader(platform, **reader_args) if platform is not None \
            else ProcessPlatformReader(cfg.platform, platform_opts, lock_memory=cfg.lock_memory,
                                       **reader_args)
        reader = self.reader
        if self.record_path is not None and self.recorder is None:
            self.recorder = SessionRecorder(
                self.record_path, self._record_meta(), queue_size=cfg.record_queue_size,
                pins_rate_hz=cfg.record_pins_rate_hz,
                image_rate_hz=cfg.record_image_rate_hz or None)
            if self.link is not None:
                self.link.tap = self.recorder.tap
        loop_args: dict[str, Any] = dict(
            rate_hz=cfg.render_rate_hz, safe_mode=cfg.safe_state,
            link_loss_timeout_s=cfg.link_loss_timeout_s,
            stale_timeout_s=cfg.stale_frame_timeout_s, max_frame_age_s=cfg.max_frame_age_s,
            max_offset_uncertainty_s=cfg.max_offset_uncertainty_s,
            retry_min_s=cfg.device_retry_min_s, retry_max_s=cfg.device_retry_max_s)
        if cfg.render_loop == "process":
            self.loop = DisplayProcess(
                display=cfg.display, display_options=display_opts,
                render_config=self.render_config,
                scene="remote" if self.remote_mode else spec,
                interpolation_order=cfg.interpolation_order, platform=reader,
                loop_args=loop_args, link=self.link, recorder=self.recorder,
                ledger=self.ledger, retry_min_s=cfg.device_retry_min_s,
                retry_max_s=cfg.device_retry_max_s,
                gil_switch_interval_s=cfg.gil_switch_interval_s, lock_memory=cfg.lock_memory)
            self.frames = self.loop.frames  # type: ignore[assignment]
            return
        self.loop = DisplayLoop(
            display, Renderer(self.render_config), self.scene,
            positions=lambda: reader.latest, platform_ok=lambda: reader.healthy,
            frames=self.frames if self.remote_mode else None, link=self.link,
            recorder=self.recorder, ledger=self.ledger,
            **loop_args)

    def _record_meta(self) -> dict[str, Any]:
        """What the recording's start metadata says about this run (read by the analysis)."""
        return {"session": self.link_config.session if self.link_config else None,
                "mode": "relay" if self.remote_mode else "scene",
                "scene": self.config.scene or "remote", "platform": self.config.platform,
                "display": self.config.display, "motion": self.config.motion,
                "workspace": dataclasses.asdict(self.workspace),
                "render": dataclasses.asdict(self.render_config)}

    def _require_open(self) -> tuple[DisplayLoop | DisplayProcess,
                                     PlatformReader | ProcessPlatformReader]:
        if self.loop is None or self.reader is None:
            raise ConfigError("LocalAgent.open() has not been called")
        return self.loop, self.reader

    # ------------------------------------------------------------------ control

    def request_stop(self, reason: str = "stopped") -> None:
        """Ask the agent to stop (thread-safe from the event loop's thread)."""
        if self.exit_reason is None:
            self.exit_reason = reason
        if self._stop is not None:
            self._stop.set()

    @property
    def elapsed_s(self) -> float:
        """Seconds since :meth:`run` started (0 before)."""
        return 0.0 if self._started_s is None else monotonic_s() - self._started_s

    # ------------------------------------------------------------------ tasks

    async def _uplink(self) -> None:
        link, reader = self.link, self.reader
        if link is None or reader is None:
            return
        period_s = 1.0 / self.config.platform_send_rate_hz
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        last = None
        # ``local.motion`` (docs of shared/motion_to_touch.py): a movement just after the
        # previous message's sample shows first in the next message. The previous sample's
        # time; None when no message went out since the link came up or a sample was skipped
        # (one the link's queue replaces unsent passes its own stamp on: carry_motion)
        sent_us: int | None = None
        seq = 0
        # a sample older than this is never sent (the platform counts as lost by then): a
        # reader that resumes after a stall may first decode samples the board buffered
        # meanwhile, stamped when they were latched (the remote would drop them as stale)
        stale_s = self.config.platform_read_timeout_s
        gap_limit_us = stale_s * 1e6  # a longer gap between samples: the platform was lost
        while True:
            sample = reader.latest
            if sample is not None and sample is not last:
                last = sample
                if stale_since_s(sample, stale_s) is not None:
                    self.platform_states_skipped_stale += 1
                    sent_us = None
                elif link.is_connected:
                    seq += 1
                    velocity = tuple(min(max(v, -_VELOCITY_LIMIT_MM_S), _VELOCITY_LIMIT_MM_S)
                                     for v in sample.velocity_mm_s)
                    motion_us = sent_us
                    if motion_us is not None and not 0 < sample.t_us - motion_us <= gap_limit_us:
                        motion_us = None  # the platform was lost meanwhile: not a wait
                    capture = Hop("local", "capture", sample.t_us)
                    hops = (capture,) if motion_us is None else (
                        Hop("local", "motion", motion_us), capture)
                    msg = PlatformState(seq=seq, ts_us=sample.t_us, hops=hops,
                                        position_mm=sample.position_mm,
                                        velocity_mm_s=velocity)  # type: ignore[arg-type]
                    try:
                        await link.send(msg)
                    except LocalProtocolError as err:
                        self.send_errors += 1
                        sent_us = None
                        if self.send_errors == 1:
                            log.warning("platform_state not sent: %s", err)
                    except (AuthError, RoleTakenError):
                        return  # the receive task reports the refusal
                    except SessionError:
                        return  # link closed: shutting down
                    else:
                        self.platform_states_sent += 1
                        sent_us = sample.t_us
                else:
                    self.platform_states_skipped_link_down += 1
                    sent_us = None
            next_t += period_s
            now = loop.time()
            if next_t < now - period_s:
                next_t = now
            await asyncio.sleep(max(0.0, next_t - now))

    def _decode_compact(self, msg: TactileCompact) -> TactileFrame | None:
        """The frame of a compact message; None while its key frame is missing (nothing is
        rendered: the scene ages into the safe state) or when it does not decode. A new
        link session (a reconnect) forgets the key frame of the last one: a restarted sender
        numbers its frames from 1 again, and its deltas must not be applied to an old key
        frame that happens to share a seq."""
        link = self.link
        if link is not None and link.counters.connects != self._decoder_connects:
            self.tactile_decoder.reset()
            self._decoder_connects = link.counters.connects
        try:
            return self.tactile_decoder.decode(msg)
        except InputDataError as err:
            if self.tactile_decoder.counters.rejected <= 3 or log.isEnabledFor(logging.DEBUG):
                log.warning("compact tactile frame seq=%d refused, pins untouched: %s",
                            msg.seq, err)
            return None

    async def _receive(self) -> None:
        link = self.link
        if link is None:
            return
        try:
            async for msg in link.messages():
                if isinstance(msg, TactileCompact):
                    decoded = self._decode_compact(msg)
                    if decoded is None:
                        continue
                    msg = decoded
                if isinstance(msg, TactileFrame):
                    rx_us = next((h.t_us for h in reversed(msg.hops)
                                  if h.clock == "local" and h.stage == "station_rx"), None)
                    self.frames.put(msg, now_us() if rx_us is None else rx_us)
                elif isinstance(msg, ArmState):
                    self.arm_states_received += 1
                    self.last_arm_state = msg
                elif isinstance(msg, Error):
                    self.relay_errors += 1
                    if self.relay_errors <= 3 or log.isEnabledFor(logging.DEBUG):
                        log.warning("relay error: %s: %s", msg.code, msg.message)
                elif isinstance(msg, Bye):
                    log.info("relay said bye: %s", msg.reason)
        except SessionError as err:  # messages() raises only a final refusal (a wrong
            # token, a replaced connection, a hello the relay can never accept): each ended
            # the receive task silently but the first, with the station up and its link down
            log.error("the relay refused this station for good: %s", err)
            self.exit_code = 1
            self.request_stop("link_refused")

    def _status_text(self, rates: dict[str, float]) -> str:
        loop, reader = self._require_open()
        link = self.link
        parts = ["local"]
        if link is not None:
            parts.append("link up" if link.is_connected
                         else f"link DOWN {link.link_down_for_s():.1f}s")
        parts.append(f"platform {rates['platform_hz']:.0f} Hz" if reader.healthy
                     else "platform LOST")
        if link is not None:
            parts.append(f"tx {rates['tx_hz']:.0f}/s")
            c = loop.counters
            parts.append(f"frames {rates['frames_hz']:.0f}/s rx {self.frames.put_count} "
                         f"rend {c.frames_rendered} rej {c.frames_rejected}")
            e2e = list(loop.recent_e2e_ms)[-500:]
            if e2e:
                p50, p99 = np.percentile(e2e, [50, 99])
                parts.append(f"e2e p50 {p50:.1f} p99 {p99:.1f} ms")
            drops = link.counters.stale_dropped_rx + link.counters.stale_dropped_tx \
                + self.frames.superseded
            parts.append(f"drops {drops}")
        period = loop.periods.summary(last=1000)
        if period["rate_hz"] is not None:
            parts.append(f"loop {period['rate_hz']:.0f} Hz p99 {period['period_p99_ms']:.2f} ms")
        if loop.safe_reason is not None:
            parts.append(f"SAFE({loop.safe_reason})")
        return " | ".join(parts)

    async def _status(self) -> None:
        status, reader, loop = self.status, self.reader, self.loop
        if status is None or reader is None or loop is None:
            return
        interval_s = self.config.status_interval_s
        last = (monotonic_s(), reader.reads, self.platform_states_sent, self.frames.put_count)
        while True:
            await asyncio.sleep(interval_s)
            now = (monotonic_s(), reader.reads, self.platform_states_sent, self.frames.put_count)
            dt = max(1e-6, now[0] - last[0])
            rates = {"platform_hz": (now[1] - last[1]) / dt, "tx_hz": (now[2] - last[2]) / dt,
                     "frames_hz": (now[3] - last[3]) / dt}
            last = now
            status.update(self._status_text(rates))

    async def _supervise(self) -> None:
        _, reader = self._require_open()
        while True:
            if self.duration_s is not None and self.elapsed_s >= self.duration_s:
                self.request_stop("duration")
                return
            if self.until_motion_done and reader.motion_done.is_set():
                if self._motion_done_at_s is None:
                    self._motion_done_at_s = monotonic_s()
                    log.info("scripted motion finished; stopping in %.2f s",
                             self.config.motion_done_grace_s)
                if monotonic_s() - self._motion_done_at_s >= self.config.motion_done_grace_s:
                    self.request_stop("motion_done")
                    return
            await asyncio.sleep(0.02)

    # ------------------------------------------------------------------ run

    async def run(self) -> int:
        """Run until a stop condition, shut down cleanly, write the outputs.

        Returns:
            The exit code: 0, or 1 when the relay refused the station for good.

        Raises:
            ConfigError: bad settings (from :meth:`open`).
        """
        if self.loop is None:
            self.open()
        loop, reader = self._require_open()
        aio = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        signals: list[int] = []
        if self.handle_signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                    aio.add_signal_handler(sig, self.request_stop, "signal")
                    signals.append(sig)
        self._started_s = monotonic_s()
        self._thread_stop.clear()
        await self._start_view()
        process_settings = contextlib.ExitStack()  # undone when the station ends (finally)
        # the switch interval is for the display loop: with the loop in a process of its own,
        # that process takes it and the station keeps Python's (0: left alone)
        process_settings.enter_context(switch_interval(
            0.0 if isinstance(loop, DisplayProcess) else self.config.gil_switch_interval_s))
        self.memory_lock = process_settings.enter_context(memory_locked(self.config.lock_memory))
        reader.start()
        if self.link is not None:
            self.link.start()
        display_task: asyncio.Future[None]
        async_stop = asyncio.Event()
        if isinstance(loop, DisplayProcess) or self.config.render_loop == "thread":
            display_task = aio.run_in_executor(None, loop.run_in_thread, self._thread_stop,
                                               self.config.display_thread_nice,
                                               self.config.display_thread_realtime)
        else:
            display_task = aio.create_task(loop.run_async(async_stop), name="display-loop")
        tasks = [aio.create_task(coro, name=name) for name, coro in (
            ("uplink", self._uplink()), ("receive", self._receive()),
            ("status", self._status()), ("supervise", self._supervise()))]
        try:
            stop_wait = aio.create_task(self._stop.wait())
            waiters: set[asyncio.Future[Any]] = {stop_wait, display_task}
            # systemd (Type=notify): ready now; its watchdog pinged from this loop; this
            # loop stuck for hang_timeout_s: stacks written, exit 1 (to be restarted)
            async with service("local station running"), loop_watchdog(self.config.hang_timeout_s):
                await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
            if not stop_wait.done():
                stop_wait.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await stop_wait
                self.request_stop("display_loop_ended")
            if display_task.done() and display_task.exception() is not None:
                self.exit_code = 1
                log.error("display loop failed: %s", display_task.exception())
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            self._thread_stop.set()
            async_stop.set()
            with contextlib.suppress(Exception):
                await display_task
            await self._shutdown()
            for signum in signals:
                aio.remove_signal_handler(signum)
            process_settings.close()
        return self.exit_code

    async def _start_view(self) -> None:
        """Serve the live view in its own thread (and its analysis in a child process).

        Raises:
            ConfigError: the view's address cannot be bound.
        """
        address, loop = self.view_address, self.loop
        if address is None or loop is None:
            return
        if not address.is_loopback:
            log.warning("the live view listens on %s, not on loopback: whoever reaches it "
                        "sees this session (the station's view has no token; "
                        "see docs/view.md)", address.host)
        self.view = StationView(self)
        server = ViewServer(self.view, self._view_config)
        try:
            port = await asyncio.to_thread(server.start_thread, address.host, address.port)
        except ConfigError:
            self.view.close()
            self.view = None
            raise
        self.view_server = server
        loop.frame_listener = self.view.frame_accepted
        host = f"[{address.host}]" if ":" in address.host else address.host
        self.view_url = f"http://{host}:{port}/"
        log.info("live view: %s", self.view_url)
        if self._view_ready is not None:
            self._view_ready(self.view_url)

    async def _stop_view(self) -> None:
        if self.loop is not None:
            self.loop.frame_listener = None
        if self.view_server is not None:
            await asyncio.to_thread(self.view_server.stop_thread)
        if self.view is not None:
            await asyncio.to_thread(self.view.close)

    async def _shutdown(self) -> None:
        loop, reader = self._require_open()
        display = loop.display
        loop.finish("shutdown")
        display_stats = display.stats()
        feedback = display.latest_feedback() if display.is_connected else None
        try:
            await asyncio.to_thread(display.disconnect)
        except DeviceError as err:
            log.warning("display close failed: %s", err)
        await asyncio.to_thread(reader.stop)
        platform_stats = reader.platform_stats()
        try:
            await asyncio.to_thread(reader.disconnect)
        except DeviceError as err:
            log.warning("platform close failed: %s", err)
        if self.link is not None:
            await self.link.close("local station stopping")
        await self._stop_view()  # after the pins are safe and the devices closed
        if self.status is not None:
            self.status.close()
        self.summary = self._build_summary(display_stats, platform_stats, feedback)
        if self.recorder is not None and self.remote_mode and self.config.record_findings:
            found = await asyncio.to_thread(self.recorder.add_findings)
            self.summary["findings_recorded"] = found
        if self.recorder is not None:
            end = {k: self.summary[k] for k in ("exit_reason", "duration_s", "frames_received",
                                                "frames_accepted", "frames_rendered",
                                                "frames_rejected", "motion_to_touch_ms")}
            try:
                await asyncio.to_thread(self.recorder.close, end)
                self.summary["recording"] = self.recorder.counts()
                lost = self.recorder.mcap.loss_error()
                if lost is not None:  # finished, but incomplete: not a clean stop
                    raise lost
            except ConfigError as err:
                log.error("%s", err)
                self.exit_code = 1
                self.summary["recording"] = self.recorder.counts()
                self.summary["recording_error"] = str(err)
        if self.summary_path is not None:
            text = json.dumps(to_jsonable(self.summary), allow_nan=False, sort_keys=True)
            try:
                self.summary_path.write_text(text + "\n")
            except OSError as err:
                log.error("cannot write the summary %s: %s", self.summary_path, err)
                self.exit_code = 1

    def _build_summary(self, display_stats: Any, platform_stats: Any,
                       feedback: Any) -> dict[str, Any]:
        loop, reader = self._require_open()
        link = self.link
        elapsed = max(1e-9, self.elapsed_s)
        c = loop.counters
        safe_time_s = c.safe_time_s
        return {
            "mode": "relay" if self.remote_mode else "scene",
            "scene": self.config.scene or "remote",
            "session": self.link_config.session if self.link_config else None,
            "exit_reason": self.exit_reason, "exit_code": self.exit_code,
            "duration_s": elapsed,
            "frames_received": self.frames.put_count,
            "frames_accepted": c.frames_accepted,
            "frames_rendered": c.frames_rendered,
            "frames_rejected": c.frames_rejected,
            "frames_superseded": self.frames.superseded + c.frames_superseded_unrendered,
            "rendered_frame_age_max_ms": round(c.rendered_frame_age_max_ms, 3),
            "late_sends_withdrawn": c.late_sends_withdrawn,
            "late_sends_refused": c.late_sends_refused,
            "motion_to_touch_ms": self.ledger.summary_ms(),
            # where the slowest 5 % of the complete frames lose their time, stage by stage
            "motion_to_touch_tail_ms": self.ledger.tail_ms(0.95),
            "tactile_codec": dataclasses.asdict(self.tactile_decoder.counters),
            "memory_lock": None if self.memory_lock is None else self.memory_lock.to_dict(),
            "display_loop": {"mode": self.config.render_loop,
                             "process_restarts": getattr(loop, "restarts", 0),
                             "process_error": getattr(loop, "child_error", None),
                             # accepted frames, pins samples, hops and periods the display
                             # process gave up because a report outgrew a packet
                             "process_report_items_shed": getattr(
                                 getattr(loop, "totals", None), "shed", 0),
                             "thread_nice": loop.priority_applied,
                             "thread_realtime": loop.realtime_applied,
                             **loop.periods.summary()},
            "platform": {"spec": self.config.platform, "reads": reader.reads,
                         "read_rate_hz": reader.reads / elapsed,
                         "decoded_rate_hz": platform_stats.frames_ok / elapsed,
                         "errors": reader.errors,
                         "reconnects": reader.reconnects, "recoveries": reader.recoveries,
                         "last_error": reader.last_error,
                         "process": isinstance(reader, ProcessPlatformReader),
                         "process_restarts": getattr(reader, "restarts", 0),
                         **dataclasses.asdict(platform_stats)},
            "uplink": {"platform_states_sent": self.platform_states_sent,
                       "send_rate_hz": self.platform_states_sent / elapsed,
                       "skipped_link_down": self.platform_states_skipped_link_down,
                       "skipped_stale": self.platform_states_skipped_stale,
                       "send_errors": self.send_errors},
            "display": {"spec": self.config.display, "commands_sent": c.commands_sent,
                        "commands_skipped_unchanged": c.commands_skipped_unchanged,
                        "keepalives_sent": c.keepalives_sent,
                        "render_rejected": c.render_rejected, "errors": c.display_errors,
                        "reconnects": c.display_reconnects,
                        "driver": dataclasses.asdict(display_stats),
                        "last_feedback_safe_state": None if feedback is None
                        else feedback.safe_state},
            "safe_state": {"mode": self.config.safe_state, "entries": dict(c.safe_entries),
                           "time_s": safe_time_s,
                           "link_loss_to_safe_ms": _percentiles_ms(c.link_loss_to_safe_ms)},
            "render": dataclasses.asdict(loop.renderer.stats),
            "link": None if link is None else {
                **dataclasses.asdict(link.counters), "url": link.url,
                "clock_offsets_us": link.clock_offsets_us,
                "relay_errors": self.relay_errors},
            "arm_states_received": self.arm_states_received,
            "recording": None if self.recorder is None else self.recorder.counts(),
        }
