"""A test double of the part of ``franky``'s public Python API that the Franka backend uses.

Written from franky's public documentation (its README and the pybind11 bindings'
signatures), not from its code, with the same names, argument conventions and units:

* ``Robot(fci_hostname, relative_dynamics_factor=1.0)`` connects in its constructor
  (libfranka raises ``NetworkException`` when nobody answers); ``recover_from_errors()``,
  the ``relative_dynamics_factor`` property, ``move(motion, asynchronous=False)``,
  ``join_motion(timeout=None) -> bool`` (False while the motion still runs at the timeout),
  ``stop()``, the read-only properties ``has_errors``, ``current_cartesian_state`` and
  ``state``.
* ``current_cartesian_state.pose.end_effector_pose`` is an ``Affine`` (``.translation`` in
  metres, ``.quaternion`` as [x, y, z, w]); ``current_cartesian_state.velocity
  .end_effector_twist`` a ``Twist`` (``.linear`` m/s, ``.angular`` rad/s);
  ``state.O_F_ext_hat_K`` the estimated external wrench (N, Nm), ``state.robot_mode``.
* ``Affine(translation=[0, 0, 0], quaternion=[0, 0, 0, 1])``, ``CartesianMotion(target,
  reference_type=ReferenceType.Absolute)``, ``CartesianStopMotion()``,
  ``ReferenceType.Absolute`` / ``ReferenceType.Relative``.
* Exceptions registered one by one (``py::register_exception``): ``Exception``,
  ``CommandException``, ``ControlException``, ``InvalidOperationException``,
  ``NetworkException``, ... each derives from Python's ``Exception`` only, not from one
  another.
* An error inside an *asynchronous* motion is stored and raised by the next ``move`` or
  ``join_motion`` call (franky README, "Real-Time Motions").

The simulated robot is kinematic: an absolute Cartesian motion puts the end effector at its
target the moment it is accepted, a relative one adds to the pose, a stop motion zeroes the
velocity. Tests drive the failure paths through :class:`FrankyDouble`.
"""

from __future__ import annotations

import enum
import types
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["FakeRobot", "FrankyDouble", "make_module"]


class ReferenceType(enum.Enum):
    """Whether a motion's target is absolute or relative to the current pose."""

    Absolute = 0
    Relative = 1


class RobotMode(enum.Enum):
    """libfranka's robot modes (the ones a test needs)."""

    Idle = 1
    Move = 2
    Reflex = 4


class Affine:
    """A rigid transform: translation (m) and rotation quaternion [x, y, z, w]."""

    def __init__(self, translation: Any = (0.0, 0.0, 0.0),
                 quaternion: Any = (0.0, 0.0, 0.0, 1.0)) -> None:
        t = np.asarray(translation, dtype=float)
        q = np.asarray(quaternion, dtype=float)
        if t.shape != (3,) or q.shape != (4,):
            raise TypeError(f"Affine(translation[3], quaternion[4]), got {t.shape}, {q.shape}")
        self.translation = t
        self.quaternion = q / np.linalg.norm(q)


@dataclass
class Twist:
    """Linear (m/s) and angular (rad/s) velocity."""

    linear: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class RobotPose:
    end_effector_pose: Affine


@dataclass
class RobotVelocity:
    end_effector_twist: Twist


@dataclass
class CartesianState:
    pose: RobotPose
    velocity: RobotVelocity


@dataclass
class RobotState:
    O_F_ext_hat_K: list[float]  # libfranka's name
    robot_mode: RobotMode


class CartesianMotion:
    """A Cartesian point-to-point motion to ``target``."""

    def __init__(self, target: Affine, reference_type: ReferenceType = ReferenceType.Absolute,
                 relative_dynamics_factor: float = 1.0) -> None:
        if not isinstance(target, Affine):
            raise TypeError("CartesianMotion needs an Affine target")
        if not isinstance(reference_type, ReferenceType):
            raise TypeError("reference_type must be a ReferenceType")
        self.target = target
        self.reference_type = reference_type
        self.relative_dynamics_factor = relative_dynamics_factor


class CartesianStopMotion:
    """Decelerate to standstill in Cartesian pose control."""


def _exception(name: str) -> type[Exception]:
    return type(name, (Exception,), {"__module__": "franky"})


EXCEPTION_NAMES = ("Exception", "CommandException", "ControlException",
                   "IncompatibleVersionException", "InvalidOperationException", "ModelException",
                   "NetworkException", "ProtocolException", "RealtimeException")


