"""Simulated arm: a Cartesian point with Franka-like velocity/acceleration/jerk limits.

A 1 kHz control law moves the pad towards its target with a time-optimal braking profile
(``v_des = min(v_max, sqrt(2 m a_max d), K_p d)`` along the line to the target, with a braking
margin ``m`` < 1 that absorbs the jerk-limited ramp and a proportional gain ``K_p`` for the
final, exponential approach), then limits acceleration and jerk. At every step the pad
feels the phantom: the measured force is
``phantom.force_n(position)`` plus optional Gaussian noise.

Time is injectable: with ``realtime=True`` the arm follows the wall clock: every call that
looks at or changes the arm (a reading, a move, a stop, the samples) first runs the 1 kHz
steps that have fallen due since the last call, so what is seen is the state at the last
step boundary, exactly as a thread stepping every millisecond would have left it (a target
set between two boundaries takes effect at the next, as it did there), without a thread
waking 1000 times a second. With ``realtime=False`` nothing moves until the caller calls
:meth:`SimArm.advance`, which makes tests deterministic and fast. Every step's
(t, x, y, z, force) is kept in a bounded buffer for the stiffness stage
(:meth:`SimArm.drain_samples`).

Franka Research 3 Cartesian limits (translation): 1.7 m/s, 13 m/s^2, 6500 m/s^3; the
defaults below are a slower palpation profile within them.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from remote_site.arm.base import Arm, ArmLimits, ArmReading, Vec3
from shared.errors import ConfigError

__all__ = ["FRANKA_LIMITS", "ArmNoise", "ForceField", "SimArm", "SimArmConfig"]


class ForceField(Protocol):
    """What the pad presses: the normal force at a pad pose (arm frame, mm)."""

    def force_n(self, position_mm: Sequence[float]) -> float:
        """Normal force (N) on the pad at ``position_mm``."""
        ...

log = logging.getLogger(__name__)

#: Franka Cartesian translation limits (mm/s, mm/s^2, mm/s^3)
FRANKA_LIMITS = (1700.0, 13000.0, 6.5e6)
_BRAKE_MARGIN = 0.6
#: realtime: the most simulated time one call runs to catch up with the wall clock (s)
_MAX_CATCH_UP_S = 0.1


@dataclass(frozen=True)
class SimArmConfig:
    """Settings of the simulated arm.

    Attributes:
        max_velocity_mm_s: Cartesian speed limit.
        max_acceleration_mm_s2: acceleration limit.
        max_jerk_mm_s3: jerk limit.
        loop_hz: internal control rate.
        position_gain_1_s: gain of the final approach (time constant 1 / gain).
        force_noise_n: standard deviation of the force sensor noise.
        seed: noise seed.
        realtime: follow the wall clock (steps run when due, on the next call that looks at
            the arm; else only in :meth:`SimArm.advance`).
        sample_buffer: how many 1 kHz samples :meth:`SimArm.drain_samples` keeps.
    """

    max_velocity_mm_s: float = 250.0
    max_acceleration_mm_s2: float = 2500.0
    max_jerk_mm_s3: float = 1.0e6
    loop_hz: float = 1000.0
    position_gain_1_s: float = 40.0
    force_noise_n: float = 0.0
    seed: int = 0
    realtime: bool = True
    sample_buffer: int = 10_000

    def __post_init__(self) -> None:
        lims = (self.max_velocity_mm_s, self.max_acceleration_mm_s2, self.max_jerk_mm_s3)
        if not all(math.isfinite(v) and v > 0
                   for v in (*lims, self.loop_hz, self.position_gain_1_s)):
            raise ConfigError("sim arm: limits and loop rate must be finite and > 0")
        if any(v > f for v, f in zip(lims, FRANKA_LIMITS, strict=True)):
            raise ConfigError(f"sim arm: limits exceed the Franka's {FRANKA_LIMITS}")
        if not (math.isfinite(self.force_noise_n) and self.force_noise_n >= 0):
            raise ConfigError("sim arm: force_noise_n must be >= 0")

        if self.sample_buffer < 1:
            raise ConfigError("sim arm: sample_buffer must be >= 1")


@dataclass(frozen=True)
class ArmNoise:
    """A simulated world's imperfections of the arm's sensing (see ``remote_site.agent.world``).

    Attributes:
        force_noise_n: white noise of the force reading (per control step).
        force_bias_n: constant offset of the force reading (what a tare leaves behind).
        force_drift_n_per_min: linear drift of that offset with time.
        position_noise_mm: noise of the reported position around the true one (encoder /
            kinematic noise; the dynamics' own tracking lag comes on top).
    """

    force_noise_n: float = 0.0
    force_bias_n: float = 0.0
    force_drift_n_per_min: float = 0.0
    position_noise_mm: float = 0.0

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in self.__dict__.values()):
            raise ConfigError("sim arm noise: values must be finite")
        if self.force_noise_n < 0 or self.position_noise_mm < 0:
            raise ConfigError("sim arm noise: noise levels must be >= 0")


class SimArm(Arm):
    """The simulated arm backend (name ``sim``).

    Args:
        phantom: what the pad presses, a :class:`ForceField` such as a phantom (None: free
            space, force 0).
        config: dynamics and loop settings.
        limits: Cartesian box and home pose; the arm starts at home.
        noise: the simulated world's sensing imperfections (none by default).
    """

    def __init__(self, phantom: ForceField | None = None, config: SimArmConfig | None = None, *,
                 limits: ArmLimits | None = None, noise: ArmNoise | None = None) -> None:
        super().__init__(limits=limits)
        self.phantom = phantom
        self.config = config or SimArmConfig()
        self.noise = noise or ArmNoise()
        self._dt = 1.0 / self.config.loop_hz
        self._lock = threading.Lock()
        # the state as plain floats: a step is ~40 scalar operations, which numpy arrays of
        # three made several times slower (per-call overhead)
        self._pos = [float(v) for v in self.limits.home_mm]
        self._vel = [0.0, 0.0, 0.0]
        self._acc = [0.0, 0.0, 0.0]
        self._target = list(self._pos)
        self._halting = False
        self._t_s = 0.0
        self._force_n = 0.0
        #: the phantom force at the last stepped position (the arm at rest feels the same)
        self._felt: tuple[tuple[float, float, float], float] | None = None
        self._rng = np.random.default_rng(self.config.seed)
        self._samples: deque[tuple[float, float, float, float, float]] = deque(
            maxlen=self.config.sample_buffer)
        #: realtime: wall-clock origin of step 0 and the steps run since (None: not running)
        self._origin_s: float | None = None
        self._due_steps = 0
        self._step_count = 0

    # --------------------------------------------------------------- plant

    def _step(self) -> None:
        """One control period (call with the lock held)."""
        cfg, dt = self.config, self._dt
        px, py, pz = self._pos
        vx, vy, vz = self._vel
        ax, ay, az = self._acc
        ex, ey, ez = self._target[0] - px, self._target[1] - py, self._target[2] - pz
        dist = math.sqrt(ex * ex + ey * ey + ez * ez)
        if not self._halting and dist > 1e-12:
            speed = min(cfg.max_velocity_mm_s,
                        math.sqrt(2.0 * _BRAKE_MARGIN * cfg.max_acceleration_mm_s2 * dist),
                        cfg.position_gain_1_s * dist)
            k = speed / dist
            dvx, dvy, dvz = ex * k - vx, ey * k - vy, ez * k - vz
        else:
            dvx, dvy, dvz = -vx, -vy, -vz
        # desired acceleration, limited in norm
        adx, ady, adz = dvx / dt, dvy / dt, dvz / dt
        a_norm = math.sqrt(adx * adx + ady * ady + adz * adz)
        if a_norm > cfg.max_acceleration_mm_s2:
            k = cfg.max_acceleration_mm_s2 / a_norm
            adx, ady, adz = adx * k, ady * k, adz * k
        # its change limited by the jerk
        dax, day, daz = adx - ax, ady - ay, adz - az
        da_norm = math.sqrt(dax * dax + day * day + daz * daz)
        da_max = cfg.max_jerk_mm_s3 * dt
        if da_norm > da_max:
            k = da_max / da_norm
            dax, day, daz = dax * k, day * k, daz * k
        ax, ay, az = ax + dax, ay + day, az + daz
        vx, vy, vz = vx + ax * dt, vy + ay * dt, vz + az * dt
        v_norm = math.sqrt(vx * vx + vy * vy + vz * vz)
        if v_norm > cfg.max_velocity_mm_s:
            k = cfg.max_velocity_mm_s / v_norm
            vx, vy, vz = vx * k, vy * k, vz * k
            v_norm = cfg.max_velocity_mm_s
        px, py, pz = px + vx * dt, py + vy * dt, pz + vz * dt
        self._t_s += dt
        self._step_count += 1
        if self._halting and v_norm < 1e-6:
            vx = vy = vz = ax = ay = az = 0.0
            self._target = [px, py, pz]
        self._pos = [px, py, pz]
        self._vel = [vx, vy, vz]
        self._acc = [ax, ay, az]
        force = self._feel((px, py, pz))
        if cfg.force_noise_n > 0:
            force += float(self._rng.normal(0.0, cfg.force_noise_n))
        nz = self.noise
        if nz.force_noise_n > 0 or nz.force_bias_n or nz.force_drift_n_per_min:
            force += (nz.force_bias_n + nz.force_drift_n_per_min * self._t_s / 60.0
                      + float(self._rng.normal(0.0, nz.force_noise_n)))
        self._force_n = force
        self._samples.append((self._t_s, px, py, pz, force))

    def _feel(self, pos: tuple[float, float, float]) -> float:
        """The phantom's force at ``pos`` (computed again only when the pad moved)."""
        if self.phantom is None:
            return 0.0
        if self._felt is not None and self._felt[0] == pos:
            return self._felt[1]
        force = float(self.phantom.force_n(pos))
        self._felt = (pos, force)
        return force

    def advance(self, seconds: float) -> int:
        """Run the loop for ``seconds`` of simulated time (``realtime=False`` mode).

        Returns:
            The number of control steps run.

        Raises:
            ConfigError: called on a realtime arm (the wall clock drives it), or a negative
                time.
        """
        if self.config.realtime:
            raise ConfigError("advance() is for realtime=False; the wall clock drives this arm")
        if not (math.isfinite(seconds) and seconds >= 0):
            raise ConfigError("advance: seconds must be finite and >= 0")
        steps = round(seconds / self._dt)
        with self._lock:
            for _ in range(steps):
                self._step()
        return steps

    def _catch_up(self) -> None:
        """Realtime: run the steps due by now (call with the lock held).

        After a gap longer than :data:`_MAX_CATCH_UP_S` (the process was stopped or starved)
        only that much is run and the clock resynchronises: simulated time then lags the
        wall clock (the 1 kHz thread this replaces resynchronised after 50 ms behind). Unlike
        the thread, a gap in which nobody looked at the arm is cut too: a caller that needs
        longer spans simulated must look at least every 0.1 s (the station's watchdog does,
        every 5 ms).
        """
        if self._origin_s is None:
            return
        due = int((time.monotonic() - self._origin_s) / self._dt)
        behind = due - self._due_steps
        if behind <= 0:
            return
        most = max(1, round(_MAX_CATCH_UP_S / self._dt))
        if behind > most:
            self._origin_s += (behind - most) * self._dt
            behind = most
            due = self._due_steps + behind
        for _ in range(behind):
            self._step()
        self._due_steps = due

    # --------------------------------------------------------------- backend hooks

    def _connect(self) -> None:
        if self.config.realtime:
            with self._lock:
                self._origin_s = time.monotonic()
                self._due_steps = 0

    def _disconnect(self) -> None:
        with self._lock:
            self._catch_up()
            self._origin_s = None

    def _move_to(self, target_mm: Vec3) -> None:
        with self._lock:
            self._catch_up()
            self._target = [float(target_mm[0]), float(target_mm[1]), float(target_mm[2])]
            self._halting = False

    def _stop(self) -> None:
        with self._lock:
            self._catch_up()
            self._halting = True

    def _read(self) -> ArmReading:
        with self._lock:
            self._catch_up()
            px, py, pz = self._pos
            vx, vy, vz = self._vel
            tx, ty, tz = self._target
            ex, ey, ez = tx - px, ty - py, tz - pz
            moving = (math.sqrt(vx * vx + vy * vy + vz * vz) > 1e-3
                      or math.sqrt(ex * ex + ey * ey + ez * ez) > 1e-3)
            status = "halted" if self._halting else ("moving" if moving else "ok")
            if self.noise.position_noise_mm > 0:
                nx, ny, nz = self._rng.normal(0.0, self.noise.position_noise_mm, 3).tolist()
                px, py, pz = px + nx, py + ny, pz + nz
            return ArmReading((px, py, pz), (vx, vy, vz), self._force_n, status, (tx, ty, tz),
                              self._t_s)

    # --------------------------------------------------------------- extras

    def true_position_mm(self) -> Vec3:
        """Where the pad really is (the reading carries ``position_noise_mm``)."""
        with self._lock:
            self._catch_up()
            return (self._pos[0], self._pos[1], self._pos[2])

    @property
    def sim_time_s(self) -> float:
        """Simulated time since creation."""
        with self._lock:
            self._catch_up()
            return self._t_s

    @property
    def acceleration_mm_s2(self) -> Vec3:
        """The current commanded acceleration (for limit tests)."""
        with self._lock:
            self._catch_up()
            return (self._acc[0], self._acc[1], self._acc[2])

    def drain_samples(self) -> NDArray[np.float64]:
        """Return and clear the buffered 1 kHz samples as an (n, 5) array: t_s, x, y, z, force_n."""
        with self._lock:
            self._catch_up()
            out = np.asarray(self._samples, dtype=float).reshape(-1, 5)
            self._samples.clear()
        return out
