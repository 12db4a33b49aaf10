"""Arm <-> phantom registration: the rigid fit, the bead finder and the whole procedure."""

from __future__ import annotations

import cmath
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.agent.world import REALISTIC, Registration, world_for
from remote_site.arm.base import ArmLimits
from remote_site.arm.sim import SimArm, SimArmConfig
from remote_site.cli import parse_fiducials
from remote_site.phantom import make_scene
from remote_site.phantom.phantom_file import phantom_from_dict
from remote_site.reconstruction.reconstructor import Reconstructor
from remote_site.registration import (
    MAX_YAW_DEG,
    RegistrationEstimate,
    _arc,
    _consistent,
    calibrate_with_fiducials,
    fit_registration,
    guarded,
    locate_bump,
)
from remote_site.sensor.sim_calibration import simulated_calibration
from remote_site.sensor.simulator import SimulatedSensor
from shared.errors import CalibrationError, ConfigError, InputDataError
from shared.workspace import WorkspaceMap

CORNERS = np.array([[-42.0, 0.0], [0.0, -42.0], [42.0, 0.0], [0.0, 42.0]])


@settings(max_examples=50, deadline=None)
@given(st.floats(-5, 5), st.floats(-5, 5), st.floats(-10, 10))
def test_fit_recovers_an_exact_rigid_motion(dx: float, dy: float, yaw: float) -> None:
    # reference: complex numbers; the arm sees the phantom point q at a = (q - d) / e^{i yaw}
    rot = cmath.exp(1j * math.radians(yaw))
    arm = [(q - complex(dx, dy)) / rot for q in (complex(*c) for c in CORNERS)]
    est = fit_registration([(a.real, a.imag) for a in arm], CORNERS)
    assert est.dx_mm == pytest.approx(dx, abs=1e-9)
    assert est.dy_mm == pytest.approx(dy, abs=1e-9)
    assert est.yaw_deg == pytest.approx(yaw, abs=1e-9)
    assert est.residual_rms_mm == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(est.arm_to_phantom([(a.real, a.imag) for a in arm]), CORNERS,
                               atol=1e-9)
    # the platform -> arm map reaches the designed phantom point on the real phantom
    ws = WorkspaceMap()
    to_arm = est.workspace_to_arm(ws)
    p = [12.0, 47.0, 40.0]
    a = to_arm.forward_unclamped(p)
    np.testing.assert_allclose(est.arm_to_phantom(a[:2]), ws.forward_unclamped(p)[:2],
                               atol=1e-9)


def test_uncertainty_matches_the_scatter_of_noisy_fits() -> None:
    rng = np.random.default_rng(3)
    sigma = 0.2
    fits = [fit_registration(CORNERS + rng.normal(0, sigma, CORNERS.shape), CORNERS)
            for _ in range(400)]
    dx = np.array([f.dx_mm for f in fits])
    yaw = np.array([f.yaw_deg for f in fits])
    # independent reference: for n points at radius r the LS translation std is
    # sigma / sqrt(n), the angle std sigma / (r sqrt(n))
    r = 42.0
    assert dx.std() == pytest.approx(sigma / 2.0, rel=0.15)
    assert yaw.std() == pytest.approx(math.degrees(sigma / (r * 2.0)), rel=0.15)
    # the reported std, averaged, agrees with the scatter within the estimate's own noise
    assert np.mean([f.std_dx_mm for f in fits]) == pytest.approx(dx.std(), rel=0.3)
    assert np.mean([f.std_yaw_deg for f in fits]) == pytest.approx(yaw.std(), rel=0.3)


def test_fit_refuses_bad_input() -> None:
    with pytest.raises(InputDataError, match="at least 2"):
        fit_registration([[0.0, 0.0]], [[1.0, 1.0]])
    with pytest.raises(InputDataError, match="equal shape"):
        fit_registration(CORNERS, CORNERS[:3])
    with pytest.raises(InputDataError, match="finite"):
        fit_registration([[0.0, np.nan], [1.0, 1.0]], [[0.0, 0.0], [1.0, 1.0]])
    with pytest.raises(InputDataError, match="one place"):
        fit_registration([[1.0, 1.0], [1.0, 1.0]], [[0.0, 0.0], [1.0, 1.0]])