class FakeRobot:
    """The double of ``franky.Robot`` (see the module docstring)."""

    def __init__(self, fci_hostname: str, relative_dynamics_factor: float = 1.0) -> None:
        double = FrankyDouble.current
        if double.connect_error is not None:
            raise double.connect_error
        self.fci_hostname = fci_hostname
        self._factor = float(relative_dynamics_factor)
        self.calls: list[tuple[str, Any]] = []
        self.translation_m = np.array(double.start_translation_m, dtype=float)
        self.quaternion = np.array([1.0, 0.0, 0.0, 0.0])
        self.linear_velocity_m_s = np.zeros(3)
        self.force_z_n = 0.0
        self.has_errors_flag = False
        self.stored_error: Exception | None = None
        self.state_error: Exception | None = None
        self.motion_running = False
        self.halt_takes_forever = False
        double.robots.append(self)

    # ------------------------------------------------------------------ API

    def recover_from_errors(self) -> bool:
        self.calls.append(("recover_from_errors", None))
        self.has_errors_flag = False
        return True

    @property
    def relative_dynamics_factor(self) -> float:
        return self._factor

    @relative_dynamics_factor.setter
    def relative_dynamics_factor(self, value: float) -> None:
        if not 0.0 < float(value) <= 1.0:
            raise ValueError("relative dynamics factor must lie in (0, 1]")
        self.calls.append(("relative_dynamics_factor", float(value)))
        self._factor = float(value)

    def move(self, motion: Any, asynchronous: bool = False) -> bool:
        self.calls.append(("move", (motion, asynchronous)))
        self._raise_stored()
        if isinstance(motion, CartesianStopMotion):
            self.linear_velocity_m_s = np.zeros(3)
            self.motion_running = self.halt_takes_forever
            return True
        if not isinstance(motion, CartesianMotion):
            raise FrankyDouble.current.module.InvalidMotionTypeException(
                f"unsupported motion {type(motion).__name__}")
        if motion.reference_type is ReferenceType.Absolute:
            self.translation_m = motion.target.translation.copy()
            self.quaternion = motion.target.quaternion.copy()
        else:
            self.translation_m = self.translation_m + motion.target.translation
        self.motion_running = asynchronous
        return True

    def join_motion(self, timeout: float | None = None) -> bool:
        self.calls.append(("join_motion", timeout))
        self._raise_stored()
        if self.motion_running and self.halt_takes_forever:
            return False
        self.motion_running = False
        return True

    def stop(self) -> None:
        self.calls.append(("stop", None))
        self.motion_running = False

    @property
    def has_errors(self) -> bool:
        return self.has_errors_flag

    @property
    def current_cartesian_state(self) -> CartesianState:
        if self.state_error is not None:
            raise self.state_error
        return CartesianState(
            RobotPose(Affine(self.translation_m.copy(), self.quaternion.copy())),
            RobotVelocity(Twist(self.linear_velocity_m_s.copy())))

    @property
    def state(self) -> RobotState:
        if self.state_error is not None:
            raise self.state_error
        mode = RobotMode.Reflex if self.has_errors_flag else \
            (RobotMode.Move if self.motion_running else RobotMode.Idle)
        return RobotState([0.0, 0.0, self.force_z_n, 0.0, 0.0, 0.0], mode)

    # ------------------------------------------------------------------ failure injection

    def fail_running_motion(self, err: Exception) -> None:
        """The running asynchronous motion dies (a reflex): stored, raised by the next call."""
        self.stored_error = err
        self.has_errors_flag = True
        self.motion_running = False
        self.linear_velocity_m_s = np.zeros(3)

    def _raise_stored(self) -> None:
        err, self.stored_error = self.stored_error, None
        if err is not None:
            raise err


class FrankyDouble:
    """What a test controls: the module, the robots it made, the failures to inject.

    Attributes:
        module: the fake ``franky`` module (installed in ``sys.modules`` by the fixture).
        robots: every :class:`FakeRobot` constructed.
        connect_error: raised by the next ``Robot(...)`` when set.
        start_translation_m: end-effector position of a new robot, base frame (m).
    """

    current: FrankyDouble

    def __init__(self) -> None:
        self.module = make_module()
        self.robots: list[FakeRobot] = []
        self.connect_error: Exception | None = None
        self.start_translation_m = (0.5, 0.0, 0.22)
        FrankyDouble.current = self

    @property
    def robot(self) -> FakeRobot:
        """The last robot constructed."""
        return self.robots[-1]


def make_module() -> types.ModuleType:
    """A fresh fake ``franky`` module with the classes above and franky's exceptions."""
    module = types.ModuleType("franky", __doc__)
    for name in (*EXCEPTION_NAMES, "InvalidMotionTypeException"):
        setattr(module, name, _exception(name))
    module.Robot = FakeRobot  # type: ignore[attr-defined]
    module.Affine = Affine  # type: ignore[attr-defined]
    module.Twist = Twist  # type: ignore[attr-defined]
    module.CartesianMotion = CartesianMotion  # type: ignore[attr-defined]
    module.CartesianStopMotion = CartesianStopMotion  # type: ignore[attr-defined]
    module.ReferenceType = ReferenceType  # type: ignore[attr-defined]
    module.RobotMode = RobotMode  # type: ignore[attr-defined]
    module.CartesianState = CartesianState  # type: ignore[attr-defined]
    module.RobotState = RobotState  # type: ignore[attr-defined]
    return module
