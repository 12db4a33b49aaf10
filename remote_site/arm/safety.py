"""Station-side arm safety, the same for every backend.

:class:`SafeArm` wraps any :class:`~remote_site.arm.base.Arm` and enforces the design's
conventions:

* a command whose clock-corrected age exceeds ``max_command_age_ms`` (100 ms) is dropped,
  counted and reported (status ``stale_command``);
* no accepted command for ``command_timeout_ms`` (100 ms) halts the arm (checked by
  :meth:`SafeArm.poll`, which the station calls at >= 100 Hz, or by the built-in watchdog
  thread started with :meth:`SafeArm.start_watchdog`);
* pressing stops at ``force_limit_n``: once the measured force reaches it no target may lie
  deeper than a hold depth (status ``force_limit``), whatever its x and y (sliding sideways
  onto stiffer tissue at the same depth raises the force too). While a reading's force is at
  or above the limit the hold depth rises to ``force_backoff_mm`` x (force / limit) above
  the current depth (never lower than before), so the arm backs off until the force falls
  below the limit; it releases once the force falls below
  ``force_release_ratio * force_limit_n`` and the newest command no longer asks for a depth
  below the hold (a press held at the limit stays held, however stiff the tissue: released
  at each back-off, it pressed again and buzzed around the limit). A halted arm
  (stop, link-loss halt, watchdog halt) is only backed off where it is (its x and y, up to
  the hold depth), never sent on towards its old target;
* a reading with a non-finite force or position halts the arm (status ``fault``): the force
  limit cannot be judged from it. Moves are refused (status ``fault``) while the arm's
  reading is non-finite; once it is finite again the next accepted move resumes;
* targets are clamped to the workspace box, and the applied command is returned;
* below ``press_zone_z_mm`` (phantom z; the surface is z = 0) a downward target may lie at
  most ``max_press_step_mm`` below the arm's current depth. Pressing therefore advances in
  small steps (the arm's final approach then moves at most ``gain * step``, a few tens of
  mm/s), so the arm can stop within a fraction of a millimetre when the force limit trips:
  without it an arm at full speed would need ``v^2 / 2a`` (12 mm at 250 mm/s, 2.5 m/s^2) to
  brake.

Clock correction: a command stamped ``sent_ts_us`` on the sender's clock was sent at
``sent_ts_us + clock_offset_us`` on ours, where ``clock_offset_us`` is our clock minus the
sender's (from the relay's clock-offset estimates of both stations), give or take
``offset_uncertainty_us`` (their error bounds). The command is executed only when it is
certainly younger than ``max_command_age_ms`` (:func:`shared.freshness.judge_age`): an
unknown offset, a bound wider than ``max_offset_uncertainty_ms``, or a stamp later than now
by more than the bound (a clock stepped since the offsets were measured) all refuse it.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from remote_site.arm.base import Arm, ArmReading, Vec3, as_vec3
from shared.errors import CommandExpiredError, ConfigError
from shared.freshness import AgeVerdict, judge_age
from shared.protocol.messages import ArmCommand
from shared.timebase import monotonic_s, now_us

__all__ = ["CommandResult", "SafeArm", "SafetyConfig", "SafetyCounters"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SafetyConfig:
    """Safety settings (resolve with ``shared.config.resolve_config(..., "arm.safety")``).

    Attributes:
        max_command_age_ms: commands that may be older than this (clock-corrected, error
            bound included) are dropped.
        max_offset_uncertainty_ms: commands are dropped while the clock offsets' error bound
            is wider than this (the age could not be judged finely enough).
        command_timeout_ms: the arm halts when the newest command it executed is this old
            (by its stamp, clock-corrected, error bound included; unstamped commands count
            from their arrival), i.e. no fresh command for this long.
        force_limit_n: the pressing force limit. Once a reading reaches it, no target may
            lie deeper than the hold depth (sideways targets too); while readings stay at or
            above it the hold depth rises above the arm's current depth by
            ``force_backoff_mm`` x (force / limit) (never lower), so the arm backs off until
            the force is below the limit.
        force_release_ratio: the limit releases below this fraction of it.
        press_zone_z_mm: below this phantom z, downward targets are rate-limited.
        max_press_step_mm: how far below the current depth a target may lie in that zone.
        force_backoff_mm: how far above the current depth the force limit's hold depth
            rises while the force is at the limit (in proportion above it: twice as far at
            twice the limit); small, as on stiff tissue each step sheds stiffness x step of
            force.
    """

    max_command_age_ms: float = 100.0
    max_offset_uncertainty_ms: float = 30.0
    command_timeout_ms: float = 100.0
    force_limit_n: float = 10.0
    force_release_ratio: float = 0.8
    press_zone_z_mm: float = 2.0
    max_press_step_mm: float = 0.3
    force_backoff_mm: float = 0.05

    def __post_init__(self) -> None:
        vals = (self.max_command_age_ms, self.max_offset_uncertainty_ms,
                self.command_timeout_ms, self.force_limit_n, self.max_press_step_mm,
                self.force_backoff_mm)
        if not all(math.isfinite(v) and v > 0 for v in vals):
            raise ConfigError("arm safety: ages, timeout, force limit, press step and force "
                              "back-off must be finite and > 0")
        if not 0 < self.force_release_ratio <= 1:
            raise ConfigError("arm safety: force_release_ratio must be in (0, 1]")
        if not math.isfinite(self.press_zone_z_mm):
            raise ConfigError("arm safety: press_zone_z_mm must be finite")


@dataclass(frozen=True)
class CommandResult:
    """What happened to one command.

    Attributes:
        accepted: the arm was told to move.
        applied_mm: the target actually sent (after clamping), or None.
        status: an ``ARM_STATUSES`` value describing the outcome.
        clamped: the target was changed by the workspace box or the force limit.
        age_ms: clock-corrected age of the command, when it carried a timestamp.
        refused: why an age-checked command was refused (a
            :data:`shared.freshness.Verdict` other than ``fresh``), else None.
        speed_before_mm_s: the arm's speed when the move was given (read right before it),
            None when it was not given.
    """

    accepted: bool
    applied_mm: Vec3 | None
    status: str
    clamped: bool = False
    age_ms: float | None = None
    refused: str | None = None
    speed_before_mm_s: float | None = None


@dataclass
class SafetyCounters:
    """Running totals, for the station's stats."""

    commands: int = 0
    applied: int = 0
    dropped_stale: int = 0
    #: refused because the clock offsets were unknown, too uncertain or inconsistent
    dropped_clock: int = 0
    #: of the refused: fresh on arrival, stale by the time the arm would have moved (the
    #: process was stopped or starved in between; judged again right before the move)
    dropped_late: int = 0
    clamped: int = 0
    force_limited: int = 0
    press_rate_limited: int = 0
    watchdog_halts: int = 0
    #: halts for a reading with a non-finite force or position (one per such episode)
    fault_halts: int = 0
    max_age_ms: float = field(default=0.0)