@settings(max_examples=30, deadline=None)
@given(st.floats(-4, 4), st.floats(-3, 3))
def test_bump_is_found_where_it_is_on_a_pad_plateau(ox: float, oy: float) -> None:
    pitch = 0.5
    ys, xs = np.mgrid[0:30, 0:40]
    x = (xs - 19.5) * pitch
    y = (ys - 14.5) * pitch
    plateau = 0.3 * np.clip((7.0 - np.hypot(x, y)) / 1.0 + 0.5, 0, 1)
    bump = 0.08 * np.exp(-((x - ox) ** 2 + (y - oy) ** 2) / (2 * 0.8 ** 2))
    fx, fy = locate_bump(plateau + bump, pitch)
    assert fx == pytest.approx(ox, abs=0.15) and fy == pytest.approx(oy, abs=0.15)


def test_no_bump_is_an_error() -> None:
    with pytest.raises(InputDataError, match="no bump"):
        locate_bump(np.zeros((30, 40)), 0.5)
    with pytest.raises(InputDataError, match="finite 2-D"):
        locate_bump(np.zeros(5), 0.5)
    with pytest.raises(InputDataError, match="pitch"):
        locate_bump(np.ones((30, 40)), 0.0)


def _register(registration: Registration, seed: int, scene: str = "breast",
              **options: Any) -> RegistrationEstimate:
    """Run the procedure on a simulated scene placed with ``registration``."""
    world = world_for(make_scene(scene, seed), REALISTIC, seed, registration)
    arm = SimArm(config=SimArmConfig(realtime=False, loop_hz=250.0), limits=ArmLimits(),
                 **world.arm_options())
    holder: list[SimulatedSensor] = []
    sensor = SimulatedSensor(**world.sensor_options(arm, lambda: holder[0]))
    holder.append(sensor)
    arm.connect()
    sensor.connect()
    try:
        return calibrate_with_fiducials(guarded(arm), sensor,
                                        Reconstructor(simulated_calibration()),
                                        [f.center_mm for f in world.phantom.fiducials],
                                        wait=arm.advance, **options)
    finally:
        sensor.disconnect()
        arm.disconnect()


@pytest.mark.parametrize(("seed", "registration"), [
    (11, Registration(2.0, -1.5, 0.1, 3.0)),
    (12, Registration(2.0, -1.5, 0.1, -4.0)),
    # the OOD benchmark's seed 15004 draws a 13.1 deg turn: the search used to find one
    # fiducial, take the phantom's edge for a second and report 14 mm off as +-1 mm
    (15004, Registration(-2.38, 0.82, 0.25, 13.1)),
    (15004, Registration(-2.38, 0.82, 0.25, -13.1)),
    # shifted 8 mm and turned 10 deg: the first bead felt is not a fiducial (every later one
    # disagreed with it, and the search used to give up with one found)
    (7, Registration(6.0, -5.0, 0.25, 10.0)),
    (8, Registration(6.0, -5.0, 0.25, -MAX_YAW_DEG)),
])
def test_procedure_measures_the_hidden_registration(seed: int,
                                                    registration: Registration) -> None:
    est = _register(registration, seed)
    assert est.fiducials == 4
    assert abs(est.dx_mm - registration.dx_mm) < 4 * est.std_dx_mm + 0.1
    assert abs(est.dy_mm - registration.dy_mm) < 4 * est.std_dy_mm + 0.1
    assert abs(est.yaw_deg - registration.yaw_deg) < 4 * est.std_yaw_deg + 0.1
    # after registration a workspace-edge point is placed to well under a millimetre
    corner = np.array([30.0, 30.0])
    err = np.linalg.norm(est.arm_to_phantom(corner)
                         - np.array(registration.to_phantom((*corner, 0))[:2]))
    assert err < 1.0


def test_the_search_gives_up_after_its_press_budget() -> None:
    with pytest.raises(CalibrationError, match="gave up after 8 presses"):
        _register(Registration(1.0, 1.0, 0.1, 45.0), 3, max_presses=2)


