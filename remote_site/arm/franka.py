"""Optional Franka backend through ``franky-control`` (``pip install teletouch[franka]``).

Thin by design: the phantom frame is a pure translation of the robot base frame
(``origin_in_base_m``), the pad points straight down (``orientation_xyzw``, franky's ``Affine``
takes an [x, y, z, w] quaternion), targets go out as asynchronous absolute Cartesian motions
that preempt each other, and the measured force is the z component of the estimated external
wrench (``O_F_ext_hat_K``). Our API speaks mm and mm/s, franky metres and m/s; the conversion
happens in :meth:`FrankaArm._to_base` and :meth:`FrankaArm._position_mm` only. ``franky`` is
imported in :meth:`FrankaArm._connect` only.

Errors by phase (checked against a test double of franky's API,
``tests/remote_site/fake_franky.py``)::

    any franky error while connecting            DeviceInitError
    franky.NetworkException once connected       DeviceTimeoutError (the robot stopped answering)
    any other franky error (ControlException,    DeviceOperationError
      InvalidOperationException, ...)

franky registers each exception class on its own (they do not share a Python base class), and
an error inside an asynchronous motion surfaces at the *next* ``move``/``join_motion`` call,
so a reflex during a press is reported by the next target, and by :meth:`FrankaArm.state` at
once (``status="fault"`` while ``robot.has_errors``).

Halting (``stop()``, and always before disconnecting) preempts the running motion with
franky's ``CartesianStopMotion``, which decelerates along the path within the dynamics
limits; disconnecting then waits up to ``halt_timeout_s`` for the arm to stand still.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from remote_site.arm.base import Arm, ArmLimits, ArmReading, Vec3
from shared.errors import DeviceInitError, DeviceOperationError, DeviceTimeoutError

__all__ = ["FrankaArm", "FrankaConfig"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrankaConfig:
    """Settings of the Franka backend.

    Attributes:
        host: FCI address of the robot.
        origin_in_base_m: phantom origin in the robot base frame (m).
        orientation_xyzw: pad-down orientation quaternion in the base frame, [x, y, z, w].
        relative_dynamics_factor: franky's velocity/acceleration/jerk scale (0, 1].
        halt_timeout_s: how long disconnecting waits for the halt to finish.
    """

    host: str = "172.16.0.2"
    origin_in_base_m: tuple[float, float, float] = (0.5, 0.0, 0.2)
    orientation_xyzw: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    relative_dynamics_factor: float = 0.05
    halt_timeout_s: float = 2.0


class FrankaArm(Arm):
    """Franka Research 3 / Panda through franky (backend name ``franka``)."""

    def __init__(self, config: FrankaConfig | None = None, *,
                 limits: ArmLimits | None = None) -> None:
        super().__init__(limits=limits)
        self.config = config or FrankaConfig()
        self._franky: Any = None
        self._robot: Any = None
        self._target: Vec3 | None = None
        self._halted = False

    @property
    def name(self) -> str:
        return f"Franka at {self.config.host}"

    def _connect(self) -> None:
        try:
            import franky
        except ImportError as err:
            raise DeviceInitError(
                "the franka backend needs `pip install teletouch[franka]`") from err
        try:
            robot = franky.Robot(self.config.host)
            robot.recover_from_errors()
            robot.relative_dynamics_factor = self.config.relative_dynamics_factor
        except Exception as err:  # franky's exception classes share no base but Exception
            raise DeviceInitError(
                f"cannot connect to the Franka at {self.config.host}: "
                f"{type(err).__name__}: {err} (FCI enabled, brakes open, network?)") from err
        self._franky, self._robot = franky, robot
        self._target, self._halted = None, False

    def _disconnect(self) -> None:
        robot, self._robot = self._robot, None
        if robot is None:
            return
        with self._franky_errors("halt"):
            still = robot.join_motion(timeout=self.config.halt_timeout_s)
        if still is False:  # franky: False when the motion did not finish within the timeout
            raise DeviceTimeoutError(f"{self.name}: did not stand still within "
                                     f"{self.config.halt_timeout_s:g} s of the halt")

    @contextmanager
    def _franky_errors(self, what: str) -> Iterator[None]:
        """Sort franky's errors by phase (see the module docstring)."""
        network_error = getattr(self._franky, "NetworkException", None)
        try:
            yield
        except Exception as err:  # franky's exception classes share no base but Exception
            if (network_error is not None and isinstance(err, network_error)) \
                    or isinstance(err, TimeoutError):
                raise DeviceTimeoutError(f"{self.name}: {what}: the robot stopped answering: "
                                         f"{err}") from err
            raise DeviceOperationError(f"{self.name}: {what} failed: "
                                       f"{type(err).__name__}: {err}") from err

    def _to_base(self, p_mm: Vec3) -> list[float]:
        """Phantom mm -> robot base frame m."""
        return [o + v / 1000.0 for o, v in zip(self.config.origin_in_base_m, p_mm, strict=True)]

    def _move_to(self, target_mm: Vec3) -> None:
        fr = self._franky
        with self._franky_errors("move"):
            pose = fr.Affine(self._to_base(target_mm), list(self.config.orientation_xyzw))
            self._robot.move(fr.CartesianMotion(pose, fr.ReferenceType.Absolute),
                             asynchronous=True)
        self._target = target_mm
        self._halted = False

    def _position_mm(self) -> tuple[Vec3, Vec3]:
        """Robot base frame m, m/s -> phantom mm, mm/s."""
        state = self._robot.current_cartesian_state
        t = state.pose.end_effector_pose.translation
        v = state.velocity.end_effector_twist.linear
        pos = tuple((float(t[i]) - self.config.origin_in_base_m[i]) * 1000.0 for i in range(3))
        vel = tuple(float(v[i]) * 1000.0 for i in range(3))
        return pos, vel  # type: ignore[return-value]

    def _read(self) -> ArmReading:
        with self._franky_errors("state read"):
            pos, vel = self._position_mm()
            force = float(self._robot.state.O_F_ext_hat_K[2])
            fault = bool(self._robot.has_errors)
        moving = sum(c * c for c in vel) > 1e-6
        status = "fault" if fault else "halted" if self._halted else \
            ("moving" if moving else "ok")
        return ArmReading(pos, vel, force, status, self._target, time.monotonic())

    def _stop(self) -> None:
        if self._robot is None:
            return
        fr = self._franky
        with self._franky_errors("stop"):  # preempt the running motion, decelerate on path
            self._robot.move(fr.CartesianStopMotion(), asynchronous=True)
        self._halted = True
