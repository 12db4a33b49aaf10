"""The realistic simulated world: each imperfection is there, --ideal removes them all."""

from __future__ import annotations

import numpy as np
import pytest

from remote_site.agent.world import IDEAL, REALISTIC, Realism, Registration, build_world
from remote_site.arm.sim import ArmNoise, SimArm, SimArmConfig
from remote_site.sensor.simulator import SimulatedSensor
from shared.errors import ConfigError


def test_ideal_world_is_perfect_and_realistic_one_is_not() -> None:
    ideal = build_world("breast", 4, ideal=True)
    assert ideal.registration == Registration() and ideal.phantom.layer.nonlinearity == 0
    assert "noise" not in ideal.arm_options()
    real = build_world("breast", 4)
    assert real.realism == REALISTIC and real.registration != Registration()
    assert real.phantom.layer.nonlinearity == REALISTIC.tissue_nonlinearity
    assert real.arm_options()["noise"].force_noise_n == REALISTIC.force_noise_n
    # the registration is per session (seed), hidden, and repeatable
    assert build_world("breast", 4).registration == real.registration
    assert build_world("breast", 5).registration != real.registration


def test_registration_moves_what_the_arm_feels() -> None:
    world = build_world("localization", 2)
    t = world.phantom.tumors[0]
    reg = world.registration
    # the arm commanded onto the true tumor position (inverse registration) feels it
    c, s = np.cos(np.radians(-reg.yaw_deg)), np.sin(np.radians(-reg.yaw_deg))
    px, py = t.center_mm[0] - reg.dx_mm, t.center_mm[1] - reg.dy_mm
    on = (c * px - s * py, s * px + c * py, -2.0)
    field = world.arm_options()["phantom"]
    direct = world.phantom.force_n((*t.center_mm, -2.0 + reg.dz_mm))
    assert field.force_n(on) == pytest.approx(direct, rel=1e-6)


def test_arm_noise_bias_and_drift() -> None:
    arm = SimArm(config=SimArmConfig(realtime=False),
                 noise=ArmNoise(force_noise_n=0.05, force_bias_n=0.3, force_drift_n_per_min=0.6,
                                position_noise_mm=0.1))
    arm.connect()
    forces, xs = [], []
    for _ in range(200):
        arm.advance(0.01)
        r = arm.state()
        forces.append(r.force_n)
        xs.append(r.position_mm[0])
    arm.disconnect()
    f = np.array(forces)
    assert f[:50].mean() == pytest.approx(0.3 + 0.6 * 0.25 / 60, abs=0.03)  # bias in free air
    assert f[-50:].mean() - f[:50].mean() == pytest.approx(0.6 * 1.5 / 60, abs=0.03)
    assert np.std(xs) == pytest.approx(0.1, rel=0.3)
    assert arm.true_position_mm()[0] == 0.0
    with pytest.raises(ConfigError):
        ArmNoise(force_noise_n=-1.0)


def test_led_drift_changes_brightness_with_time() -> None:
    clock = [0.0]
    sensor = SimulatedSensor(led_drift_per_min=0.01, seed=3, clock_s=lambda: clock[0])
    sensor.connect()
    first = sensor.read_latest().rgb.astype(float).mean(axis=(0, 1))
    clock[0] = 600.0  # ten minutes later
    later = sensor.read_latest().rgb.astype(float).mean(axis=(0, 1))
    sensor.disconnect()
    expected = 1.0 + sensor._drift_per_s * 600.0
    np.testing.assert_allclose(later / first, expected, rtol=0.01)
    assert np.abs(later / first - 1).max() > 0.005


def test_realism_is_validated_and_scales() -> None:
    with pytest.raises(ConfigError, match="force_noise_n"):
        Realism(force_noise_n=-0.1)
    assert REALISTIC.scaled(0.0) == Realism()
    assert REALISTIC.scaled(2.0).camera_noise_dn == pytest.approx(2 * REALISTIC.camera_noise_dn)
    assert IDEAL.camera_noise_dn == 1.0


def test_depth_provider_turns_a_contact_and_leaves_no_contact_flat() -> None:
    from remote_site.agent.world import _rotate
    from remote_site.phantom.phantom import PixelGrid

    world = build_world("breast", 4)
    assert world.registration.yaw_deg != 0.0
    grid = PixelGrid(width_px=320, height_px=240, mm_per_px=0.0634)
    pose = [0.0, 0.0, 5.0]
    provide = world.depth_provider(None, lambda: grid, lambda: pose)  # type: ignore[arg-type]
    above = provide()
    assert above.shape == (240, 320) and not above.any()
    pose[2] = -1.5
    pressed = world.phantom.contact(world.true_pose(pose), grid).depth_map_mm
    assert pressed.any()
    np.testing.assert_array_equal(provide(), _rotate(pressed, world.registration.yaw_deg))