class SafeArm:
    """Safety wrapper around any arm backend.

    Args:
        arm: the backend (connected by the caller).
        config: safety settings.
        bounds_mm: optional (lower, upper) box tighter than the arm's own limits (for
            example :attr:`shared.workspace.WorkspaceMap.phantom_bounds_mm`).
        wall_clock_us: our wall clock in microseconds (injectable for tests).
        monotonic: monotonic seconds for the watchdog (injectable for tests).
    """

    def __init__(self, arm: Arm, config: SafetyConfig | None = None, *,
                 bounds_mm: tuple[Sequence[float], Sequence[float]] | None = None,
                 wall_clock_us: Callable[[], int] = now_us,
                 monotonic: Callable[[], float] = monotonic_s) -> None:
        self.arm = arm
        self.config = config or SafetyConfig()
        lo, hi = (arm.limits.lower_mm, arm.limits.upper_mm)
        if bounds_mm is not None:
            blo, bhi = as_vec3(bounds_mm[0], "bounds lower"), as_vec3(bounds_mm[1], "bounds upper")
            lo = tuple(max(a, b) for a, b in zip(lo, blo, strict=True))  # type: ignore[assignment]
            hi = tuple(min(a, b) for a, b in zip(hi, bhi, strict=True))  # type: ignore[assignment]
            if any(a > b for a, b in zip(lo, hi, strict=True)):
                raise ConfigError("arm safety: bounds do not overlap the arm's limits")
        self._lo, self._hi = lo, hi
        self._wall_us = wall_clock_us
        self._mono = monotonic
        self.counters = SafetyCounters()
        self._force_limit_n = self.config.force_limit_n
        self._last_command_s: float | None = None
        self._halted = False
        self._limit_hold_z: float | None = None  # deepest z allowed while force-limited
        #: the hold depth a halted arm was last backed off to (None: not backed off since the
        #: halt): a halted arm is backed off again only when the hold depth rose above it
        self._backoff_z: float | None = None
        #: the depth the newest accepted command asked for, before the hold (None: none
        #: since the last halt): the limit is not released while it lies below the hold
        self._wanted_z: float | None = None
        #: the arm's last reading was non-finite (an episode: halted, logged once)
        self._fault = False
        self._lock = threading.RLock()
        self._watchdog: threading.Thread | None = None
        self._watchdog_stop = threading.Event()
        #: the watchdog's check period (ms): a check halts when the next one would be late
        self._check_period_ms = 0.0

    # --------------------------------------------------------------- properties

    @property
    def force_limit_n(self) -> float:
        """The current pressing force limit."""
        return self._force_limit_n

    @property
    def halted(self) -> bool:
        """True after a watchdog halt or stop until the next accepted move."""
        return self._halted

    # --------------------------------------------------------------- commands

    def move(self, target_mm: Sequence[float], *, sent_ts_us: int | None = None,
             clock_offset_us: float | None = 0.0,
             offset_uncertainty_us: float = 0.0) -> CommandResult:
        """Apply a move target if fresh, clamped and force-limited.

        Args:
            target_mm: target (phantom mm).
            sent_ts_us: sender's timestamp of the command (None: not age-checked).
            clock_offset_us: our clock minus the sender's (None: unknown, refused).
            offset_uncertainty_us: the error bound of ``clock_offset_us``.

        Returns:
            The outcome, with the applied target.

        Raises:
            InputDataError: a non-finite or malformed target.
        """
        target = as_vec3(target_mm)
        clock = None if clock_offset_us is None else (clock_offset_us, offset_uncertainty_us)
        with self._lock:
            self.counters.commands += 1
            age_ms = None
            if sent_ts_us is not None:
                verdict = self._judge(sent_ts_us, clock)
                age_ms = verdict.age_ms
                if not verdict.fresh:
                    return self._refused(verdict)
            clamped_box = tuple(min(max(v, a), b)
                                for v, a, b in zip(target, self._lo, self._hi, strict=True))
            applied: Vec3 = (clamped_box[0], clamped_box[1], clamped_box[2])
            clamped = applied != target
            status = "moving"
            reading = self.arm.state()
            if not self._reading_finite(reading):
                return CommandResult(False, None, "fault", False, age_ms)
            self._update_force_limit(reading)
            z_now = reading.position_mm[2]
            cfg = self.config
            if applied[2] < cfg.press_zone_z_mm:
                z_floor = min(z_now, cfg.press_zone_z_mm) - cfg.max_press_step_mm
                if applied[2] < z_floor:
                    applied = (applied[0], applied[1], z_floor)
                    self.counters.press_rate_limited += 1
            wanted_z = applied[2]  # the depth asked for, before the force limit's hold
            if self._limit_hold_z is not None and applied[2] < self._limit_hold_z:
                applied = (applied[0], applied[1], self._limit_hold_z)
                clamped = True
                status = "force_limit"
                self.counters.force_limited += 1
            #: how long ago (s) the command was sent, at most: the watchdog's clock starts
            #: then, not at arrival, so the arm halts when the newest command it executed is
            #: command_timeout_ms old by its own stamp (the delay on the way counts)
            sent_ago_s = 0.0
            deadline_s = None
            if sent_ts_us is not None:
                # judged again right before the move: reading the arm's state took time,
                # and a stopped or starved process may have slept since the first check
                verdict = self._judge(sent_ts_us, clock)
                age_ms = verdict.age_ms
                if not verdict.fresh:
                    self.counters.dropped_late += 1
                    return self._refused(verdict)
                if verdict.age_us is not None and verdict.uncertainty_us is not None:
                    sent_ago_s = max(0.0, verdict.age_us + verdict.uncertainty_us) / 1e6
                # and the arm itself refuses to start the move once the command may be
                # older than the limit (the time left, on the arm's monotonic clock)
                deadline_s = monotonic_s() + cfg.max_command_age_ms / 1e3 - sent_ago_s
            if clamped:
                self.counters.clamped += 1
            try:
                applied = self.arm.move_to(applied, not_after_s=deadline_s)
            except CommandExpiredError as err:
                self.counters.dropped_late += 1
                self.counters.dropped_stale += 1
                if log.isEnabledFor(logging.DEBUG):
                    log.debug("dropped arm command at the arm: %s", err)
                return CommandResult(False, None, "stale_command", False, age_ms, "stale")
            self._last_command_s = self._mono() - sent_ago_s
            self._halted = False
            self._backoff_z = None
            self._wanted_z = wanted_z
            self.counters.applied += 1
            return CommandResult(True, applied, status, clamped, age_ms,
                                 speed_before_mm_s=math.hypot(*reading.velocity_mm_s))

    def _judge(self, sent_ts_us: int, clock: tuple[float, float] | None) -> AgeVerdict:
        """A command's age now, by its stamp (error bound included); the worst age is kept."""
        cfg = self.config
        verdict = judge_age(sent_ts_us, self._wall_us(), clock,
                            max_age_us=cfg.max_command_age_ms * 1000.0,
                            max_uncertainty_us=cfg.max_offset_uncertainty_ms * 1000.0)
        if verdict.age_us is not None:
            self.counters.max_age_ms = max(self.counters.max_age_ms, verdict.age_us / 1000.0)
        return verdict

    def _refused(self, verdict: AgeVerdict) -> CommandResult:
        if verdict.verdict == "stale":
            self.counters.dropped_stale += 1
        else:
            self.counters.dropped_clock += 1
        age_ms = verdict.age_ms
        if log.isEnabledFor(logging.DEBUG):
            log.debug("dropped arm command: %s (age %s ms, +- %s us)",
                      verdict.verdict, age_ms, verdict.uncertainty_us)
        return CommandResult(False, None, "stale_command", False, age_ms, verdict.verdict)

    def stop(self) -> None:
        """Halt the arm now."""
        with self._lock:
            self.arm.stop()
            self._halted = True
            self._backoff_z = None
            self._wanted_z = None

    def home(self, *, sent_ts_us: int | None = None, clock_offset_us: float | None = 0.0,
             offset_uncertainty_us: float = 0.0) -> CommandResult:
        """Move home (age-checked, clamped and force-limited like any :meth:`move`)."""
        return self.move(self.arm.limits.home_mm, sent_ts_us=sent_ts_us,
                         clock_offset_us=clock_offset_us,
                         offset_uncertainty_us=offset_uncertainty_us)

    def set_force_limit(self, force_limit_n: float) -> None:
        """Change the pressing force limit (never above the configured one).

        Not age-checked: a wire command goes through :meth:`handle`, which is.

        Raises:
            ConfigError: ``force_limit_n`` is not a finite positive number.
        """
        if not (math.isfinite(force_limit_n) and force_limit_n > 0):
            raise ConfigError(f"force_limit_n must be finite and > 0, got {force_limit_n!r}")
        with self._lock:
            self._force_limit_n = min(float(force_limit_n), self.config.force_limit_n)

    def handle(self, command: ArmCommand, *, clock_offset_us: float | None = 0.0,
               offset_uncertainty_us: float = 0.0) -> CommandResult:
        """Apply a wire :class:`~shared.protocol.messages.ArmCommand`.

        ``move`` is age-checked like :meth:`move`; ``stop`` always acts (stopping is never
        refused, however old); ``home`` and ``set_force_limit`` are age-checked the same
        way (an unknown or too uncertain clock refuses them). A ``set_force_limit`` without
        a finite positive ``force_limit_n`` is refused (status ``fault``), never raised: a
        bad command must not end the station's receive loop.
        """
        if command.action == "stop":
            self.stop()
            return CommandResult(True, None, "halted")
        if command.action == "set_force_limit":
            return self._handle_force_limit(command, clock_offset_us, offset_uncertainty_us)
        target = command.target_mm if command.action == "move" else self.arm.limits.home_mm
        if target is None:
            return CommandResult(False, None, "fault")
        return self.move(target, sent_ts_us=command.ts_us, clock_offset_us=clock_offset_us,
                         offset_uncertainty_us=offset_uncertainty_us)

    def _handle_force_limit(self, command: ArmCommand, clock_offset_us: float | None,
                            offset_uncertainty_us: float) -> CommandResult:
        """A wire ``set_force_limit``: age-checked like a move, refused when invalid."""
        limit = command.force_limit_n
        clock = None if clock_offset_us is None else (clock_offset_us, offset_uncertainty_us)
        with self._lock:
            self.counters.commands += 1
            verdict = self._judge(command.ts_us, clock)
            if not verdict.fresh:
                return self._refused(verdict)
            if limit is None or not (math.isfinite(limit) and limit > 0):
                log.warning("refused set_force_limit %d: force_limit_n must be finite and > 0, "
                            "got %r", command.seq, limit)
                return CommandResult(False, None, "fault", False, verdict.age_ms)
            self.set_force_limit(limit)
            return CommandResult(True, None, "ok", False, verdict.age_ms)

    # --------------------------------------------------------------- watchdog

    def _reading_finite(self, reading: ArmReading) -> bool:
        """False for a reading with a non-finite force or position, which cannot be judged
        against the force limit: the arm is halted then (once per episode: counted in
        ``fault_halts`` and logged) and stays halted until a move is accepted after the
        readings are finite again."""
        if math.isfinite(reading.force_n) and all(math.isfinite(v)
                                                  for v in reading.position_mm):
            self._fault = False
            return True
        if not self._fault:
            self.arm.stop()
            self._halted = True
            self._backoff_z = None
            self._wanted_z = None
            self._fault = True
            self.counters.fault_halts += 1
            log.warning("arm reading not finite (force %r N, position %r mm): arm halted",
                        reading.force_n, reading.position_mm)
        return False

    def _update_force_limit(self, reading: ArmReading) -> bool:
        """Engage or release the force limit from a reading; True when it is engaged.

        While the force is at or above the limit the hold depth rises to
        ``force_backoff_mm`` x (force / limit) above the current depth (at most a press step,
        never above the box; never lower than before): holding the depth alone would let a
        sideways slide onto stiffer tissue raise the force without bound. It is released
        below ``force_release_ratio`` of the limit once the newest command no longer asks
        for a depth below the hold.
        """
        z = reading.position_mm[2]
        if reading.force_n >= self._force_limit_n:
            # a step in proportion to the overshoot: small for a press that just reached the
            # limit (stiff tissue sheds stiffness x step of force), larger for a slide onto
            # an inclusion far past it
            rise = min(self.config.force_backoff_mm * reading.force_n / self._force_limit_n,
                       self.config.max_press_step_mm)  # one wild reading lifts it 0.3 mm
            hold = min(z + rise, self._hi[2])  # never above the box: a command can reach it
            if self._limit_hold_z is None or hold > self._limit_hold_z:
                self._limit_hold_z = hold
            return True
        if (self._limit_hold_z is not None
                and reading.force_n < self.config.force_release_ratio * self._force_limit_n
                and (self._wanted_z is None
                     or self._wanted_z >= min(self._limit_hold_z, self._hi[2]))):
            self._limit_hold_z = None
        return self._limit_hold_z is not None

    def poll(self) -> ArmReading:
        """Enforce the command timeout and the force limit; return the arm's reading.

        The returned status is ``fault`` for a non-finite reading (the arm is halted),
        ``halted`` after a halt and ``force_limit`` while the force limit holds the arm.

        While the force limit holds, an arm tracking a target deeper than the hold depth is
        re-targeted to that target's x and y at the hold depth. A halted arm is not: the
        backends take any move as the end of a halt, so it would drive on to its old target;
        it is only backed off where it is (its x and y), up to the hold depth, when it lies
        below it.
        """
        with self._lock:
            reading = self.arm.state()
            if not self._reading_finite(reading):
                return reading.with_status("fault")
            limited = self._update_force_limit(reading)
            hold = self._limit_hold_z
            if limited and hold is not None:
                if self._halted:
                    x, y, z = reading.position_mm
                    if z < hold and (self._backoff_z is None or self._backoff_z < hold):
                        self.arm.move_to((x, y, hold))
                        self._backoff_z = hold
                        self.counters.force_limited += 1
                elif reading.target_mm is not None and reading.target_mm[2] < hold:
                    x, y, _ = reading.target_mm
                    self.arm.move_to((x, y, hold))
                    self.counters.force_limited += 1
            # with the watchdog thread checking every period, a check halts when the
            # command will be past the timeout at the next check: the halt then comes
            # within the timeout, not up to one period after it
            if (not self._halted and self._last_command_s is not None
                    and (self._mono() - self._last_command_s) * 1000.0
                    > self.config.command_timeout_ms - self._check_period_ms):
                self.arm.stop()
                self._halted = True
                self._backoff_z = None
                self._wanted_z = None
                self.counters.watchdog_halts += 1
                log.warning("no arm command for %.0f ms: arm halted",
                            self.config.command_timeout_ms)
            if self._halted:
                return reading.with_status("halted")
            if limited:
                return reading.with_status("force_limit")
            return reading

    def start_watchdog(self, period_s: float = 0.005) -> None:
        """Run :meth:`poll` every ``period_s`` in a daemon thread until :meth:`close`.

        From then on :meth:`poll` halts the arm once the newest command is older than
        ``command_timeout_ms - period``: the check after that would come too late.
        """
        if self._watchdog is not None:
            return
        self._check_period_ms = period_s * 1000.0
        self._watchdog_stop.clear()

        def loop() -> None:
            failing = False
            while not self._watchdog_stop.wait(period_s):
                try:
                    self.poll()
                    failing = False
                except Exception as err:  # a device fault must not end the watchdog
                    if not failing:
                        log.error("arm watchdog: reading the arm failed (%s); halting and "
                                  "retrying", err)
                        failing = True
                    with contextlib.suppress(Exception):
                        self.arm.stop()

        self._watchdog = threading.Thread(target=loop, name="arm-watchdog", daemon=True)
        self._watchdog.start()

    def close(self) -> None:
        """Stop the watchdog thread (the arm itself is left to its owner)."""
        self._watchdog_stop.set()
        if self._watchdog is not None:
            self._watchdog.join(timeout=1.0)
            self._watchdog = None
