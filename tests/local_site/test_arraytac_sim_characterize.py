"""Measured simulator figures against the paper's (Fig. 2D-F, Fig. 8D), design, CLI."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from lab.cli import main
from local_site.arraytac_sim import PlantParams
from local_site.arraytac_sim.characterize import (
    PAPER_FIGURES,
    measure_force_displacement,
    measure_frequency_response,
    measure_step,
    measure_transfer_bandwidths,
)
from local_site.arraytac_sim.design import (
    DesignTargets,
    design_linear,
    refine_for_sampling,
    second_order_bandwidth_ratio,
)


def test_step_response_matches_paper() -> None:
    step = measure_step()
    assert step.rise_time_s == pytest.approx(PAPER_FIGURES["rise_time_s"], rel=0.2)
    assert step.fall_time_s == pytest.approx(PAPER_FIGURES["fall_time_s"], rel=0.2)
    assert step.fall_time_s > step.rise_time_s                # the asymmetry of Fig. 2D
    assert step.overshoot_pct < 0.1 and step.undershoot_pct < 0.1
    assert abs(step.steady_state_error_mm) < 2e-4
    assert abs(step.true_steady_state_error_mm) < 0.05      # cubic-fit residual only


def test_bandwidths_match_paper_and_sweep_agrees() -> None:
    fr = measure_frequency_response(quick=True)
    assert fr.open_loop_bandwidth_hz == pytest.approx(15.29, rel=0.1)
    assert fr.closed_loop_bandwidth_hz == pytest.approx(123.39, rel=0.1)
    assert fr.closed_loop_bandwidth_hz > 8 * fr.open_loop_bandwidth_hz   # "eight-fold"
    # bandwidth is the min of -3 dB and -90 deg; here the -3 dB point limits both
    assert fr.open_loop_minus3db_hz < fr.open_loop_minus90deg_hz
    assert fr.closed_loop_minus3db_hz < fr.closed_loop_minus90deg_hz
    # the sine sweep cross-checks the transfer function
    assert fr.sweep_open_loop_bandwidth_hz == pytest.approx(fr.open_loop_bandwidth_hz, rel=0.06)
    assert fr.sweep_closed_loop_bandwidth_hz == pytest.approx(fr.closed_loop_bandwidth_hz,
                                                              rel=0.06)


def test_mistuned_plant_fails_the_targets() -> None:
    """The measurement is not a tautology: a slower plant measures slower."""
    slow = PlantParams(mech_time_constant_s=0.02)
    ol_hz, _cl_hz = measure_transfer_bandwidths(slow)
    assert ol_hz < 0.6 * 15.29
    assert measure_step(PlantParams(slew_up_v_per_s=5000.0)).rise_time_s > 1.3 * 0.013


def test_force_displacement_is_biphasic_and_ordered() -> None:
    curves = measure_force_displacement(quick=True)
    slopes = [c.region_b_stiffness_n_per_mm for c in curves]
    yields = [c.yield_force_n for c in curves]
    assert all(math.isfinite(s) and s > 0 for s in slopes)
    assert all(b > a for a, b in itertools.pairwise(slopes))
    assert all(b >= a for a, b in itertools.pairwise(yields)) and yields[-1] > yields[0]
    for c in curves:  # region A: no compression below the yield force, then it grows
        comp = np.asarray(c.compression_mm)
        force = np.asarray(c.force_n)
        assert np.all(comp[force <= c.yield_force_n] < 0.02)
        assert np.all(np.diff(comp) > -1e-3)
        assert comp[-1] > 0.1


def test_closed_form_design_satisfies_its_equations() -> None:
    t = DesignTargets()
    p = design_linear(t)
    wn = 1.0 / (2 * t.damping * p.driver_time_constant_s)
    f3 = wn * second_order_bandwidth_ratio(t.damping) / (2 * math.pi)
    assert f3 == pytest.approx(t.closed_loop_bandwidth_hz, rel=1e-12)
    w = 2 * math.pi * t.open_loop_bandwidth_hz
    gain2 = 1 / ((1 + (w * p.driver_time_constant_s) ** 2)
                 * (1 + (w * p.mech_time_constant_s) ** 2))
    assert gain2 == pytest.approx(0.5, rel=1e-12)
    assert p.ki_v_per_mm_s * p.mech_time_constant_s == pytest.approx(p.kp_v_per_mm)


def test_defaults_are_the_derived_design() -> None:
    t = DesignTargets()
    derived = refine_for_sampling(design_linear(t), t)
    d = PlantParams()
    for name in ("mech_time_constant_s", "driver_time_constant_s", "kp_v_per_mm",
                 "ki_v_per_mm_s"):
        assert getattr(d, name) == pytest.approx(getattr(derived, name), rel=1e-3), name


def test_cli_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["display", "characterize", "--quick", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("open_loop_bandwidth_hz", "closed_loop_bandwidth_hz", "rise_time_s",
                "fall_time_s", "overshoot_pct", "steady_state_error_mm", "force_displacement"):
        assert key in out
    assert [c["k"] for c in out["force_displacement"]] == [0.5, 0.625, 0.75, 0.875, 1.0]
