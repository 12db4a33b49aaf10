"""Settings of the remote station agent (TOML table ``[remote.agent]``).

Resolve with ``shared.config.resolve_config(RemoteAgentConfig, "remote.agent", ...)``; the
link (``[remote.link]``), arm safety (``[arm.safety]``), workspace (``[workspace]``) and
stiffness (``[stiffness]``) settings resolve through their own dataclasses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from shared.errors import ConfigError
from shared.loop_watchdog import check_hang_timeout

__all__ = ["RemoteAgentConfig"]


@dataclass(frozen=True)
class RemoteAgentConfig:
    """Loop rates and tactile-frame layout of the remote station.

    Attributes:
        frame_rate_hz: sensor frames processed per second (>= 60 for the paper's display).
        patch_pitch_mm: tactile patch pitch on the display side (platform mm); the actual
            pitch is the nearest integer multiple of the sensor pixel.
        patch_size_mm: (x, y) patch extent in phantom mm; 0 = the whole sensor area.
        arm_poll_hz: rate of the arm monitor (safety poll, stiffness samples, link check).
        arm_state_hz: rate of ``arm_state`` messages to the local station (at most
            ``arm_poll_hz``: each carries one poll's reading).
        link_loss_halt_ms: the arm is halted when the link has been down this long (at most
            5000 ms).
        watchdog_period_s: period of the safety watchdog thread (command timeout, force
            limit), independent of the event loop.
        sensor_max_age_ms: a sensor frame older than this is refused (aged from its image's
            time: a camera's ``--sensor-latency-ms`` counts against it).
        stiffness_cell_mm: cell size of the stiffness map (the phantom's area in such
            cells at most ``remote_site.stiffness.stiffness_map.MAX_CELLS``, a million).
        friction: value of the friction layer (0 for palpation).
        status_interval_s: how often the status line is refreshed.
        tactile_codec: ``compact`` (protocol v2 ``tactile_compact``: int16 layers, deltas
            against key frames, Weber deadband; docs/protocol.md) or ``raw``
            (``tactile_frame``, float32 layers, understood by version-1 peers).
        tactile_weber: the compact codec's deadband, a fraction of the key frame's value.
        tactile_floor_um: the compact codec's absolute deadband on heights (um).
        tactile_key_every: the compact codec sends a key frame at least every this many
            frames (a late joiner or a lost key frame waits at most this long).
        capture_on_pose: with a sensor that captures on demand (the simulator; a camera
            streams on its own clock and keeps the frame clock), take the next frame as soon
            as the arm has reached the latest command's pose, instead of on the next tick of
            the frame clock. Frames keep a schedule of ``frame_rate_hz`` on average while
            commands come faster than that (the waits for a command and for the pose do not
            add up; before, when each frame was due a period after the previous one began,
            this default of 60 gave 47 frames/s with commands every 4 ms: docs/speed.md
            sections 16-17); no frame starts within half a period of the previous one, and
            without commands a frame comes every two periods.
        pose_tolerance_mm: the pose counts as reached within this distance of the target
            (or when the arm is no longer moving: settled, blocked or halted).
        pose_wait_max_ms: the arm is waited for only if, at its current speed towards the
            target, it gets there within this long of the command; otherwise the frame is
            taken at once (an arm tracking a moving hand lags it all the time: waiting would
            only add latency).
        command_fresh_ms: with capture on pose, a frame that is due (by the frame schedule)
            is taken at once only for a command applied at most this long
            ago; for an older one it waits for the next command, when that is due (by the
            commands' recent interval) within a frame period, so that the frame answers a
            command the moment it arrives instead of one that aged meanwhile (1000: taken at
            once, as the frame gate did before; the pose wait's first look stays).
        opencv_threads: OpenCV's thread count while the station runs (``cv2.setNumThreads``;
            restored after). 1 (default) runs its resizes and blurs in the calling thread:
            on sensor-sized frames (320 x 240) its worker pool saved nothing per frame but
            spun in ``sched_yield`` between frames (about 16,000 calls/s, 0.05 of a core in
            the demo; docs/speed.md section 9). 0 leaves OpenCV's own setting (one worker
            per core).
        lock_memory: keep the station's memory in RAM while it runs (``mlockall`` on
            fault, :mod:`shared.memlock`): the arm watchdog, the command path and the frame
            pipeline never wait for a page read back from disk. Taken only where it cannot
            make a later allocation fail (``RLIMIT_MEMLOCK`` unlimited, as the systemd unit
            sets, or ``CAP_IPC_LOCK``); otherwise logged at INFO and the summary's
            ``memory_lock.reason`` says why.
        gil_switch_interval_s: ``sys.setswitchinterval`` while the station runs (restored
            after; :mod:`shared.gil`): how long the frame pipeline's worker may keep the
            event loop (commands in, frames out) off the GIL. 0 leaves the interpreter's
            setting (5 ms) alone.
        hang_timeout_s: the station's event loop stuck this long (a busy loop, a call that
            never returns), or a frame's capture and processing in the pipeline's thread not
            returned after it, once its loops run: every thread's stack is written to standard
            error and the process exits with code 1 (:mod:`shared.loop_watchdog`), for
            systemd or a container's ``restart: on-failure`` to start it again. The arm's
            halt on lost commands (its own thread) and its safety limits do not wait for it.
            0: no such watchdog (a debugger's breakpoint stops the loop); else at least 1 s.
    """

    frame_rate_hz: float = 60.0
    patch_pitch_mm: float = 0.5
    patch_size_mm: tuple[float, float] = (0.0, 0.0)
    arm_poll_hz: float = 250.0
    arm_state_hz: float = 50.0
    link_loss_halt_ms: float = 100.0
    watchdog_period_s: float = 0.005
    sensor_max_age_ms: float = 100.0
    stiffness_cell_mm: float = 2.0
    friction: float = 0.0
    status_interval_s: float = 1.0
    tactile_codec: str = "compact"
    tactile_weber: float = 0.0
    tactile_floor_um: float = 2.0
    tactile_key_every: int = 30
    capture_on_pose: bool = True
    pose_tolerance_mm: float = 0.25
    pose_wait_max_ms: float = 10.0
    command_fresh_ms: float = 1.0
    opencv_threads: int = 1
    lock_memory: bool = True
    gil_switch_interval_s: float = 0.0
    hang_timeout_s: float = 30.0

    def __post_init__(self) -> None:
        check_hang_timeout("remote.agent.hang_timeout_s", self.hang_timeout_s)
        positive = ("frame_rate_hz", "patch_pitch_mm", "arm_poll_hz", "arm_state_hz",
                    "link_loss_halt_ms", "watchdog_period_s", "sensor_max_age_ms",
                    "stiffness_cell_mm", "status_interval_s", "pose_tolerance_mm")
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(f"remote.agent.{name} must be finite and > 0, got {value!r}")
        if not self.link_loss_halt_ms <= 5000.0:  # docs/safety.md: halted within 100 ms
            raise ConfigError(f"remote.agent.link_loss_halt_ms ({self.link_loss_halt_ms:g}) "
                              "must be <= 5000: the arm must be halted soon after the link "
                              "is lost (docs/safety.md)")
        if not (math.isfinite(self.pose_wait_max_ms) and 0.0 <= self.pose_wait_max_ms <= 1000.0):
            raise ConfigError("remote.agent.pose_wait_max_ms must lie in [0, 1000], got "
                              f"{self.pose_wait_max_ms!r}")
        if not (math.isfinite(self.command_fresh_ms) and 0.0 <= self.command_fresh_ms <= 1000.0):
            raise ConfigError("remote.agent.command_fresh_ms must lie in [0, 1000], got "
                              f"{self.command_fresh_ms!r}")
        if not (isinstance(self.gil_switch_interval_s, int | float)
                and math.isfinite(self.gil_switch_interval_s)
                and 0.0 <= self.gil_switch_interval_s <= 0.1):
            raise ConfigError("remote.agent.gil_switch_interval_s must lie in [0, 0.1] s, got "
                              f"{self.gil_switch_interval_s!r}")
        if isinstance(self.opencv_threads, bool) or not isinstance(self.opencv_threads, int) \
                or not 0 <= self.opencv_threads <= 256:
            raise ConfigError("remote.agent.opencv_threads must be an integer in [0, 256], "
                              f"got {self.opencv_threads!r}")
        if not isinstance(self.lock_memory, bool):
            raise ConfigError(f"remote.agent.lock_memory must be true or false, "
                              f"got {self.lock_memory!r}")
        if self.frame_rate_hz > 1000.0 or self.arm_poll_hz > 2000.0:
            raise ConfigError("remote.agent: frame_rate_hz <= 1000 and arm_poll_hz <= 2000")
        if self.arm_state_hz > self.arm_poll_hz:  # each arm_state is one poll's reading
            raise ConfigError(f"remote.agent.arm_state_hz ({self.arm_state_hz:g}) must be <= "
                              f"remote.agent.arm_poll_hz ({self.arm_poll_hz:g}): each "
                              "arm_state carries one poll's reading")
        if len(self.patch_size_mm) != 2 or not all(
                math.isfinite(v) and v >= 0 for v in self.patch_size_mm):
            raise ConfigError("remote.agent.patch_size_mm must be two numbers >= 0")
        if not 0.0 <= self.friction <= 1.0:
            raise ConfigError("remote.agent.friction must lie in [0, 1]")
        if self.tactile_codec not in ("compact", "raw"):
            raise ConfigError("remote.agent.tactile_codec must be 'compact' or 'raw', got "
                              f"{self.tactile_codec!r}")
        if not (0.0 <= self.tactile_weber < 1.0 and 0.0 <= self.tactile_floor_um <= 1000.0
                and 1 <= self.tactile_key_every <= 10000):
            raise ConfigError("remote.agent: tactile_weber in [0, 1), tactile_floor_um in "
                              "[0, 1000], tactile_key_every in [1, 10000]")