def test_a_phantom_turned_beyond_the_search_is_refused_not_misregistered() -> None:
    with pytest.raises(CalibrationError, match="fiducials found, 3 needed"):
        _register(Registration(1.0, 1.0, 0.1, 45.0), 3)


@settings(max_examples=60, deadline=None)
@given(dx=st.floats(-8, 8), dy=st.floats(-8, 8), yaw=st.floats(-MAX_YAW_DEG, MAX_YAW_DEG),
       spacing=st.floats(2.0, 6.0))
def test_the_arc_passes_within_half_its_spacing_of_a_turned_fiducial(
        dx: float, dy: float, yaw: float, spacing: float) -> None:
    rot = cmath.exp(-1j * math.radians(yaw))
    arm = [complex(*q) - complex(dx, dy) for q in CORNERS]
    arm = [a * rot for a in arm]  # a = R(-yaw) (q - d)
    arc = _arc((arm[0].real, arm[0].imag), tuple(CORNERS[0]), tuple(CORNERS[2]),
               MAX_YAW_DEG, spacing)
    gap = min(abs(complex(*xy) - arm[2]) for xy in arc)
    assert gap <= spacing / 2.0 + 1e-6
    # yaw 0 first: the design offset from the fiducial found, unturned
    first = complex(*arc[0]) - arm[0]
    assert first == pytest.approx(complex(*(CORNERS[2] - CORNERS[0])))


@settings(max_examples=60, deadline=None)
@given(dx=st.floats(-8, 8), dy=st.floats(-8, 8), yaw=st.floats(-30, 30),
       false_hits=st.lists(st.tuples(st.integers(0, 3), st.floats(-60, 60), st.floats(-60, 60)),
                           max_size=3),
       order=st.randoms(use_true_random=False))
def test_the_consistent_set_is_the_true_fiducials_among_false_bumps(
        dx: float, dy: float, yaw: float, false_hits: list[tuple[int, float, float]],
        order: object) -> None:
    design = [(float(q[0]), float(q[1])) for q in CORNERS]
    rot = cmath.exp(-1j * math.radians(yaw))
    true = [(i, ((complex(*q) - complex(dx, dy)) * rot)) for i, q in enumerate(design)]
    hits = [(i, (a.real, a.imag)) for i, a in true[:3]]
    for i, x, y in false_hits:
        a = dict(true)[i]
        if abs(complex(x, y) - a) > 3.0:  # a bump elsewhere than the fiducial itself
            hits.append((i, (x, y)))
    order.shuffle(hits)  # type: ignore[attr-defined]
    got = _consistent(hits, design, 1.0)
    assert sorted(got) == [0, 1, 2] or len(got) > 3
    for i in (0, 1, 2):
        assert complex(*got[i]) == pytest.approx(dict(true)[i], abs=1e-9)


def test_procedure_fails_clearly_without_fiducials() -> None:
    healthy = phantom_from_dict({"layer": {"size_mm": [100, 100], "thickness_mm": 20,
                                           "modulus_kpa": 50}})
    world = world_for(healthy, REALISTIC, 1)
    arm = SimArm(config=SimArmConfig(realtime=False, loop_hz=250.0), **world.arm_options())
    holder: list[SimulatedSensor] = []
    sensor = SimulatedSensor(**world.sensor_options(arm, lambda: holder[0]))
    holder.append(sensor)
    arm.connect()
    sensor.connect()
    try:
        with pytest.raises(CalibrationError, match="only 0 of 2 fiducials"):
            calibrate_with_fiducials(guarded(arm), sensor, Reconstructor(simulated_calibration()),
                                     [(0.0, 0.0), (20.0, 0.0)], wait=arm.advance)
    finally:
        sensor.disconnect()
        arm.disconnect()


def test_fiducials_flag() -> None:
    assert parse_fiducials("-42,-42;42,42") == ((-42.0, -42.0), (42.0, 42.0))
    assert parse_fiducials(None) == ()
    for bad in ("1,2", "1;2", "a,b;1,2", "nan,1;2,3"):
        with pytest.raises(ConfigError, match="--fiducials"):
            parse_fiducials(bad)
