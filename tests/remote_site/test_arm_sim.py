"""Simulated arm: limits, convergence, clamping, phantom feel, registry, lifecycle."""

from __future__ import annotations

import importlib.util
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.arm import ARM_BACKENDS, Arm, ArmLimits, arm_class, open_arm
from remote_site.arm.sim import SimArm, SimArmConfig
from remote_site.phantom import make_scene
from shared.errors import ConfigError, DeviceInitError, DeviceNotConnectedError, InputDataError
from tests.support import scaled

PHANTOM = make_scene("breast", 1)


def manual_arm(**kwargs: object) -> SimArm:
    cfg = SimArmConfig(realtime=False, **kwargs)  # type: ignore[arg-type]
    arm = SimArm(PHANTOM, cfg)
    arm.connect()
    return arm


@pytest.mark.parametrize("target", [(10.0, 5.0, 2.0), (-40.0, 30.0, 10.0), (0.0, 0.0, -3.0),
                                    (0.01, 0.0, 20.0)])
def test_limits_hold_and_target_is_reached(target: tuple[float, float, float]) -> None:
    arm = manual_arm()
    cfg = arm.config
    arm.move_to(target)
    prev_acc = np.zeros(3)
    for _ in range(1500):
        arm.advance(0.001)
        s = arm.state()
        acc = np.array(arm.acceleration_mm_s2)
        assert np.linalg.norm(s.velocity_mm_s) <= cfg.max_velocity_mm_s * (1 + 1e-9)
        assert np.linalg.norm(acc) <= cfg.max_acceleration_mm_s2 * (1 + 1e-9)
        assert np.linalg.norm(acc - prev_acc) / 0.001 <= cfg.max_jerk_mm_s3 * (1 + 1e-9)
        prev_acc = acc
    assert np.allclose(s.position_mm, target, atol=1e-3)
    assert s.status == "ok"


def test_no_large_overshoot_on_a_press() -> None:
    arm = manual_arm()
    arm.move_to((0.0, 0.0, -3.0))
    zs = []
    for _ in range(1500):
        arm.advance(0.001)
        zs.append(arm.state().position_mm[2])
    assert min(zs) > -3.0 - 0.05


def test_force_is_the_phantom_force_at_the_pose() -> None:
    arm = manual_arm()
    arm.move_to((3.0, -4.0, -2.0))
    arm.advance(1.5)
    s = arm.state()
    assert s.force_n == pytest.approx(PHANTOM.force_n(s.position_mm))
    assert s.force_n > 1.0
    samples = arm.drain_samples()
    assert samples.shape == (1500, 5)
    assert np.all(np.diff(samples[:, 0]) > 0)
    assert arm.drain_samples().shape == (0, 5)


def test_force_noise_is_seeded() -> None:
    forces = []
    for _ in range(2):
        arm = manual_arm(force_noise_n=0.02, seed=3)
        arm.move_to((0.0, 0.0, -2.0))
        arm.advance(1.0)
        forces.append(arm.drain_samples()[:, 4])
    np.testing.assert_array_equal(forces[0], forces[1])
    tail = forces[0][-200:]
    assert 0.01 < tail.std() < 0.03


def test_targets_are_clamped_to_the_limits_and_validated() -> None:
    arm = SimArm(PHANTOM, SimArmConfig(realtime=False),
                 limits=ArmLimits((-10.0, -10.0, -2.0), (10.0, 10.0, 30.0), (0.0, 0.0, 5.0)))
    with arm:
        assert arm.move_to((50.0, -50.0, -9.0)) == (10.0, -10.0, -2.0)
        with pytest.raises(InputDataError):
            arm.move_to((0.0, float("nan"), 0.0))
        with pytest.raises(InputDataError):
            arm.move_to((1.0, 2.0))
        assert arm.home() == (0.0, 0.0, 5.0)


def test_stop_halts_and_holds() -> None:
    arm = manual_arm()
    arm.move_to((40.0, 0.0, 20.0))
    arm.advance(0.1)
    arm.stop()
    arm.advance(0.5)
    s1 = arm.state()
    arm.advance(0.5)
    s2 = arm.state()
    assert s1.status == "halted" and s1.position_mm == s2.position_mm
    assert s1.position_mm[0] < 40.0


def test_not_connected_and_lifecycle() -> None:
    arm = SimArm(PHANTOM, SimArmConfig(realtime=False))
    with pytest.raises(DeviceNotConnectedError):
        arm.state()
    with arm:
        assert arm.connected
    assert not arm.connected
    arm.disconnect()  # idempotent


def test_realtime_arm_follows_the_wall_clock_without_a_thread() -> None:
    import threading

    before = threading.active_count()
    arm = SimArm(PHANTOM, SimArmConfig(realtime=True))
    with arm:
        assert threading.active_count() == before  # steps run when the arm is looked at
        with pytest.raises(ConfigError):
            arm.advance(0.1)
        arm.move_to((0.0, 0.0, 15.0))
        deadline = time.monotonic() + scaled(3.0)
        while time.monotonic() < deadline and arm.state().status != "ok":
            time.sleep(0.01)
        assert arm.state().position_mm == pytest.approx((0.0, 0.0, 15.0), abs=1e-3)
        assert arm.sim_time_s > 0.02


