"""The remote station's loops: follow platform states, stream tactile frames and arm state.

Four asyncio tasks share one :class:`RemoteStation`:

* **receive**: every ``platform_state`` from the relay goes through the workspace map to a
  :class:`~remote_site.arm.safety.SafeArm` move, age-checked with the relay's clock offsets
  (``age = (now_remote - off_remote) - (ts_local - off_local)``; older than 100 ms: dropped
  and counted). ``arm_command`` messages go to :meth:`SafeArm.handle`.
* **arm monitor** (``arm_poll_hz``): :meth:`SafeArm.poll` (no command for 100 ms halts, the
  force limit), every reading to the stiffness stage, the link-loss halt (link down for more
  than ``link_loss_halt_ms``), and ``arm_state`` at ``arm_state_hz``.
* **frames** (at most ``frame_rate_hz``): :meth:`FramePipeline.process` in a worker thread
  (numpy releases the GIL, so the receive path stays responsive), then ``tactile_frame`` out.
  With a sensor that captures on demand (the simulator) and ``capture_on_pose``, a frame is
  taken as soon as the arm has reached the pose of the latest applied command (within
  ``pose_tolerance_mm``, or no longer moving), on a schedule of one frame per period
  (:func:`next_frame_due_s`: the waits for a command and for the pose do not add up, so
  ``frame_rate_hz`` is met on average); a frame that is due when the newest command is older than
  ``command_fresh_ms`` waits for the next command if that is due within a frame period (by
  the commands' recent interval, :func:`next_command_wait_s`), so frames answer commands as
  they arrive; an arm that will not get there within ``pose_wait_max_ms`` of the command
  at its current speed (tracking a moving hand, it lags all the time) is not waited for;
  without a new command within a period of its due time, a frame is taken anyway (it keeps
  the touch fresh) and the schedule restarts at it: a frame every two periods. A streaming camera
  keeps the frame clock: the newest frame at each tick (:func:`pose_reached`,
  :class:`CaptureCounters`); a camera that says when a new image arrives
  (``notifies_frames``) is read as it arrives instead, at most ``frame_rate_hz``. Its image
  was taken before the tick, perhaps before the newest
  command: the frame is paired with the command applied by the image's timestamp
  (:meth:`RemoteStation.applied_at`), never a later one, and placed at the arm's pose then
  (:meth:`RemoteStation.reading_at`, between the two arm polls around it). The timestamp
  is the arrival less the camera's known latency (``--sensor-latency-ms``; 0 by default,
  which leaves a real delay uncounted).
* **status**: one status line per ``status_interval_s``.

The StationLink answers clock pings and reconnects with backoff by itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from typing import Any, Protocol

import numpy as np

from remote_site.agent.config import RemoteAgentConfig
from remote_site.agent.pipeline import FrameOutcome, FramePipeline
from remote_site.agent.stiffness_stage import StiffnessStage
from remote_site.arm.base import ArmReading, polled_reading_at
from remote_site.arm.safety import CommandResult, SafeArm
from remote_site.tactile import AppliedCommand
from shared.client import LinkCounters
from shared.errors import DeviceError, InputDataError, LocalProtocolError
from shared.freshness import ClockView
from shared.loop_watchdog import WaitedCalls, loop_watchdog
from shared.protocol.messages import (
    MOTION_CARRY_MAX_US,
    ArmCommand,
    Message,
    PlatformState,
    carry_motion,
    without_motion,
)
from shared.protocol.tactile_codec import CodecSettings, TactileEncoder
from shared.sd_notify import service
from shared.timebase import monotonic_s, now_us

__all__ = ["ARM_FAULT_RESTART_S", "RemoteStation", "StationCounters", "command_clock",
           "next_command_wait_s", "next_frame_due_s", "percentiles_ms"]

log = logging.getLogger(__name__)


class _Link(Protocol):
    """What the station needs of :class:`shared.client.StationLink`."""

    counters: LinkCounters

    @property
    def is_connected(self) -> bool: ...

    @property
    def clock_view(self) -> ClockView | None: ...

    def link_down_for_s(self, now_s: float | None = None) -> float: ...

    async def send(self, msg: Message) -> None: ...

    async def recv(self, timeout_s: float | None = None) -> Message: ...


@dataclass
class StationCounters:
    """Running totals of the station (see :meth:`RemoteStation.summary`)."""

    platform_states: int = 0
    platform_applied: int = 0
    platform_dropped_no_clock: int = 0
    #: platform states the arm's safety layer refused: stale by their stamp, or their age not
    #: judged finely enough (the arm_commands' refusals are the safety layer's own counters)
    platform_dropped_stale: int = 0
    platform_dropped_clock: int = 0
    platform_invalid: int = 0
    arm_commands: int = 0
    arm_commands_applied: int = 0
    frames_sent: int = 0
    frames_not_sent_link_down: int = 0
    #: frames whose schedule fell more than a period behind (not counted for a sensor read as
    #: its images arrive: there is no schedule to fall behind)
    frames_late: int = 0
    arm_states_sent: int = 0
    link_loss_halts: int = 0
    stiffness_samples_rejected: int = 0
    #: arm device errors (a lost state packet, a failed move) the loops went on after
    arm_errors: int = 0
    #: arm readings the wire refused to carry (a force or position beyond its ranges)
    arm_states_refused: int = 0


@dataclass
class CaptureCounters:
    """Why each frame was taken (capture on pose; see the module docstring).

    Attributes:
        on_pose: the arm had reached the latest command's pose.
        moving: the arm was still on its way and would not get there within
            ``pose_wait_max_ms`` of the command at its speed (an arm tracking a moving hand
            lags it all the time): taken at once rather than waited for.
        idle: no new command for a period (refresh).
        clock: the frame clock (a streaming sensor, or ``capture_on_pose`` off).
        on_arrival: frames (counted under ``clock`` as well) taken as the streaming sensor's
            new image arrived (a source that notifies, :attr:`TactileSensor.notifies_frames`);
            the other clock ticks of such a sensor came after ``sensor_max_age_ms`` without
            one.
        waited_for_command: frames (counted above as well) that were due while the newest
            command was older than ``command_fresh_ms`` and waited for the next one.
    """

    on_pose: int = 0
    moving: int = 0
    idle: int = 0
    clock: int = 0
    on_arrival: int = 0
    waited_for_command: int = 0


def pose_reached(reading: ArmReading, tolerance_mm: float) -> bool:
    """Whether the arm has reached its commanded pose: within ``tolerance_mm`` of its target,
    or not moving any more (settled, blocked, halted, no target)."""
    if reading.target_mm is None or reading.status != "moving":
        return True
    return math.dist(reading.position_mm, reading.target_mm) <= tolerance_mm


def pose_eta_s(reading: ArmReading, tolerance_mm: float) -> float:
    """When the arm will be within ``tolerance_mm`` of its target at its current speed
    towards it (0 when reached; ``inf`` when it is not closing in)."""
    if pose_reached(reading, tolerance_mm):
        return 0.0
    assert reading.target_mm is not None
    closing = closing_speed_mm_s(reading)
    dist = math.dist(reading.target_mm, reading.position_mm)
    return (dist - tolerance_mm) / closing if closing > 1e-9 else math.inf


def closing_speed_mm_s(reading: ArmReading) -> float:
    """The arm's speed towards its target (negative: moving away; 0 without a target or at
    it)."""
    if reading.target_mm is None:
        return 0.0
    gap = [t - p for t, p in zip(reading.target_mm, reading.position_mm, strict=True)]
    dist = math.hypot(*gap)
    if dist == 0.0:
        return 0.0
    return sum(v * g for v, g in zip(reading.velocity_mm_s, gap, strict=True)) / dist


#: arm calls of one loop failing this long without a success between end the station (for
#: its supervisor to start it again and the arm backend to recover as it connects)
ARM_FAULT_RESTART_S = 2.0
#: a failure this long after the previous one starts a new run (the receive loop may have
#: had no command to apply in between)
_ARM_FAULT_GAP_S = 0.5

#: an arm slower than this is at rest (the pose wait gives it time to set off)
_AT_REST_MM_S = 1.0

#: command gaps longer than this are pauses (link, operator), not the command rate
_COMMAND_GAP_MAX_S = 0.1

#: a frame whose first unshown state came longer ago than this ends an outage of the touch
#: path (a sensor or pipeline stall): it counts from its own state's sample, not the outage
#: (the loaded tails measured so far stay well below it, 0.16-0.45 s at worst); the same
#: bound as a latest-wins slot's carry (:data:`~shared.protocol.MOTION_CARRY_MAX_US`)
_CHAIN_MAX_S = MOTION_CARRY_MAX_US / 1e6

#: the platform states kept (with the commands applied from them) to find the one a
#: streaming sensor's image answers: seconds of states at any usable rate, while an image
#: older than ``sensor_max_age_ms`` (100 ms by default) is refused
_RECEIVED_KEEP = 2048

#: the arm readings kept to place a streaming sensor's image (with ``arm_poll_hz`` <= 2000,
#: a quarter of a second or more)
_READINGS_KEEP = 512


@dataclass(frozen=True, slots=True)
class _Chain:
    """The first platform_state received since the last capture that gave a frame."""

    first: PlatformState
    connects: int
    since_s: float


def _finite(reading: ArmReading) -> bool:
    """Whether a reading's force and position are finite (else the arm is at fault)."""
    return math.isfinite(reading.force_n) and all(math.isfinite(v) for v in reading.position_mm)


