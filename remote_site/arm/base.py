"""The arm interface: one base class, backends implement a few private methods.

Positions are the pad centre in phantom coordinates (mm, see
:mod:`remote_site.phantom.phantom`); force is the measured normal force on the pad (N,
positive when pressing). Public methods validate, clamp to the arm's limits and return
what was actually applied; the lifecycle (``connect``/``disconnect``, context manager,
errors by phase, halting before disconnect) is :class:`~shared.devices.base.Device`'s.
Backends override ``_connect``, ``_disconnect``, ``_move_to``, ``_read``, ``_stop``.
"""

from __future__ import annotations

import logging
import math
from abc import abstractmethod
from collections.abc import Reversible, Sequence
from dataclasses import dataclass

import numpy as np

from shared.devices import Device
from shared.errors import CommandExpiredError, ConfigError, InputDataError
from shared.protocol.messages import ARM_STATUSES, ArmState
from shared.timebase import monotonic_s

__all__ = ["Arm", "ArmLimits", "ArmReading", "Vec3", "as_vec3", "polled_reading_at",
           "reading_between"]

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]


def as_vec3(value: Sequence[float], name: str = "target_mm") -> Vec3:
    """Validate three finite numbers.

    Raises:
        InputDataError: wrong length, not numbers, NaN or infinite.
    """
    try:
        x, y, z = (float(v) for v in value)
    except (TypeError, ValueError) as err:
        raise InputDataError(f"{name} must be three numbers, got {value!r}") from err
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise InputDataError(f"{name} must be finite, got {value!r}")
    return x, y, z


@dataclass(frozen=True)
class ArmLimits:
    """Cartesian box the pad may be commanded into, and the home pose (phantom mm).

    The default box spans the phantom (100 x 100 mm) from 6 mm deep to 40 mm above it.
    """

    lower_mm: Vec3 = (-50.0, -50.0, -6.0)
    upper_mm: Vec3 = (50.0, 50.0, 40.0)
    home_mm: Vec3 = (0.0, 0.0, 20.0)

    def __post_init__(self) -> None:
        lo, hi, home = (np.asarray(v, dtype=float) for v in (self.lower_mm, self.upper_mm,
                                                              self.home_mm))
        if not (np.isfinite(lo).all() and np.isfinite(hi).all() and np.isfinite(home).all()):
            raise ConfigError("arm limits must be finite")
        if lo.shape != (3,) or hi.shape != (3,) or np.any(lo >= hi):
            raise ConfigError("arm limits: lower_mm must be below upper_mm on every axis")
        if np.any(home < lo) or np.any(home > hi):
            raise ConfigError("arm limits: home_mm must lie inside the box")

    def clamp(self, target_mm: Vec3) -> Vec3:
        """Clamp a position into the box."""
        x, y, z = (min(max(v, lo), hi) for v, lo, hi in zip(target_mm, self.lower_mm,
                                                              self.upper_mm, strict=True))
        return x, y, z


@dataclass(frozen=True)
class ArmReading:
    """One snapshot of the arm.

    Attributes:
        position_mm: pad centre, phantom coordinates.
        velocity_mm_s: Cartesian velocity.
        force_n: measured normal force (N, >= 0 when pressing).
        status: one of :data:`shared.protocol.messages.ARM_STATUSES`.
        target_mm: the target being tracked, or None.
        t_s: time of the reading (the backend's clock, seconds).
    """

    position_mm: Vec3
    velocity_mm_s: Vec3
    force_n: float
    status: str
    target_mm: Vec3 | None
    t_s: float

    def with_status(self, status: str) -> ArmReading:
        """A copy with another status (the safety layer overrides it)."""
        return ArmReading(self.position_mm, self.velocity_mm_s, self.force_n, status,
                          self.target_mm, self.t_s)

    def to_message(self, seq: int, ts_us: int, source_seq: int | None = None) -> ArmState:
        """The wire message for this reading."""
        return ArmState(seq=seq, ts_us=ts_us, position_mm=self.position_mm,
                        force_n=float(self.force_n), status=self.status, source_seq=source_seq)