def test_config_rejects_beyond_franka_limits() -> None:
    with pytest.raises(ConfigError):
        SimArmConfig(max_velocity_mm_s=5000.0)
    with pytest.raises(ConfigError):
        SimArmConfig(force_noise_n=-1.0)


def test_registry() -> None:
    assert arm_class("sim") is SimArm
    assert arm_class("remote_site.arm.sim:SimArm") is SimArm
    assert set(ARM_BACKENDS) >= {"sim", "franka"}
    arm = open_arm("sim", phantom=PHANTOM, config=SimArmConfig(realtime=False))
    assert isinstance(arm, Arm)
    with pytest.raises(ConfigError):
        arm_class("nope")
    with pytest.raises(ConfigError):
        arm_class("remote_site.arm.sim:SimArmConfig")
    with pytest.raises(DeviceInitError):
        arm_class("no_such_module_xyz:Arm")


def test_franka_backend_without_franky() -> None:
    if importlib.util.find_spec("franky") is not None:
        pytest.skip("franky installed: needs a robot")
    arm = open_arm("franka")
    with pytest.raises(DeviceInitError):
        arm.connect()


def test_reading_to_wire_message() -> None:
    arm = manual_arm()
    msg = arm.state().to_message(seq=4, ts_us=123, source_seq=2)
    assert msg.seq == 4 and msg.source_seq == 2 and msg.status == "ok"


def test_a_move_past_its_deadline_is_not_started() -> None:
    from shared.errors import CommandExpiredError
    from shared.timebase import monotonic_s

    arm = SimArm(make_scene("localization", 0), SimArmConfig(realtime=False))
    with arm:
        arm.move_to((1.0, 2.0, 5.0), not_after_s=monotonic_s() + 10.0)
        with pytest.raises(CommandExpiredError, match="past its deadline"):
            arm.move_to((9.0, 9.0, 9.0), not_after_s=monotonic_s() - 0.001)
        assert arm.state().target_mm == (1.0, 2.0, 5.0)


def _reference_trajectory(cfg: SimArmConfig, home: tuple[float, float, float],
                          moves: list[tuple[tuple[float, float, float], int, bool]]
                          ) -> np.ndarray:
    """The control law written with numpy vectors (the previous implementation): positions."""
    dt = 1.0 / cfg.loop_hz
    pos, vel, acc = np.array(home, float), np.zeros(3), np.zeros(3)
    out = []
    for target_t, steps, halt in moves:
        target = np.array(target_t, float)
        for _ in range(steps):
            err = target - pos
            dist = float(np.linalg.norm(err))
            if halt or dist <= 1e-12:
                v_des = np.zeros(3)
            else:
                speed = min(cfg.max_velocity_mm_s,
                            np.sqrt(2.0 * 0.6 * cfg.max_acceleration_mm_s2 * dist),
                            cfg.position_gain_1_s * dist)
                v_des = err / dist * speed
            a_des = (v_des - vel) / dt
            a_norm = float(np.linalg.norm(a_des))
            if a_norm > cfg.max_acceleration_mm_s2:
                a_des *= cfg.max_acceleration_mm_s2 / a_norm
            da = a_des - acc
            da_norm = float(np.linalg.norm(da))
            if da_norm > cfg.max_jerk_mm_s3 * dt:
                da *= cfg.max_jerk_mm_s3 * dt / da_norm
            acc = acc + da
            vel = vel + acc * dt
            v_norm = float(np.linalg.norm(vel))
            if v_norm > cfg.max_velocity_mm_s:
                vel *= cfg.max_velocity_mm_s / v_norm
            pos = pos + vel * dt
            if halt and float(np.linalg.norm(vel)) < 1e-6:
                vel[:] = 0.0
                acc[:] = 0.0
                target = pos.copy()
            out.append(pos.copy())
    return np.asarray(out)


@settings(max_examples=15, deadline=None)
@given(targets=st.lists(st.tuples(st.floats(-45, 45), st.floats(-45, 45), st.floats(-5, 35),
                                  st.integers(1, 400), st.booleans()), min_size=1, max_size=4))
def test_control_law_matches_a_numpy_reference(
        targets: list[tuple[float, float, float, int, bool]]) -> None:
    # the arm steps in plain floats; the same law with numpy vectors is the reference
    arm = manual_arm()
    moves = []
    for x, y, z, steps, halt in targets:
        arm.move_to((x, y, z))
        if halt:
            arm.stop()
        arm.advance(steps / arm.config.loop_hz)
        moves.append(((x, y, z), steps, halt))
    got = arm.drain_samples()[:, 1:4]
    want = _reference_trajectory(arm.config, arm.limits.home_mm, moves)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