def next_command_wait_s(age_s: float, interval_s: float | None, fresh_s: float,
                        period_s: float) -> float:
    """How long a frame that is due now waits for the next command (0: taken at once).

    Args:
        age_s: how long ago the newest command was applied.
        interval_s: the commands' recent interval (None: not known yet).
        fresh_s: a command at most this old is answered at once.
        period_s: the frame period (the longest wait).

    Returns:
        0 for a fresh command, an unknown interval, or a next command not due within a
        period; else the time until the next one is due plus half an interval of slack for
        its jitter, at most ``period_s`` (it usually arrives, and ends the wait, sooner).
    """
    if age_s <= fresh_s or interval_s is None:
        return 0.0
    due_s = interval_s - age_s
    if due_s > period_s:
        return 0.0
    return min(period_s, max(0.0, due_s) + 0.5 * interval_s)


def next_frame_due_s(due_s: float, start_s: float, now_s: float, period_s: float,
                     answered: bool) -> tuple[float, bool]:
    """When the next frame is due with capture on pose, and whether the schedule fell behind.

    A frame that answered a new command keeps an absolute schedule: the next is due a period
    after this one was *due*, not after it began, so the waits before a frame (for the next
    command, for the pose: a few ms each) do not add up. (Counted from each frame's start,
    ``frame_rate_hz = 60`` gave 47 frames/s with commands every 4 ms; docs/speed.md section
    17.) A schedule more than a period behind ``now_s`` restarts at ``now_s`` (late: True),
    and no frame starts sooner than half a period after the previous one began: a schedule
    that fell behind is not caught up in back-to-back frames (beside two CPU burners they
    lengthened the motion-to-touch tail), and waits of up to half a period still do not add
    up. An idle frame (no new command within a period of its due time) restarts the
    schedule at its start: without commands, a frame every two periods.

    Args:
        due_s: when this frame was due.
        start_s: when it began (after its waits).
        now_s: now (after it was processed and sent).
        period_s: the frame period.
        answered: whether the frame answered a new command.
    """
    if not answered:
        return start_s + period_s, False
    due_s += period_s
    late = due_s < now_s - period_s
    if late:
        due_s = now_s
    return max(due_s, start_s + 0.5 * period_s), late