def reading_between(earlier: ArmReading, later: ArmReading, weight: float) -> ArmReading:
    """The arm between two readings, ``weight`` of the way from ``earlier`` (0) to
    ``later`` (1): position, velocity, force and time on the straight line between them;
    the status and target of the nearer one (they do not blend).

    Raises:
        InputDataError: a weight outside [0, 1] or not finite.
    """
    w = float(weight)
    if not 0.0 <= w <= 1.0:  # also refuses NaN
        raise InputDataError(f"reading_between: weight must be in [0, 1], got {weight!r}")
    if w == 0.0:
        return earlier
    if w == 1.0:
        return later
    near = earlier if w <= 0.5 else later

    def blend(a: float, b: float) -> float:
        return a + (b - a) * w

    def blend3(a: Vec3, b: Vec3) -> Vec3:
        return blend(a[0], b[0]), blend(a[1], b[1]), blend(a[2], b[2])

    return ArmReading(blend3(earlier.position_mm, later.position_mm),
                      blend3(earlier.velocity_mm_s, later.velocity_mm_s),
                      blend(earlier.force_n, later.force_n), near.status, near.target_mm,
                      blend(earlier.t_s, later.t_s))


def polled_reading_at(readings: Reversible[tuple[int, ArmReading]],
                      t_us: int) -> ArmReading | None:
    """Where the arm was at ``t_us``, from readings polled at known times (``(t_us,
    reading)`` in increasing time order, on one clock; readings out of order give a wrong
    answer, not an error): on the straight line between the two polled around it
    (:func:`reading_between`), the oldest or the newest when ``t_us`` lies outside them
    (no guess beyond what was polled); of two readings with the same stamp, the later one;
    None without readings."""
    later: tuple[int, ArmReading] | None = None
    for polled_us, reading in reversed(readings):
        if polled_us <= t_us:
            if later is None or polled_us == t_us:
                return reading
            return reading_between(reading, later[1],
                                   (t_us - polled_us) / (later[0] - polled_us))
        later = (polled_us, reading)
    return None if later is None else later[1]


class Arm(Device):
    """Base class of every arm backend.

    Args:
        limits: the Cartesian box targets are clamped to.
    """

    def __init__(self, *, limits: ArmLimits | None = None) -> None:
        super().__init__()
        self.limits = limits or ArmLimits()

    # --------------------------------------------------------------- lifecycle

    @property
    def connected(self) -> bool:
        """True between :meth:`connect` and :meth:`disconnect` (same as ``is_connected``)."""
        return self._connected

    def _before_disconnect(self) -> None:
        """Halt before the link is released."""
        with self._operation("stop"):
            self._stop()

    def _require(self) -> None:
        self._require_connected()

    # --------------------------------------------------------------- commands

    def move_to(self, target_mm: Sequence[float], *, not_after_s: float | None = None) -> Vec3:
        """Track a Cartesian target; returns the target applied after clamping.

        Args:
            target_mm: the target (phantom mm).
            not_after_s: a deadline on :func:`shared.timebase.monotonic_s`: the move is not
                started after it (checked at the last moment before the backend is told, so
                a process stopped or starved between the caller's age check and here does
                not move the arm with an old command).

        Raises:
            InputDataError: not three finite numbers.
            DeviceNotConnectedError: not connected.
            CommandExpiredError: ``not_after_s`` had passed; the arm was not told.
        """
        self._require()
        applied = self.limits.clamp(as_vec3(target_mm))
        with self._operation("move"):
            if not_after_s is not None:
                late_s = monotonic_s() - not_after_s
                if late_s > 0:
                    raise CommandExpiredError(f"{self.name}: move {late_s * 1e3:.1f} ms past "
                                              "its deadline; not started")
            self._move_to(applied)
        return applied

    set_target = move_to

    def state(self) -> ArmReading:
        """The latest pose, velocity, measured force and status.

        Raises:
            DeviceNotConnectedError: not connected.
        """
        self._require()
        with self._operation("state read"):
            reading = self._read()
        if reading.status not in ARM_STATUSES:
            reading = reading.with_status("fault")
        return reading

    def stop(self) -> None:
        """Halt as fast as the limits allow and hold position.

        Raises:
            DeviceNotConnectedError: not connected.
        """
        self._require()
        with self._operation("stop"):
            self._stop()

    def home(self) -> Vec3:
        """Move to the home pose; returns it."""
        return self.move_to(self.limits.home_mm)

    # --------------------------------------------------------------- backend hooks

    # _connect() / _disconnect(): see shared.devices.base.Device

    @abstractmethod
    def _move_to(self, target_mm: Vec3) -> None: ...

    @abstractmethod
    def _read(self) -> ArmReading: ...

    @abstractmethod
    def _stop(self) -> None: ...
