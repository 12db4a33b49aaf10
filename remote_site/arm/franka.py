"""Optional Franka backend through ``franky-control`` (``pip install teletouch[franka]``).

Thin by design: the phantom frame is a pure translation of the robot base frame
(``origin_in_base_m``), the pad points straight down (``orientation_xyzw``), targets go out
as asynchronous absolute Cartesian motions that preempt each other, and the measured force is
the z component of the estimated external wrench (``O_F_ext_hat_K``). ``franky`` is imported
in :meth:`FrankaArm._connect` only. Untested without a robot (tests skip it when ``franky``
is not installed).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

from remote_site.arm.base import Arm, ArmLimits, ArmReading, Vec3
from shared.errors import DeviceInitError, DeviceOperationError

__all__ = ["FrankaArm", "FrankaConfig"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrankaConfig:
    """Settings of the Franka backend.

    Attributes:
        host: FCI address of the robot.
        origin_in_base_m: phantom origin in the robot base frame (m).
        orientation_xyzw: pad-down orientation quaternion in the base frame.
        relative_dynamics_factor: franky's velocity/acceleration/jerk scale (0, 1].
    """

    host: str = "172.16.0.2"
    origin_in_base_m: tuple[float, float, float] = (0.5, 0.0, 0.2)
    orientation_xyzw: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    relative_dynamics_factor: float = 0.05


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
        except Exception as err:  # franky raises its own exception types
            raise DeviceInitError(
                f"cannot connect to the Franka at {self.config.host}: {err}") from err
        self._franky, self._robot = franky, robot

    def _disconnect(self) -> None:
        self._robot = None

    def _to_base(self, p_mm: Vec3) -> list[float]:
        return [o + v / 1000.0 for o, v in zip(self.config.origin_in_base_m, p_mm, strict=True)]

    def _move_to(self, target_mm: Vec3) -> None:
        fr = self._franky
        try:
            pose = fr.Affine(self._to_base(target_mm), list(self.config.orientation_xyzw))
            self._robot.move(fr.CartesianMotion(pose, fr.ReferenceType.Absolute),
                             asynchronous=True)
        except Exception as err:
            raise DeviceOperationError(f"Franka move failed: {err}") from err
        self._target = target_mm
        self._halted = False

    def _position_mm(self) -> tuple[Vec3, Vec3]:
        state = self._robot.current_cartesian_state
        t = state.pose.end_effector_pose.translation
        v = state.velocity.end_effector_twist.linear
        pos = tuple((float(t[i]) - self.config.origin_in_base_m[i]) * 1000.0 for i in range(3))
        vel = tuple(float(v[i]) * 1000.0 for i in range(3))
        return pos, vel  # type: ignore[return-value]

    def _read(self) -> ArmReading:
        try:
            pos, vel = self._position_mm()
            force = float(self._robot.state.O_F_ext_hat_K[2])
        except Exception as err:
            raise DeviceOperationError(f"Franka state read failed: {err}") from err
        moving = sum(c * c for c in vel) > 1e-6
        status = "halted" if self._halted else ("moving" if moving else "ok")
        return ArmReading(pos, vel, force, status, self._target, time.monotonic())

    def _stop(self) -> None:
        if self._robot is None:
            return
        try:  # preempt the running motion with one to the current pose
            pos, _ = self._position_mm()
            self._move_to(pos)
        except DeviceOperationError:
            log.exception("Franka stop failed")
            raise
        self._halted = True