def command_clock(view: ClockView | None) -> tuple[float, float] | None:
    """Our clock minus the local station's, and its error bound, from the relay's offsets
    (None when either is unknown: commands are then refused)."""
    return None if view is None else view.relative("remote", "local", now_us())


def percentiles_ms(samples_s: Any) -> dict[str, float] | None:
    """n, p50, p99, mean and max (ms) of samples in seconds; None when empty."""
    arr = np.asarray(list(samples_s), dtype=float) * 1000.0
    if arr.size == 0:
        return None
    return {"n": int(arr.size), "p50": float(np.percentile(arr, 50)),
            "p99": float(np.percentile(arr, 99)), "mean": float(arr.mean()),
            "max": float(arr.max())}


class RemoteStation:
    """Runs the remote station's loops around the devices and the link.

    Args:
        link: the station's relay link (started by the caller).
        safe_arm: the arm behind the station's safety layer (connected).
        pipeline: the frame pipeline (sensor connected).
        stiffness: the stiffness stage the pipeline reads.
        workspace_forward: platform mm -> phantom mm (``WorkspaceMap.forward``).
        config: loop rates and limits.
        status: called with the status text every ``status_interval_s`` (None: no status).
    """

    def __init__(self, link: _Link, safe_arm: SafeArm, pipeline: FramePipeline,
                 stiffness: StiffnessStage, workspace_forward: Callable[[Any], np.ndarray],
                 config: RemoteAgentConfig | None = None, *,
                 status: Callable[[str], None] | None = None) -> None:
        self.link = link
        self.safe_arm = safe_arm
        self.pipeline = pipeline
        self.stiffness = stiffness
        self.forward = workspace_forward
        self.config = config or RemoteAgentConfig()
        self.status = status
        self.counters = StationCounters()
        self.latest: AppliedCommand | None = None
        #: the first platform_state received since the last capture that gave a frame (the
        #: link connection it came on, when): what the next frame is the first to show
        #: starts there (:meth:`_frame_source`)
        self._chain: _Chain | None = None
        #: every state received with its age checkable, in order, with the command applied
        #: from it (None: refused): which command an image answers, and the chain its
        #: capture leaves for the next frame (the states received after that command)
        self._received: deque[tuple[_Chain, AppliedCommand | None]] = deque(
            maxlen=_RECEIVED_KEEP)
        #: the arm's readings as polled (our clock, microseconds): where the arm was when a
        #: streaming sensor's image was taken
        self._readings: deque[tuple[int, ArmReading]] = deque(maxlen=_READINGS_KEEP)
        #: the command the last frame given answered (a capture of it again is idle)
        self._answered: AppliedCommand | None = None
        self.last_reading: ArmReading | None = None
        self.captures = CaptureCounters()
        #: the frame calls in the pipeline's thread, watched like the loop (hang_timeout_s)
        self.waited = WaitedCalls()
        #: set when a platform_state is applied to the arm (wakes a frame capture on pose)
        self._command_applied = asyncio.Event()
        #: the commands' recent interval (seconds, moving average; None: not known yet)
        self.command_interval_s: float | None = None
        self._frame_seq = 0
        self._arm_state_seq = 0
        self._link_halted = False
        self._warned_no_clock = False
        #: per loop, whether its last arm call failed (one warning per run of failures)
        #: per loop, (since, last): when its run of arm failures began and when it last
        #: failed (None or absent: the last call succeeded)
        self._arm_failing: dict[str, tuple[float, float] | None] = {}
        self._frame_read_warned = False
        self._started_s: float | None = None
        self._stopped_s: float | None = None
        window = 20_000
        self.pipeline_s: deque[float] = deque(maxlen=window)
        #: exposure to arrival of each frame's image (a camera's given latency; 0 on demand)
        self.delivery_s: deque[float] = deque(maxlen=window)
        self.capture_s: deque[float] = deque(maxlen=window)
        self.reconstruct_s: deque[float] = deque(maxlen=window)
        self.assemble_s: deque[float] = deque(maxlen=window)
        self.dispatch_s: deque[float] = deque(maxlen=window)
        self.frame_period_s: deque[float] = deque(maxlen=window)
        #: from a command's application to the start of the frame that answers it (frames
        #: answering a new command only; with a streaming sensor, to its image's time): the
        #: wait part of the ledger's arm_and_sensor stage
        self.command_wait_s: deque[float] = deque(maxlen=window)
        cfg = self.config
        #: the compact tactile codec (None: raw tactile_frame messages)
        self.encoder = TactileEncoder(CodecSettings(
            weber=cfg.tactile_weber, floor={"height_mm": cfg.tactile_floor_um * 1e-3},
            key_every=cfg.tactile_key_every)) if cfg.tactile_codec == "compact" else None
        #: the link session (``counters.connects``) the encoder's key frame was sent in
        self._encoder_connects = -1

    # ------------------------------------------------------------------ commands

    def apply_platform_state(self, state: PlatformState) -> CommandResult | None:
        """Turn one platform_state into a safe arm move (age-checked, clamped).

        Returns:
            The safety layer's result, or None when the state was not offered to the arm
            (clock offsets unknown, or an invalid position).
        """
        self.counters.platform_states += 1
        clock = command_clock(self.link.clock_view)
        if clock is None:  # the touch path is not up yet (or no longer): no chain starts
            self.counters.platform_dropped_no_clock += 1
            if not self._warned_no_clock:
                log.warning("clock offsets not reported by the relay yet: platform states "
                            "are dropped until their age can be checked")
                self._warned_no_clock = True
            return None
        connects = self.link.counters.connects
        joined = _Chain(state, connects, monotonic_s())
        if self._chain is None or self._chain.connects != connects:
            self._chain = joined
        try:
            target = self.forward(state.position_mm)
            result = self.safe_arm.move(tuple(float(v) for v in target),
                                        sent_ts_us=state.ts_us, clock_offset_us=clock[0],
                                        offset_uncertainty_us=clock[1])
        except InputDataError as err:
            self._received.append((joined, None))
            self.counters.platform_invalid += 1
            log.warning("unusable platform_state %d: %s", state.seq, err)
            return None
        if result.refused == "stale":
            self.counters.platform_dropped_stale += 1
        elif result.refused is not None:
            self.counters.platform_dropped_clock += 1
        if result.accepted:
            t_us = now_us()
            if self.latest is not None:
                gap_s = (t_us - self.latest.arm_command_us) / 1e6
                if 0.0 < gap_s <= _COMMAND_GAP_MAX_S:
                    prev = self.command_interval_s
                    self.command_interval_s = gap_s if prev is None else prev + (gap_s - prev) / 8
            self.latest = AppliedCommand(state, t_us, result.speed_before_mm_s)
            self._command_applied.set()
            self.counters.platform_applied += 1
            rx = [h.t_us for h in state.hops if h.clock == "remote" and h.stage == "station_rx"]
            if rx:
                self.dispatch_s.append(max(0, t_us - rx[-1]) / 1e6)
        self._received.append((joined, self.latest if result.accepted else None))
        return result

    def applied_at(self, t_us: int) -> AppliedCommand | None:
        """The latest command applied to the arm at or before ``t_us`` (our clock): what an
        image taken then can show (None: none kept was; a streaming sensor's image may be
        older than the newest command)."""
        latest = self.latest
        if latest is None or latest.arm_command_us <= t_us:
            return latest
        for _, applied in reversed(self._received):
            if applied is not None and applied.arm_command_us <= t_us:
                return applied
        return None

    def reading_at(self, t_us: int) -> ArmReading:
        """Where the arm was at ``t_us`` (our clock; when an image was taken), from its
        polled readings (:func:`~remote_site.arm.base.polled_reading_at`); the current
        reading before any was polled."""
        found = polled_reading_at(self._readings, t_us)
        return self.pipeline.read_arm() if found is None else found

    def _after(self, command: AppliedCommand) -> _Chain | None:
        """The first state received after ``command`` (on the newest state's link
        connection): where the chain a capture of it leaves for the next frame starts."""
        if not self._received:
            return None
        connects = self._received[-1][0].connects
        first = None
        for joined, applied in reversed(self._received):
            if applied is command:
                return first
            if joined.connects == connects:
                first = joined
        return None  # no longer kept (more than _RECEIVED_KEEP states since it)

    def _frame_source(self, command: AppliedCommand | None
                      ) -> tuple[AppliedCommand | None, _Chain | None]:
        """What the frame captured now answers, and the chain it takes (to hand back with
        :meth:`_keep_chain` when the capture gives no frame).

        ``local.motion`` (docs of shared/motion_to_touch.py) is the start of the earliest
        movement a frame is the first to show. Frames come a few times slower than states:
        every state received since the last capture that gave a frame, up to the command
        captured (passed over, refused as too old or unusable: positions are absolute, so a
        newer state shows their movements too) is first shown by this frame, so it starts
        where the first of them started, as a latest-wins slot hands a replaced state's start
        on (:func:`~shared.protocol.carry_motion`). States received after the command captured
        (refused, or applied after a streaming sensor's image was taken) are left for the
        next frame. Not across a reconnect of the link, nor when the first
        of them reached this station more than :data:`_CHAIN_MAX_S` ago (an outage of the
        touch path, not a latency: the frame then counts from its own state's sample, as the
        uplink does across a platform outage). A command a frame already answered is
        captured again idle: that frame shows nothing first and carries no platform stamps.
        """
        if command is None:
            return None, None
        if command is self._answered:
            return dataclasses.replace(command, answers=False), None
        # the states received after this command (refused, or applied after the image of a
        # streaming sensor) stay for the next frame: it shows them first
        chain, self._chain = self._chain, self._after(command)
        state = command.state
        if chain is not None and chain.connects == self.link.counters.connects:
            if monotonic_s() - chain.since_s <= _CHAIN_MAX_S:
                state = carry_motion(chain.first, state)
            else:
                state = without_motion(state)
        return dataclasses.replace(command, state=state), chain

    def _keep_chain(self, chain: _Chain | None) -> None:
        """A capture gave no frame: its chain goes on (it started before any left or begun
        since)."""
        if chain is not None and chain.connects == self.link.counters.connects:
            self._chain = chain

    def apply_arm_command(self, command: ArmCommand) -> CommandResult:
        """Apply an explicit arm command (stop always acts; the others are age-checked)."""
        self.counters.arm_commands += 1
        clock = command_clock(self.link.clock_view)
        result = self.safe_arm.handle(command, clock_offset_us=None if clock is None
                                      else clock[0],
                                      offset_uncertainty_us=0.0 if clock is None else clock[1])
        if result.accepted:
            self.counters.arm_commands_applied += 1
        return result

    # ------------------------------------------------------------------ loops

    def _arm_error(self, loop: str, err: DeviceError) -> None:
        """An arm call of ``loop`` failed: counted, the first of a run logged, the arm
        stopped if it can be. The loop goes on: one lost packet or failed move must not end
        the station. A fault that lasts :data:`ARM_FAULT_RESTART_S` (failures with no
        success and no gap of :data:`_ARM_FAULT_GAP_S` between) is raised: it ends the
        station (exit 1), so that its supervisor (systemd's ``Restart=``) starts it again
        and the arm backend recovers as it connects (a Franka's reflex needs that), instead
        of a station that stays up with a dead arm.

        Raises:
            DeviceError: ``err``, once the run of failures has lasted that long.
        """
        self.counters.arm_errors += 1
        run = self._arm_failing.get(loop)
        now_s = monotonic_s()
        # a run is failures with no success and no quiet gap between: two lone failures
        # of a loop that had nothing to do in between are not a lasting fault
        since = now_s if run is None or now_s - run[1] > _ARM_FAULT_GAP_S else run[0]
        self._arm_failing[loop] = (since, now_s)
        if since == now_s:
            log.warning("arm error in the %s loop (halting the arm, going on): %s", loop, err)
        elif now_s - since >= ARM_FAULT_RESTART_S:
            log.error("arm calls of the %s loop have failed for %.1f s: ending the station "
                      "for its supervisor to start it again (%s)", loop, now_s - since, err)
            raise err
        with contextlib.suppress(DeviceError):
            self.safe_arm.stop()

    def _frame_read_failed(self, err: DeviceError) -> None:
        """An arm read of the frame path failed: counted (``arm_errors``), the first
        logged; the arm is left to the arm loop, whose polls stop it and judge a fault that
        lasts."""
        self.counters.arm_errors += 1
        if not self._frame_read_warned:
            self._frame_read_warned = True
            log.warning("an arm read for a frame failed (counted, going on): %s", err)

    async def _receive_loop(self) -> None:
        while True:
            msg = await self.link.recv()
            result: CommandResult | None = None
            try:
                if isinstance(msg, PlatformState):
                    result = self.apply_platform_state(msg)
                elif isinstance(msg, ArmCommand):
                    result = self.apply_arm_command(msg)
                elif log.isEnabledFor(logging.DEBUG):
                    log.debug("ignoring %s from the relay", msg.TYPE)
            except DeviceError as err:
                self._arm_error("receive", err)
            else:
                if result is not None and result.accepted:  # the arm took a command
                    self._arm_failing["receive"] = None

    def _check_link(self) -> None:
        if self.link.is_connected:
            self._link_halted = False
            return
        down_ms = self.link.link_down_for_s() * 1000.0
        if (self.link.counters.connects > 0 and not self._link_halted
                and down_ms > self.config.link_loss_halt_ms):
            self.safe_arm.stop()
            self._link_halted = True
            self.counters.link_loss_halts += 1
            log.warning("link to the relay down for %.0f ms: arm halted", down_ms)

    async def _arm_loop(self) -> None:
        period = 1.0 / self.config.arm_poll_hz
        state_period = 1.0 / self.config.arm_state_hz
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        next_state_t = next_t
        while True:
            reading: ArmReading | None = None
            try:
                reading = self._poll_arm()
                self._check_link()
            except DeviceError as err:
                self._arm_error("arm monitor", err)
            else:
                self._arm_failing["arm monitor"] = None
            now = loop.time()
            # a non-finite reading cannot go on the wire (SafeArm halted the arm for it)
            if reading is not None and _finite(reading) and now >= next_state_t:
                next_state_t = max(next_state_t + state_period, now)
                if self.link.is_connected:
                    self._arm_state_seq += 1
                    source = self.latest.state.seq if self.latest is not None else None
                    try:
                        await self.link.send(reading.to_message(self._arm_state_seq, now_us(),
                                                                source))
                    except LocalProtocolError as err:  # a reading the wire's ranges refuse
                        self.counters.arm_states_refused += 1
                        if self.counters.arm_states_refused == 1:
                            log.warning("arm_state not sent: %s", err)
                    else:
                        self.counters.arm_states_sent += 1
            next_t += period
            delay = next_t - loop.time()
            if delay < -0.05:
                next_t = loop.time()
            await asyncio.sleep(max(0.0, delay))

    def _poll_arm(self) -> ArmReading:
        """One :meth:`SafeArm.poll`: the reading kept and handed to the stiffness stage
        (a non-finite one only kept as the latest: it places nothing)."""
        polled_us = now_us()
        reading = self.safe_arm.poll()
        # stamped halfway through the poll: an arm whose poll takes a while (a real
        # one's round trip) is placed no later than it was
        polled_us = (polled_us + now_us()) // 2
        self.last_reading = reading
        if not _finite(reading):
            return reading
        self._readings.append((polled_us, reading))
        try:
            self.stiffness.add_sample(reading.t_s, reading.position_mm, reading.force_n)
        except InputDataError as err:
            self.counters.stiffness_samples_rejected += 1
            if self.counters.stiffness_samples_rejected == 1:
                log.warning("arm sample rejected by the stiffness stage: %s", err)
        return reading

    @property
    def _reads_on_arrival(self) -> bool:
        """Whether frames are taken as a streaming sensor's images arrive."""
        sensor = self.pipeline.sensor
        return sensor.notifies_frames and not sensor.captures_on_demand

    @property
    def captures_on_pose(self) -> bool:
        """Whether frames are taken on pose reached (else on the frame clock)."""
        return self.config.capture_on_pose and self.pipeline.sensor.captures_on_demand

    async def _until_pose(self, command: AppliedCommand) -> None:
        """Return once the arm has reached ``command``'s pose, or at once when it will not
        reach it within ``pose_wait_max_ms`` of the command at its current speed (an arm
        that set off from rest or settling for this command is given until then while it
        speeds up)."""
        loop = asyncio.get_running_loop()
        tolerance_mm = self.config.pose_tolerance_mm
        wait_s = self.config.pose_wait_max_ms / 1000.0 - (now_us() - command.arm_command_us) / 1e6
        deadline = loop.time() + wait_s
        prev_closing: float | None = None
        from_rest: bool | None = None
        while True:
            try:
                reading = self.pipeline.read_arm()
            except DeviceError as err:
                # a lost read: the frame is taken without waiting for the pose (counted as
                # not on pose). The arm is not stopped for it, nor is a run of failures
                # kept: the arm loop's polls judge whether the arm is gone.
                self._frame_read_failed(err)
                self.captures.moving += 1
                return
            eta_s = pose_eta_s(reading, tolerance_mm)
            if eta_s == 0.0:
                self.captures.on_pose += 1
                return
            # an arm not yet on its way to this target (at rest, or still settling from its
            # previous move: its speed is not towards this target) is given until the
            # deadline, and so is one that set off from there and is still speeding up: its
            # speed then says little about when it arrives. (Judged by the absolute speed, a
            # 10 mm step was captured 2 ms after its command, the pad at the start.) An arm
            # already closing in when it is first looked at is tracking a moving hand (each
            # command moves its target a little further, so it is always speeding up a
            # little): judged by its speed at once, without a second look a millisecond
            # later (that look slept at least 1 ms per frame, docs/speed.md section 15).
            closing = closing_speed_mm_s(reading)
            if from_rest is None:
                # at rest when the command was given, or still (a look within a millisecond
                # or two of the command may find an arm from rest already above 1 mm/s)
                from_rest = closing < _AT_REST_MM_S or (
                    command.arm_speed_mm_s is not None
                    and command.arm_speed_mm_s < _AT_REST_MM_S)
            # an arm from rest is starting at the first look, and while it speeds up
            starting = closing < _AT_REST_MM_S or (from_rest and (
                prev_closing is None or closing > prev_closing * 1.001))
            prev_closing = closing
            if loop.time() >= deadline or (loop.time() + eta_s > deadline and not starting):
                self.captures.moving += 1
                return
            await asyncio.sleep(0.001)

    async def _next_capture(self, earliest_s: float, period: float,
                            captured: AppliedCommand | None) -> bool:
        """Wait for the moment of the next frame (capture on pose, see the module doc);
        return whether it answers a new command (False: an idle frame)."""
        loop = asyncio.get_running_loop()
        delay = earliest_s - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)
        latest = self.latest
        if latest is None or latest is captured:  # nothing new: wait for one, at most a period
            wait_s = period
        else:  # a command not answered yet: now if fresh, else its successor if due soon
            wait_s = next_command_wait_s((now_us() - latest.arm_command_us) / 1e6,
                                         self.command_interval_s,
                                         self.config.command_fresh_ms / 1000.0, period)
        if wait_s > 0:
            self._command_applied.clear()
            # asyncio.timeout, not wait_for: no task is created per frame
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(wait_s):
                    await self._command_applied.wait()
            if latest is not None and latest is not captured:
                self.captures.waited_for_command += 1
        command = self.latest
        if command is captured or command is None:
            self.captures.idle += 1
            return False
        await self._until_pose(command)
        return True

    async def _next_arrival(self, earliest_s: float, arrived: asyncio.Event) -> None:
        """Wait for a streaming sensor's next image (not before ``earliest_s``: at most
        ``frame_rate_hz``), or ``sensor_max_age_ms`` without one (the tick then finds the
        newest frame too old, or the same one again, and says so). A notice of the image the
        last tick already took (stored just before that tick, announced just after) is not
        an arrival: the wait goes on."""
        loop = asyncio.get_running_loop()
        delay = earliest_s - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)
        deadline = loop.time() + self.config.sensor_max_age_ms / 1000.0
        sensor = self.pipeline.sensor
        while True:
            if not arrived.is_set():
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout_at(deadline):
                        await arrived.wait()
            if not arrived.is_set():
                return  # none within the limit
            arrived.clear()
            if sensor.newest_seq != self.pipeline.last_sensor_seq:
                self.captures.on_arrival += 1
                return

    async def _frame_loop(self, executor: ThreadPoolExecutor) -> None:
        sensor = self.pipeline.sensor
        loop = asyncio.get_running_loop()
        arrived: asyncio.Event | None = None
        if self._reads_on_arrival:
            arrived = asyncio.Event()
            event = arrived

            def on_frame() -> None:  # the sensor's thread
                loop.call_soon_threadsafe(event.set)

            sensor.on_frame = on_frame
        try:
            await self._frames(executor, arrived)
        finally:
            if arrived is not None:
                sensor.on_frame = None

    async def _frames(self, executor: ThreadPoolExecutor, arrived: asyncio.Event | None
                      ) -> None:
        period = 1.0 / self.config.frame_rate_hz
        on_pose = self.captures_on_pose
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        last_start: float | None = None
        captured: AppliedCommand | None = None
        answered = False
        while True:
            if on_pose:  # a command whose capture gave no frame is still new
                answered = await self._next_capture(next_t, period, self._answered)
            elif arrived is not None:  # a streaming sensor's image as it arrives
                await self._next_arrival(next_t, arrived)
                self.captures.clock += 1
            else:
                delay = next_t - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                self.captures.clock += 1
            start = loop.time()
            if last_start is not None:
                self.frame_period_s.append(start - last_start)
            last_start = start
            outcome: FrameOutcome
            if self.pipeline.sensor.captures_on_demand:  # the image is taken now
                if self.latest is not captured and self.latest is not None:
                    self.command_wait_s.append(
                        max(0, now_us() - self.latest.arm_command_us) / 1e6)
                captured = self.latest
                source, chain = self._frame_source(captured)
                with self.waited.waiting_for("a frame's capture and processing"):
                    outcome = await loop.run_in_executor(
                        executor, self.pipeline.process, self._frame_seq + 1, source)
            else:
                answered_before = self._answered
                captured, chain, outcome = await self._streamed_frame(executor)
                if outcome.frame is not None and captured is not None \
                        and captured is not answered_before:  # to the image's time
                    self.command_wait_s.append(
                        max(0, outcome.frame.ts_us - captured.arm_command_us) / 1e6)
            if outcome.frame is None:
                self._keep_chain(chain)
            elif captured is not None:
                self._answered = captured
            if outcome.frame is not None:
                self._frame_seq += 1
                self._record(outcome)
                if self.link.is_connected:
                    msg: Message = outcome.frame
                    if self.encoder is not None:
                        connects = self.link.counters.connects
                        if connects != self._encoder_connects:
                            # a new link session: a key frame first. The last session's
                            # unsent key frame was dropped at the welcome (reset only on a
                            # tick that found the link down, a link back between two ticks
                            # went on with deltas: the receiver waited up to key_every
                            # frames; found by audit)
                            self.encoder.reset()
                            self._encoder_connects = connects
                        msg = self.encoder.encode(outcome.frame)
                    await self.link.send(msg)
                    self.counters.frames_sent += 1
                else:  # (a key frame first when it is back: a new link session, above)
                    self.counters.frames_not_sent_link_down += 1
            if on_pose:
                next_t, late = next_frame_due_s(next_t, start, loop.time(), period, answered)
                self.counters.frames_late += late
                continue
            if arrived is not None:  # the next image as it comes, a period after this one
                next_t = start + period
                continue
            next_t += period
            now = loop.time()
            if now > next_t:
                self.counters.frames_late += 1
                next_t = now

    async def _streamed_frame(self, executor: ThreadPoolExecutor
                              ) -> tuple[AppliedCommand | None, _Chain | None, FrameOutcome]:
        """The next frame of a sensor that streams on its own clock: its newest image was
        taken before this tick, perhaps before the newest command, so the frame answers the
        command applied by the image's time and is placed where the arm was then (not where
        it is now). Returns the command answered, the chain taken and the outcome."""
        taken = self.pipeline.capture()  # the frame the sensor holds: no waiting
        if isinstance(taken, FrameOutcome):
            return self.latest, None, taken
        sensor_frame, capture_s = taken
        captured = self.applied_at(sensor_frame.timestamp_us)
        source, chain = self._frame_source(captured)
        try:
            reading = self.reading_at(sensor_frame.timestamp_us)
        except DeviceError as err:  # no polled reading yet, and the read failed
            self._frame_read_failed(err)
            return captured, chain, self.pipeline.arm_read_failed(err)
        with self.waited.waiting_for("a frame's processing"):
            outcome = await asyncio.get_running_loop().run_in_executor(
                executor, self.pipeline.build, self._frame_seq + 1, sensor_frame, reading,
                source, capture_s)
        return captured, chain, outcome

    def _record(self, outcome: FrameOutcome) -> None:
        frame = outcome.frame
        if frame is None:
            return
        stamps = {h.stage: h.t_us for h in frame.hops if h.clock == "remote"}
        if "sensor_frame" in stamps and "tactile_ready" in stamps:
            self.pipeline_s.append((stamps["tactile_ready"] - stamps["sensor_frame"]) / 1e6)
        if "sensor_frame" in stamps and "sensor_arrival" in stamps:
            self.delivery_s.append((stamps["sensor_arrival"] - stamps["sensor_frame"]) / 1e6)
        self.capture_s.append(outcome.capture_s)
        self.reconstruct_s.append(outcome.reconstruct_s)
        self.assemble_s.append(outcome.assemble_s)

    def status_text(self) -> str:
        """One line: link, frames, arm pose and force, stiffness, drops."""
        link = "up" if self.link.is_connected else "DOWN"
        elapsed = self.elapsed_s
        fps = self.pipeline.processed / elapsed if elapsed > 0 else 0.0
        r = self.last_reading
        arm = "arm ?" if r is None else (
            f"arm ({r.position_mm[0]:.1f},{r.position_mm[1]:.1f},{r.position_mm[2]:.2f}) mm "
            f"{r.force_n:.2f} N {r.status}")
        k = self.stiffness.current_n_per_mm
        k_txt = "k -" if k is None else f"k {k:.2f} N/mm"
        health = self.pipeline.sensor.health
        sensor = ("sensor ENDED | " if health.ended else
                  "sensor STALLED | " if health.stalled else "")
        bg = self.pipeline.background
        bg_txt = "" if bg is None else (
            f" | bg {bg.source} drift {np.mean(bg.drift_rgb):.1f}")
        return (f"remote: link {link} | {sensor}frames {self.counters.frames_sent} "
                f"({fps:.0f} fps) rejected {sum(self.pipeline.rejected.values())} | {arm} | "
                f"{k_txt} | stale {self.safe_arm.counters.dropped_stale}{bg_txt}")

    async def _status_loop(self) -> None:
        while True:
            await asyncio.sleep(self.config.status_interval_s)
            if self.status is not None:
                self.status(self.status_text())

    @property
    def elapsed_s(self) -> float:
        """Seconds the station has been running (until it stopped)."""
        if self._started_s is None:
            return 0.0
        end = self._stopped_s if self._stopped_s is not None else monotonic_s()
        return max(0.0, end - self._started_s)

    async def run(self, stop: asyncio.Event, duration_s: float | None = None) -> None:
        """Run until ``stop`` is set, ``duration_s`` has passed or a loop fails.

        The arm is halted and the worker thread joined before returning.

        Raises:
            SessionError: the relay refused the station for good (a wrong token, a
                connection replaced by another, a hello it can never accept).
            ConfigError: ``duration_s`` is not positive.
        """
        if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
            from shared.errors import ConfigError

            raise ConfigError(f"duration must be finite and > 0, got {duration_s}")
        self._started_s = monotonic_s()
        # this loop, or a frame's call in the pipeline's thread, stuck for hang_timeout_s:
        # stacks written, exit 1 (to be restarted); the close-down too, which waits for
        # that thread
        async with loop_watchdog(self.config.hang_timeout_s, self.waited):
            await self._run_watched(stop, duration_s)

    async def _run_watched(self, stop: asyncio.Event, duration_s: float | None) -> None:
        """:meth:`run` under its watchdog: the loops, then the close-down."""
        # the command timeout (no command for 100 ms halts the arm) runs in its own thread:
        # a busy or stalled event loop cannot delay the halt (the arm loop polls too)
        self.safe_arm.start_watchdog(self.config.watchdog_period_s)
        executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="remote-pipeline")
        tasks = [asyncio.create_task(self._receive_loop(), name="remote-receive"),
                 asyncio.create_task(self._arm_loop(), name="remote-arm"),
                 asyncio.create_task(self._frame_loop(executor), name="remote-frames"),
                 asyncio.create_task(self._status_loop(), name="remote-status")]
        stopper = asyncio.create_task(stop.wait(), name="remote-stop")
        try:
            # systemd (Type=notify): ready now; its watchdog pinged from this loop
            async with service("remote station running"):
                done, _ = await asyncio.wait({*tasks, stopper}, timeout=duration_s,
                                             return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                if task is not stopper and not task.cancelled() and task.exception() is not None:
                    raise task.exception()  # type: ignore[misc]
        finally:
            for task in (*tasks, stopper):
                task.cancel()
            for task in (*tasks, stopper):
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            self.safe_arm.stop()
            self.safe_arm.close()  # the watchdog thread
            with self.waited.waiting_for("the pipeline's thread to end"):
                await asyncio.get_running_loop().run_in_executor(None, executor.shutdown, True)
            self.stiffness.flush()
            self._stopped_s = monotonic_s()
            log.info("remote station stopped after %.1f s: %d tactile frames sent",
                     self.elapsed_s, self.counters.frames_sent)

    # ------------------------------------------------------------------ summary

    def summary(self) -> dict[str, Any]:
        """Counters and latency figures of the run (plain JSON values)."""
        c, p, s = self.counters, self.pipeline, self.safe_arm.counters
        elapsed = self.elapsed_s
        r = self.last_reading
        return {
            "role": "remote",
            "elapsed_s": elapsed,
            "frames": {
                "frame_rate_hz": self.config.frame_rate_hz,
                "capture": "on_pose" if self.captures_on_pose else (
                    "on_arrival" if self._reads_on_arrival else "clock"),
                "captures": asdict(self.captures),
                "processed": p.processed,
                "sent": c.frames_sent,
                "not_sent_link_down": c.frames_not_sent_link_down,
                "rejected": dict(p.rejected),
                "rejected_total": sum(p.rejected.values()),
                "repeated": p.repeated,
                "skipped_integration_no_contact": p.skipped_integration,
                "late": c.frames_late,
                "codec": self.config.tactile_codec,
                "key_frames": None if self.encoder is None else self.encoder.keys_sent,
                "delta_frames": None if self.encoder is None else self.encoder.deltas_sent,
                "achieved_fps": p.processed / elapsed if elapsed > 0 else 0.0,
                "patch_pitch_mm": p.patch_pitch_mm / p.assembler.scale_xy,
            },
            "sensor": asdict(p.sensor.health),
            "background": None if p.background is None else p.background.summary(),
            "platform_states": {
                "received": c.platform_states,
                "applied": c.platform_applied,
                # this stream's own (found by review: the safety layer's counter, which
                # counts stale arm_commands too, and clock refusals went nowhere)
                "dropped_stale": c.platform_dropped_stale,
                "dropped_clock": c.platform_dropped_clock,
                "dropped_no_clock": c.platform_dropped_no_clock,
                "invalid": c.platform_invalid,
            },
            "arm_commands": {"received": c.arm_commands, "applied": c.arm_commands_applied},
            "arm": {
                **asdict(s),
                "link_loss_halts": c.link_loss_halts,
                "errors": c.arm_errors,
                "arm_states_sent": c.arm_states_sent,
                "arm_states_refused": c.arm_states_refused,
                "final_position_mm": None if r is None else list(r.position_mm),
                "final_force_n": None if r is None else r.force_n,
            },
            "stiffness": {**self.stiffness.summary(),
                          "samples_rejected": c.stiffness_samples_rejected},
            "latency_ms": {
                "sensor_frame_to_tactile_ready": percentiles_ms(self.pipeline_s),
                "sensor_delivery": percentiles_ms(self.delivery_s),
                "capture": percentiles_ms(self.capture_s),
                "reconstruct": percentiles_ms(self.reconstruct_s),
                "assemble": percentiles_ms(self.assemble_s),
                "station_rx_to_arm_command": percentiles_ms(self.dispatch_s),
                "arm_command_to_capture": percentiles_ms(self.command_wait_s),
                "frame_period": percentiles_ms(self.frame_period_s),
            },
            "link": asdict(self.link.counters),
        }
