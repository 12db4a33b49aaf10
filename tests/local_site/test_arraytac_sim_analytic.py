"""ArrayTac simulator against closed-form references: plant step, stiffness law, equilibria."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from local_site.arraytac_sim import ArrayTacPlant, PlantParams
from local_site.arraytac_sim.sensor import HallSensor
from local_site.arraytac_sim.stiffness import (
    equilibrium_force_n,
    equivalent_stiffness_n_per_mm,
    feedforward_voltage_v,
    u_limit_v,
)

P = PlantParams()
Y_LIM_K = {k: P.lever_gain_mm_per_v * (float(u_limit_v(k, P.u_base_v, P.u_max_v)) - P.u_base_v)
           for k in (0.5, 0.75, 1.0)}


def _two_pole_step(t: np.ndarray, gain_mm: float) -> np.ndarray:
    td, tm = P.driver_time_constant_s, P.mech_time_constant_s
    return gain_mm * (1 - (td * np.exp(-t / td) - tm * np.exp(-t / tm)) / (td - tm))


@pytest.mark.parametrize(("integrator", "substeps", "tol_mm"),
                         [("zoh", 1, 1e-9), ("rk4", 1, 1e-6), ("euler", 4, 2e-3)])
def test_open_loop_step_matches_closed_form(integrator: str, substeps: int,
                                            tol_mm: float) -> None:
    """A 2 V open-loop step (below the slew limits) against the two-pole solution."""
    plant = ArrayTacPlant(n_units=1, integrator=integrator, substeps=substeps)
    u0 = 60.0
    plant.set_drive_override(u0)
    plant.advance(0.5)
    y0 = float(plant.true_position_mm[0])
    assert y0 == pytest.approx(P.lever_gain_mm_per_v * (u0 - P.u_base_v), rel=1e-6)
    plant.set_drive_override(u0 + 2.0)
    tr = plant.run(0.05)
    t = tr.time_s - tr.time_s[0]
    expected = y0 + _two_pole_step(t, 2.0 * P.lever_gain_mm_per_v)
    assert np.abs(tr.true_position_mm[:, 0] - expected).max() < tol_mm


def test_slew_limited_ramp_rate() -> None:
    """A full open-loop voltage step ramps the driver at exactly the slew limits."""
    plant = ArrayTacPlant(n_units=1)
    plant.set_drive_override(P.u_max_v)
    tr = plant.run(0.002)
    rate = np.diff(tr.drive_voltage_v[:, 0]) / P.control_period_s
    assert rate[1:10] == pytest.approx(P.slew_up_v_per_s, rel=1e-9)
    plant.advance(0.02)                     # settle at U_max
    plant.set_drive_override(P.u_base_v)
    tr = plant.run(0.002)
    rate = np.diff(tr.drive_voltage_v[:, 0]) / P.control_period_s
    assert rate[1:10] == pytest.approx(-P.slew_down_v_per_s, rel=1e-9)


def test_hall_calibration_is_a_good_cubic() -> None:
    sensor = HallSensor(P)
    assert sensor.r_squared > 0.997                     # paper: R^2 > 0.997 on all units
    y = np.linspace(0, 5, 501)
    assert np.abs(sensor.calibration_residual_mm(y)).max() < 0.05
    assert sensor.calibration_residual_mm(y).std() > 1e-4   # the fit is not trivially exact


def test_u_limit_formula() -> None:
    for k in (0.5, 0.6, 0.75, 1.0):
        direct = (k + 4) / 5 * (P.u_max_v - P.u_base_v) + P.u_base_v
        assert float(u_limit_v(k, P.u_base_v, P.u_max_v)) == pytest.approx(direct)
    assert float(u_limit_v(1.0, P.u_base_v, P.u_max_v)) == pytest.approx(P.u_max_v)


@settings(max_examples=200, deadline=None)
@given(k=st.floats(0.5, 1.0), e=st.floats(0.0, 5.0))
def test_stiffness_law_properties(k: float, e: float) -> None:
    ulim = float(u_limit_v(k, P.u_base_v, P.u_max_v))
    ylim = P.lever_gain_mm_per_v * (ulim - P.u_base_v)
    u = float(feedforward_voltage_v(e, k, ulim, P.u_base_v, ylim))
    direct = (ulim - P.u_base_v) * (1 - (1 - k) * e / ylim) ** 2 + P.u_base_v  # Eq. (2)
    assert u == pytest.approx(direct, rel=1e-12, abs=1e-9)
    assert P.u_base_v <= u <= ulim + 1e-9
    keff = float(equivalent_stiffness_n_per_mm(e, k, ylim, P.passive_stiffness_n_per_mm))
    assert math.isfinite(keff) and keff >= -1e-12          # Eq. (S12), boundary at k = 0.5
    if k > 0.5 + 1e-9:
        assert keff > 0
    # K_eff is dF/de: compare with a central difference of the equilibrium force
    h = 1e-5
    f_plus = equilibrium_force_n(e + h, k, 3.0, ylim, P.passive_stiffness_n_per_mm)
    f_minus = equilibrium_force_n(max(e - h, 0.0), k, 3.0, ylim, P.passive_stiffness_n_per_mm)
    fd = float((f_plus - f_minus) / (e + h - max(e - h, 0.0)))
    assert fd == pytest.approx(keff, abs=1e-6)


@settings(max_examples=100, deadline=None)
@given(k1=st.floats(0.5, 1.0), k2=st.floats(0.5, 1.0), e=st.floats(0.0, 3.0))
def test_equivalent_stiffness_increases_with_k_and_compression(k1: float, k2: float,
                                                               e: float) -> None:
    lo, hi = sorted((k1, k2))

    def keff(k: float, ee: float) -> float:
        ylim = P.lever_gain_mm_per_v * (float(u_limit_v(k, P.u_base_v, P.u_max_v)) - P.u_base_v)
        return float(equivalent_stiffness_n_per_mm(ee, k, ylim, P.passive_stiffness_n_per_mm))

    assert keff(hi, e) >= keff(lo, e) - 1e-12
    assert keff(lo, e + 0.1) >= keff(lo, e) - 1e-12          # Eq. (S21): dK/de >= 0


@pytest.mark.parametrize("k", [0.625, 0.75, 0.875])
def test_simulated_equilibrium_matches_stiffness_law(k: float) -> None:
    """Settled region-B compression under a finger force solves the static law."""
    forces = np.array([2.0, 2.2, 2.4])
    plant = ArrayTacPlant(n_units=3)
    plant.set_targets(np.full(3, 3.0), k, 0.0)
    plant.advance(0.2)
    plant.set_finger_force(forces)
    tr = plant.run(0.4)
    assert plant.saturated.all()
    e_meas = 3.0 - tr.position_mm[-200:].mean(axis=0)
    ylim = P.lever_gain_mm_per_v * (float(u_limit_v(k, P.u_base_v, P.u_max_v)) - P.u_base_v)
    y_true = tr.true_position_mm[-200:].mean(axis=0)
    y_cmd = ylim * (1 - (1 - k) * e_meas / ylim) ** 2
    force_model = P.passive_stiffness_n_per_mm * (y_cmd - y_true)
    assert force_model == pytest.approx(forces, abs=2e-3)
