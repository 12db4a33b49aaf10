"""Build the remote station from its options and run it (the body of ``teletouch remote``).

Order of start-up, so that every configuration error surfaces before anything moves:
settings (flags > environment > TOML > defaults), the probe's stiffness calibration (gel
and N/mm -> Shore 00; required for a real sensor), the simulated world (by name, through
:data:`~remote_site.agent.devices.WORLDS`; this module never imports simulator code), the
arm and sensor backends (wired to the world in :mod:`remote_site.agent.devices`), the sensor
calibration (checked against the sensor: :class:`~shared.errors.CalibrationError`), then
connect the devices, capture the no-contact background (arm at its home pose, before any
press: :mod:`remote_site.agent.background`), open the link and run
:class:`~remote_site.agent.station.RemoteStation`.
Whatever happens, the arm is halted and the devices are closed on the way out.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from remote_site.agent.background import BackgroundSettings, BackgroundTracker
from remote_site.agent.config import RemoteAgentConfig
from remote_site.agent.devices import (
    load_calibration,
    load_stiffness_calibration,
    open_world,
    open_world_arm,
    open_world_sensor,
)
from remote_site.agent.pipeline import FramePipeline
from remote_site.agent.station import RemoteStation
from remote_site.agent.stiffness_stage import StiffnessStage
from remote_site.arm.safety import SafeArm, SafetyConfig
from remote_site.reconstruction.reconstructor import Reconstructor
from remote_site.registration import calibrate_with_fiducials, guarded
from remote_site.sensor.registry import check_sensor_source
from remote_site.stiffness.estimator import StiffnessConfig
from remote_site.stiffness.stiffness_map import MapBounds
from remote_site.tactile import TactileAssembler
from shared.client import StationLink, StationLinkConfig
from shared.config import resolve_config
from shared.errors import ConfigError
from shared.gil import switch_interval
from shared.memlock import memory_locked
from shared.recording import McapRecorder
from shared.workspace import load_workspace

__all__ = ["AgentOptions", "run_agent", "sensor_options"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AgentOptions:
    """What ``teletouch remote`` was asked to do (None: take it from env/TOML/defaults).

    Attributes:
        relay: relay URL (``ws://``, ``wss://``, ``tcp://``).
        session: session id.
        token: session token (prefer ``TELETOUCH_REMOTE_LINK_TOKEN``).
        name: label shown in the relay's status.
        ca_file: CA certificate (PEM) to trust for ``wss://`` and ``tls://`` relays.
        arm: arm backend name (``sim``, ``franka`` or ``module:Class``).
        sensor: sensor name (``sim``, ``camera``) or a camera index / URL / video file.
        sensor_preset: camera crop / size preset (``mini-raw``, ``mini-recording``); None:
            the camera's default.
        sensor_fps: pace a camera source at this rate (None: a video file's own rate).
        sensor_latency_ms: a camera's latency from exposure to arrival (None: 0, the
            arrival).
        sensor_loop: restart a video file at its end.
        phantom: scene name of the simulated world (None: no world).
        seed: placement seed of the phantom (and the simulated session's noise).
        ideal: the noise-free simulated world instead of the realistic default.
        fiducials: design (x, y) positions of the phantom's fiducials (phantom mm); when
            given, the arm <-> phantom registration is measured on them at start-up
            (:mod:`remote_site.registration`) and put into the workspace map.
        calibration: the sensor calibration (.npz); the backend's default when None.
        stiffness_calibration: the probe's stiffness calibration (.json, made by
            ``teletouch sensor calibrate-stiffness``); the backend's default when None
            (a real sensor has none).
        frame_rate_hz: tactile frames per second.
        patch_pitch_mm: tactile patch pitch on the display side.
        tactile_codec: ``compact`` or ``raw`` (default from the config: compact).
        capture_on_pose: frames on pose reached (True) or on the frame clock (False); None:
            the config's (default True; a streaming camera always uses the frame clock).
        lock_memory: keep the station's memory in RAM while it runs; None: the config's
            (default True, where it is safe: :mod:`shared.memlock`).
        duration_s: stop after this many seconds (None: until stopped).
        config_path: TOML file (or ``$TELETOUCH_CONFIG``).
        record: record the session to this MCAP file (None: no recording).
    """

    relay: str | None = None
    session: str | None = None
    token: str | None = None
    name: str | None = None
    ca_file: str | None = None
    arm: str = "sim"
    sensor: str = "sim"
    sensor_preset: str | None = None
    sensor_fps: float | None = None
    sensor_latency_ms: float | None = None
    sensor_loop: bool = False
    phantom: str | None = None
    seed: int = 0
    ideal: bool = False
    fiducials: tuple[tuple[float, float], ...] = ()
    calibration: Path | None = None
    stiffness_calibration: Path | None = None
    frame_rate_hz: float | None = None
    patch_pitch_mm: float | None = None
    tactile_codec: str | None = None
    capture_on_pose: bool | None = None
    lock_memory: bool | None = None
    duration_s: float | None = None
    config_path: Path | None = None
    record: Path | None = None


def check_arm_watchdog(agent: RemoteAgentConfig, safety: SafetyConfig) -> None:
    """The arm's watchdog thread against the command timeout it enforces: it halts the arm
    once the newest command is older than the timeout less its period (its next check
    would come too late), so a period of half the timeout or more halts an arm whose
    commands come every few milliseconds.

    Raises:
        ConfigError: naming both settings.
    """
    period_ms = agent.watchdog_period_s * 1000.0
    if not period_ms < safety.command_timeout_ms / 2:
        raise ConfigError(
            f"remote.agent.watchdog_period_s ({period_ms:g} ms) must be under half "
            f"arm.safety.command_timeout_ms ({safety.command_timeout_ms:g} ms): the arm is "
            "halted once its newest command is older than the timeout less that period")


def _set_opencv_threads(threads: int | None) -> int | None:
    """``cv2.setNumThreads(threads)`` (None or 0: unchanged); the count it replaced (None
    when unchanged). See ``RemoteAgentConfig.opencv_threads``."""
    if not threads:
        return None
    import cv2

    before = int(cv2.getNumThreads())
    cv2.setNumThreads(threads)
    return before


def sensor_options(options: AgentOptions) -> dict[str, Any]:
    """The camera options given on the command line (only those given: ``sim`` refuses them
    with a ConfigError; ``sim-camera`` takes the rate and the latency)."""
    given: dict[str, Any] = {}
    if options.sensor_preset is not None:
        given["preset"] = options.sensor_preset
    if options.sensor_fps is not None:
        given["fps"] = options.sensor_fps
    if options.sensor_latency_ms is not None:
        given["latency_ms"] = options.sensor_latency_ms
    if options.sensor_loop:
        given["loop"] = True
    return given


async def run_agent(options: AgentOptions, stop: asyncio.Event, status: Any = None,
                    on_summary: Callable[[dict[str, Any]], None] | None = None
                    ) -> dict[str, Any]:
    """Build everything, run the station until ``stop``/duration, return the summary.

    Args:
        options: the command line.
        stop: set it to stop cleanly (the CLI sets it on SIGTERM/SIGINT).
        status: callable receiving the status text (None: no status line).
        on_summary: called with the summary once the station has stopped, also when it
            stopped on an error (so ``--summary-json`` is written in every case).

    Returns:
        :meth:`RemoteStation.summary` plus ``session``, ``arm``, ``sensor``, ``phantom``.

    Raises:
        ConfigError: bad settings, unknown backends, a world given to real hardware, no
            stiffness calibration for a real sensor.
        CalibrationError: missing or mismatched calibration.
        DeviceInitError: a device could not be opened.
        SessionError: the relay refused the station for good (a wrong token, a
                connection replaced by another, a hello it can never accept).
    """
    check_sensor_source(options.sensor)  # a mistyped --sensor is named before anything else
    toml = options.config_path
    link_cfg = resolve_config(StationLinkConfig, "remote.link", toml_path=toml, explicit={
        "url": options.relay, "session": options.session, "token": options.token,
        "name": options.name, "ca_file": options.ca_file})
    safety = resolve_config(SafetyConfig, "arm.safety", toml_path=toml)
    stiffness_cfg = resolve_config(StiffnessConfig, "stiffness", toml_path=toml)
    agent_cfg = resolve_config(RemoteAgentConfig, "remote.agent", toml_path=toml, explicit={
        "frame_rate_hz": options.frame_rate_hz, "patch_pitch_mm": options.patch_pitch_mm,
        "tactile_codec": options.tactile_codec, "capture_on_pose": options.capture_on_pose,
        "lock_memory": options.lock_memory})
    check_arm_watchdog(agent_cfg, safety)
    background_cfg = resolve_config(BackgroundSettings, "remote.background", toml_path=toml)
    # frames are aged from their image's time: a latency at or above an age limit refuses
    # every frame there (each tick, or the whole background capture)
    for limit_ms, where in ((agent_cfg.sensor_max_age_ms, "[remote.agent] sensor_max_age_ms"),
                            (background_cfg.max_frame_age_ms,
                             "[remote.background] max_frame_age_ms")):
        if options.sensor_latency_ms is not None and options.sensor_latency_ms >= limit_ms:
            raise ConfigError(f"--sensor-latency-ms {options.sensor_latency_ms:g} is not below "
                              f"{where} ({limit_ms:g}): frames are aged from their image's "
                              "time, so every one would be refused as too old; raise it above "
                              "the latency (plus a frame period, or some frames age out "
                              "before they are read)")
    workspace = load_workspace(toml_path=toml)
    lo, hi = workspace.phantom_bounds_mm
    bounds = MapBounds(lo[0], hi[0], lo[1], hi[1], agent_cfg.stiffness_cell_mm)  # (checked)
    stiffness_calibration = load_stiffness_calibration(options.sensor,
                                                       options.stiffness_calibration)
    if stiffness_cfg.gel_stiffness_n_per_mm is None:  # flags/env/TOML win over the file
        stiffness_cfg = stiffness_cfg.with_calibration(stiffness_calibration)
    stiffness_to_k = stiffness_calibration.stiffness_to_k()

    world = open_world("phantom", options.phantom, options.seed,
                       ideal=options.ideal) if options.phantom else None

    arm = open_world_arm(options.arm, world)
    sensor = open_world_sensor(options.sensor, world, arm, **sensor_options(options))
    calibration = load_calibration(options.sensor, options.calibration, sensor)
    reconstructor = Reconstructor(calibration)
    log.info("reconstruction relief: %s (%s)", reconstructor.relief,
             "heights above the contact rim" if reconstructor.relief == "rim"
             else "heights above the free gel")

    stiffness = StiffnessStage(stiffness_cfg, bounds)
    assembler = TactileAssembler(workspace, stiffness_to_k=stiffness_to_k,
                                 patch_size_mm=agent_cfg.patch_size_mm,
                                 friction=agent_cfg.friction)
    arm.connect()
    safe_arm: SafeArm | None = None
    recorder: McapRecorder | None = None
    recording_error: ConfigError | None = None
    opencv_before = _set_opencv_threads(agent_cfg.opencv_threads)
    process_settings = contextlib.ExitStack()  # undone when the station ends
    memory_lock = process_settings.enter_context(memory_locked(agent_cfg.lock_memory))
    gil_switch_s = process_settings.enter_context(
        switch_interval(agent_cfg.gil_switch_interval_s))
    try:
        safe_arm = SafeArm(arm, safety, bounds_mm=workspace.phantom_bounds_mm)
        sensor.connect()
        # the arm is at its home pose (pad lifted) and nothing has moved it yet
        background = BackgroundTracker(reconstructor, background_cfg)
        background.capture(sensor, safe_arm.arm.state().force_n)
        registration = None
        if options.fiducials:
            # the presses go through the safety layer (force limit, the arm's box), with a
            # command timeout longer than one scripted move (they are not a command stream)
            motion = guarded(arm, safety)
            try:
                registration = await asyncio.to_thread(
                    calibrate_with_fiducials, motion, sensor, reconstructor, options.fiducials)
            finally:
                motion.safe.close()
            log.info("registration from %d fiducials: dx %.2f +- %.2f mm, dy %.2f +- %.2f mm, "
                     "yaw %.2f +- %.2f deg (residual rms %.2f mm)", registration.fiducials,
                     registration.dx_mm, registration.std_dx_mm, registration.dy_mm,
                     registration.std_dy_mm, registration.yaw_deg, registration.std_yaw_deg,
                     registration.residual_rms_mm)
            workspace = registration.workspace_to_arm(workspace)
            assembler = TactileAssembler(workspace, stiffness_to_k=stiffness_to_k,
                                         patch_size_mm=agent_cfg.patch_size_mm,
                                         friction=agent_cfg.friction)
            safe_arm.close()
            safe_arm = SafeArm(arm, safety, bounds_mm=workspace.phantom_bounds_mm)
        pipeline = FramePipeline(sensor, reconstructor, assembler, stiffness, safe_arm.arm.state,
                                 platform_pitch_mm=agent_cfg.patch_pitch_mm,
                                 sensor_max_age_ms=agent_cfg.sensor_max_age_ms,
                                 contact_force_n=stiffness_cfg.contact_force_n,
                                 background=background)
        warm_s = await asyncio.to_thread(pipeline.warm_up)
        log.info("reconstruction warmed up in %.0f ms", warm_s * 1e3)
        link = StationLink.from_config(link_cfg, "remote")
        if options.record is not None:
            recorder = McapRecorder(options.record, "remote", meta={
                "session": link_cfg.session, "arm": options.arm, "sensor": options.sensor,
                "phantom": options.phantom, "seed": options.seed if world else None,
                "workspace": dataclasses.asdict(workspace.config)})
            link.tap = recorder.tap
        async with link:
            station = RemoteStation(link, safe_arm, pipeline, stiffness, workspace.forward,
                                    agent_cfg, status=status)
            try:
                await station.run(stop, options.duration_s)
            finally:
                summary = station.summary()
                summary.update(session=link_cfg.session, arm_backend=options.arm,
                               sensor_backend=options.sensor, phantom=options.phantom,
                               seed=options.seed if world else None,
                               registration=registration.to_dict() if registration else None,
                               memory_lock=memory_lock.to_dict(),
                               gil_switch_interval_s=gil_switch_s)
                if recorder is not None:
                    try:
                        summary["recording"] = await asyncio.to_thread(recorder.close, summary)
                        lost = recorder.loss_error()
                        if lost is not None:  # finished, but incomplete: not a clean stop
                            raise lost
                    except ConfigError as err:  # a full disk: the summary is written still
                        log.error("%s", err)
                        recording_error = err
                        summary["recording"] = recorder.counts()
                        summary["recording_error"] = str(err)
                if on_summary is not None:
                    on_summary(summary)
        if recording_error is not None:
            raise recording_error  # exit 1 (as the local station), after the summary
        return summary
    finally:
        if safe_arm is not None:
            safe_arm.stop()
            safe_arm.close()
        sensor.disconnect()
        arm.disconnect()
        _set_opencv_threads(opencv_before)
        process_settings.close()
