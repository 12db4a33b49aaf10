"""The Franka backend against a test double of franky (``tests/remote_site/fake_franky.py``):
the calls it makes, mm <-> m at the boundary, errors by phase, halting on disconnect, and the
device layer's common lifecycle, so the first session on a real arm fails early and loudly."""

from __future__ import annotations

import sys
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.arm.base import ArmLimits
from remote_site.arm.franka import FrankaArm, FrankaConfig
from remote_site.arm.registry import open_arm
from shared.errors import (
    DeviceInitError,
    DeviceNotConnectedError,
    DeviceOperationError,
    DeviceTimeoutError,
)
from tests.remote_site.fake_franky import CartesianMotion, CartesianStopMotion, FrankyDouble
from tests.shared.test_devices import KindCase
from tests.shared.test_devices import (
    test_every_kind_follows_the_same_lifecycle as run_common_lifecycle,
)

CONFIG = FrankaConfig(host="10.0.0.7", origin_in_base_m=(0.5, -0.1, 0.2),
                      relative_dynamics_factor=0.1, halt_timeout_s=0.5)


@pytest.fixture
def franky() -> Iterator[FrankyDouble]:
    """The fake ``franky`` module in ``sys.modules`` for one test (restored after)."""
    double = FrankyDouble()
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(sys.modules, "franky", double.module)
        yield double


def _moves(double: FrankyDouble) -> list[tuple[object, bool]]:
    return [args for name, args in double.robot.calls if name == "move"]


def test_connect_opens_the_configured_robot_recovers_and_slows_it(franky: FrankyDouble) -> None:
    with FrankaArm(CONFIG) as arm:
        assert arm.is_connected
        robot = franky.robot
        assert robot.fci_hostname == "10.0.0.7"
        assert ("recover_from_errors", None) in robot.calls
        assert robot.relative_dynamics_factor == pytest.approx(0.1)
    assert not arm.is_connected


def test_targets_go_out_in_metres_as_async_absolute_pad_down_motions(
        franky: FrankyDouble) -> None:
    with FrankaArm(CONFIG) as arm:
        applied = arm.move_to((10.0, -5.0, 3.0))
        assert applied == (10.0, -5.0, 3.0)
        motion, asynchronous = _moves(franky)[-1]
        assert isinstance(motion, CartesianMotion) and asynchronous is True
        assert motion.reference_type is franky.module.ReferenceType.Absolute
        np.testing.assert_allclose(motion.target.translation, [0.510, -0.105, 0.203])
        np.testing.assert_allclose(motion.target.quaternion, [1.0, 0.0, 0.0, 0.0])


def test_state_comes_back_in_mm_mm_s_and_newtons(franky: FrankyDouble) -> None:
    with FrankaArm(CONFIG) as arm:
        robot = franky.robot
        robot.translation_m = np.array([0.512, -0.097, 0.19])
        robot.linear_velocity_m_s = np.array([0.0, 0.02, -0.001])
        robot.force_z_n = 2.5
        reading = arm.state()
        assert reading.position_mm == pytest.approx((12.0, 3.0, -10.0))
        assert reading.velocity_mm_s == pytest.approx((0.0, 20.0, -1.0))
        assert reading.force_n == pytest.approx(2.5)
        assert reading.status == "moving"


@settings(max_examples=50, deadline=None)
@given(st.tuples(*(st.floats(-60.0, 60.0, allow_nan=False) for _ in range(3))))
def test_a_target_round_trips_through_franky_units(target: tuple[float, float, float]) -> None:
    double = FrankyDouble()
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(sys.modules, "franky", double.module)
        with FrankaArm(CONFIG, limits=ArmLimits()) as arm:
            applied = arm.move_to(target)
            assert arm.state().position_mm == pytest.approx(applied, abs=1e-9)
            lo, hi = arm.limits.lower_mm, arm.limits.upper_mm
            assert all(lo[i] <= applied[i] <= hi[i] for i in range(3))


def test_network_error_at_connect_is_an_init_error_naming_the_host(
        franky: FrankyDouble) -> None:
    franky.connect_error = franky.module.NetworkException("libfranka: Connection timeout")
    arm = FrankaArm(CONFIG)
    with pytest.raises(DeviceInitError, match=r"10\.0\.0\.7") as info:
        arm.connect()
    assert isinstance(info.value.__cause__, franky.module.NetworkException)
    assert not arm.is_connected


def test_control_exception_mid_press_is_a_fault_then_an_operation_error(
        franky: FrankyDouble) -> None:
    with FrankaArm(CONFIG) as arm:
        arm.move_to((0.0, 0.0, -2.0))
        reflex = franky.module.ControlException("cartesian_reflex")
        franky.robot.fail_running_motion(reflex)
        assert arm.state().status == "fault"  # seen at once, before the next target
        with pytest.raises(DeviceOperationError, match="ControlException") as info:
            arm.move_to((0.0, 0.0, -3.0))
        assert info.value.__cause__ is reflex


def test_invalid_operation_is_an_operation_error(franky: FrankyDouble) -> None:
    with FrankaArm(CONFIG) as arm:
        franky.robot.stored_error = franky.module.InvalidOperationException("not in control")
        with pytest.raises(DeviceOperationError, match="InvalidOperationException"):
            arm.move_to((1.0, 1.0, 10.0))


@pytest.mark.parametrize("error", ["network", "timeout"])
def test_a_robot_that_stops_answering_is_a_timeout(franky: FrankyDouble, error: str) -> None:
    with FrankaArm(CONFIG) as arm:
        franky.robot.state_error = (franky.module.NetworkException("UDP receive: Timeout")
                                    if error == "network" else TimeoutError("no state"))
        with pytest.raises(DeviceTimeoutError, match="stopped answering"):
            arm.state()
        franky.robot.state_error = None


def test_stop_and_disconnect_halt_the_arm_before_releasing_it(franky: FrankyDouble) -> None:
    arm = FrankaArm(CONFIG)
    arm.connect()
    arm.move_to((5.0, 5.0, 5.0))
    arm.stop()
    motion, asynchronous = _moves(franky)[-1]
    assert isinstance(motion, CartesianStopMotion) and asynchronous is True
    assert arm.state().status == "halted"
    robot = franky.robot
    n_calls = len(robot.calls)
    arm.disconnect()
    after = [name for name, _ in robot.calls[n_calls:]]
    assert after == ["move", "join_motion"]  # halt, then wait until it stands still
    assert isinstance(_moves(franky)[-1][0], CartesianStopMotion)
    assert ("join_motion", CONFIG.halt_timeout_s) in robot.calls
    with pytest.raises(DeviceNotConnectedError):
        arm.state()


def test_an_arm_that_does_not_stand_still_fails_the_disconnect_loudly(
        franky: FrankyDouble) -> None:
    arm = FrankaArm(CONFIG)
    arm.connect()
    arm.move_to((5.0, 5.0, 5.0))
    franky.robot.halt_takes_forever = True
    with pytest.raises(DeviceTimeoutError, match="stand still"):
        arm.disconnect()
    assert not arm.is_connected


def test_common_lifecycle_with_the_double(franky: FrankyDouble) -> None:
    run_common_lifecycle(KindCase("arm", "franka", lambda: {"config": CONFIG},
                                  lambda dev: dev.state()))
    assert isinstance(open_arm("franka"), FrankaArm)
    assert len(franky.robots) == 2  # connect, then the context manager's reconnect
