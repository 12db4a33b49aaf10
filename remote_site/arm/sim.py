"""Simulated arm: a Cartesian point with Franka-like velocity/acceleration/jerk limits.

A 1 kHz loop moves the pad towards its target with a time-optimal braking profile
(``v_des = min(v_max, sqrt(2 m a_max d), K_p d)`` along the line to the target, with a braking
margin ``m`` < 1 that absorbs the jerk-limited ramp and a proportional gain ``K_p`` for the
final, exponential approach), then limits acceleration and jerk. At every step the pad
feels the phantom: the measured force is
``phantom.force_n(position)`` plus optional Gaussian noise.

Time is injectable: with ``realtime=True`` a thread runs the loop against the wall clock;
with ``realtime=False`` nothing moves until the caller calls :meth:`SimArm.advance`, which
makes tests deterministic and fast. Every step's (t, x, y, z, force) is kept in a bounded
buffer for the stiffness stage (:meth:`SimArm.drain_samples`).

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
from shared.errors import ConfigError, DeviceInitError

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
        realtime: run the loop in a thread on the wall clock (else :meth:`SimArm.advance`).
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
        self._pos = np.array(self.limits.home_mm, dtype=float)
        self._vel = np.zeros(3)
        self._acc = np.zeros(3)
        self._target = self._pos.copy()
        self._halting = False
        self._t_s = 0.0
        self._force_n = 0.0
        self._rng = np.random.default_rng(self.config.seed)
        self._samples: deque[tuple[float, float, float, float, float]] = deque(
            maxlen=self.config.sample_buffer)
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._step_count = 0

    # --------------------------------------------------------------- plant

    def _step(self) -> None:
        """One control period (call with the lock held)."""
        cfg, dt = self.config, self._dt
        err = self._target - self._pos
        dist = float(np.linalg.norm(err))
        if self._halting:
            v_des = np.zeros(3)
        elif dist > 1e-12:
            speed = min(cfg.max_velocity_mm_s,
                        math.sqrt(2.0 * _BRAKE_MARGIN * cfg.max_acceleration_mm_s2 * dist),
                        cfg.position_gain_1_s * dist)
            v_des = err / dist * speed
        else:
            v_des = np.zeros(3)
        a_des = (v_des - self._vel) / dt
        a_norm = float(np.linalg.norm(a_des))
        if a_norm > cfg.max_acceleration_mm_s2:
            a_des *= cfg.max_acceleration_mm_s2 / a_norm
        da = a_des - self._acc
        da_norm = float(np.linalg.norm(da))
        da_max = cfg.max_jerk_mm_s3 * dt
        if da_norm > da_max:
            da *= da_max / da_norm
        self._acc = self._acc + da
        self._vel = self._vel + self._acc * dt
        v_norm = float(np.linalg.norm(self._vel))
        if v_norm > cfg.max_velocity_mm_s:
            self._vel *= cfg.max_velocity_mm_s / v_norm
        self._pos = self._pos + self._vel * dt
        self._t_s += dt
        self._step_count += 1
        if self._halting and float(np.linalg.norm(self._vel)) < 1e-6:
            self._vel[:] = 0.0
            self._acc[:] = 0.0
            self._target = self._pos.copy()
        force = self.phantom.force_n(self._pos.tolist()) if self.phantom is not None else 0.0
        if cfg.force_noise_n > 0:
            force += float(self._rng.normal(0.0, cfg.force_noise_n))
        nz = self.noise
        if nz.force_noise_n > 0 or nz.force_bias_n or nz.force_drift_n_per_min:
            force += (nz.force_bias_n + nz.force_drift_n_per_min * self._t_s / 60.0
                      + float(self._rng.normal(0.0, nz.force_noise_n)))
        self._force_n = force
        self._samples.append((self._t_s, *self._pos.tolist(), force))

    def advance(self, seconds: float) -> int:
        """Run the loop for ``seconds`` of simulated time (``realtime=False`` mode).

        Returns:
            The number of control steps run.

        Raises:
            ConfigError: called while the realtime thread owns the loop, or a negative time.
        """
        if self._thread is not None:
            raise ConfigError("advance() is for realtime=False; the loop thread is running")
        if not (math.isfinite(seconds) and seconds >= 0):
            raise ConfigError("advance: seconds must be finite and >= 0")
        steps = round(seconds / self._dt)
        with self._lock:
            for _ in range(steps):
                self._step()
        return steps

    def _loop(self) -> None:
        next_t = time.monotonic()
        while self._running.is_set():
            now = time.monotonic()
            behind = int((now - next_t) / self._dt) + 1
            with self._lock:
                for _ in range(min(behind, 50)):  # catch up, but never spiral
                    self._step()
            next_t += behind * self._dt
            if now - next_t > 0.05:
                next_t = now  # fell far behind (loaded machine): resynchronise
            time.sleep(max(0.0, next_t - time.monotonic()))

    # --------------------------------------------------------------- backend hooks

    def _connect(self) -> None:
        if self.config.realtime:
            self._running.set()
            self._thread = threading.Thread(target=self._loop, name="sim-arm-1khz", daemon=True)
            try:
                self._thread.start()
            except RuntimeError as err:
                self._thread = None
                raise DeviceInitError("could not start the sim arm loop") from err

    def _disconnect(self) -> None:
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None

    def _move_to(self, target_mm: Vec3) -> None:
        with self._lock:
            self._target = np.asarray(target_mm, dtype=float)
            self._halting = False

    def _stop(self) -> None:
        with self._lock:
            self._halting = True

    def _read(self) -> ArmReading:
        with self._lock:
            moving = (float(np.linalg.norm(self._vel)) > 1e-3
                      or float(np.linalg.norm(self._target - self._pos)) > 1e-3)
            status = "halted" if self._halting else ("moving" if moving else "ok")
            seen = self._pos
            if self.noise.position_noise_mm > 0:
                seen = seen + self._rng.normal(0.0, self.noise.position_noise_mm, 3)
            pos = (float(seen[0]), float(seen[1]), float(seen[2]))
            vel = (float(self._vel[0]), float(self._vel[1]), float(self._vel[2]))
            tgt = (float(self._target[0]), float(self._target[1]), float(self._target[2]))
            return ArmReading(pos, vel, self._force_n, status, tgt, self._t_s)

    # --------------------------------------------------------------- extras

    def true_position_mm(self) -> Vec3:
        """Where the pad really is (the reading carries ``position_noise_mm``)."""
        with self._lock:
            return (float(self._pos[0]), float(self._pos[1]), float(self._pos[2]))

    @property
    def sim_time_s(self) -> float:
        """Simulated time since creation."""
        return self._t_s

    @property
    def acceleration_mm_s2(self) -> Vec3:
        """The current commanded acceleration (for limit tests)."""
        with self._lock:
            return (float(self._acc[0]), float(self._acc[1]), float(self._acc[2]))

    def drain_samples(self) -> NDArray[np.float64]:
        """Return and clear the buffered 1 kHz samples as an (n, 5) array: t_s, x, y, z, force_n."""
        with self._lock:
            out = np.asarray(self._samples, dtype=float).reshape(-1, 5)
            self._samples.clear()
        return out
