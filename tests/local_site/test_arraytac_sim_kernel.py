"""The compiled (numba) engine against the numpy reference engine: identical trajectories."""

from __future__ import annotations

import sys
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import local_site.arraytac_sim as arraytac_sim
from local_site.arraytac_sim import ArrayTacPlant, PlantTrace
from shared.errors import ConfigError

TOL_MM = 1e-9
TOL_V = 1e-7   # voltages are ~100 V: 1e-9 relative


def _pair(**kwargs: object) -> tuple[ArrayTacPlant, ArrayTacPlant]:
    """(compiled, numpy per-step reference) plants with the same options."""
    return (ArrayTacPlant(engine="numba", **kwargs),  # type: ignore[arg-type]
            ArrayTacPlant(engine="numpy", fast_path=False, **kwargs))  # type: ignore[arg-type]


def _assert_same(a: PlantTrace, b: PlantTrace) -> None:
    np.testing.assert_array_equal(a.time_s, b.time_s)
    np.testing.assert_allclose(a.position_mm, b.position_mm, rtol=0, atol=TOL_MM)
    np.testing.assert_allclose(a.true_position_mm, b.true_position_mm, rtol=0, atol=TOL_MM)
    np.testing.assert_allclose(a.reference_mm, b.reference_mm, rtol=0, atol=TOL_MM)
    np.testing.assert_allclose(a.drive_voltage_v, b.drive_voltage_v, rtol=0, atol=TOL_V)


def _run_both(script: Callable[[ArrayTacPlant], list[PlantTrace]], **kwargs: object) -> None:
    fast, ref = _pair(**kwargs)
    traces_fast, traces_ref = script(fast), script(ref)
    assert len(traces_fast) == len(traces_ref) > 0
    for a, b in zip(traces_fast, traces_ref, strict=True):
        _assert_same(a, b)
    np.testing.assert_array_equal(fast.saturated, ref.saturated)
    assert fast.vibration_ticks == ref.vibration_ticks
    assert fast.time_s == ref.time_s


def _step(plant: ArrayTacPlant) -> list[PlantTrace]:
    plant.set_targets(np.linspace(0.5, 4.5, plant.n_units), 1.0, 0.0)
    first = plant.run(0.06)
    plant.set_targets(np.linspace(4.5, 0.5, plant.n_units), 0.8, 0.0)
    return [first, plant.run(0.06)]


def _sine(plant: ArrayTacPlant) -> list[PlantTrace]:
    plant.set_targets(np.full(plant.n_units, 2.5), 1.0, 0.0)
    plant.advance(0.05)
    plant.set_test_signal(0.3, np.linspace(10.0, 400.0, plant.n_units))
    return [plant.run(0.05)]


def _friction(plant: ArrayTacPlant) -> list[PlantTrace]:
    n = plant.n_units
    plant.set_targets(np.full(n, 2.0), 1.0, np.linspace(0.0, 1.0, n))
    return [plant.run(0.05)]


def _finger_load(plant: ArrayTacPlant) -> list[PlantTrace]:
    """Region A, region B (stiffness stage 2 saturated), release."""
    n = plant.n_units
    plant.set_targets(np.full(n, 3.0), np.linspace(0.5, 1.0, n), 0.0)
    plant.advance(0.1)
    out = []
    for force in (1.0, 2.5, 4.0, 0.0):
        plant.set_finger_force(np.full(n, force))
        out.append(plant.run(0.08))
    return out


def _open_loop(plant: ArrayTacPlant) -> list[PlantTrace]:
    plant.set_drive_override(60.0)
    first = plant.run(0.02)
    plant.set_drive_override(150.0, 5.0, 40.0)          # slew-limited rise
    second = plant.run(0.02)
    plant.set_drive_override(None)                        # bumpless return to the PID
    plant.set_targets(1.0, 1.0, 0.0)
    return [first, second, plant.run(0.03)]


@pytest.mark.parametrize("script", [_step, _sine, _friction, _finger_load, _open_loop],
                         ids=["step", "sine", "friction", "finger_load", "open_loop"])
def test_scenarios_match_reference(script: Callable[[ArrayTacPlant], list[PlantTrace]]) -> None:
    _run_both(script, n_units=16)


@pytest.mark.parametrize(("integrator", "substeps"), [("zoh", 3), ("rk4", 1), ("euler", 4)])
def test_every_integrator_matches_reference(integrator: str, substeps: int) -> None:
    for script in (_step, _finger_load):
        _run_both(script, n_units=4, integrator=integrator, substeps=substeps)


def test_finger_load_really_saturates() -> None:
    """The saturated scenario exercises stiffness stage 2 (the comparison is not vacuous)."""
    plant = ArrayTacPlant(n_units=4)
    traces = _finger_load(plant)
    assert plant.saturated.sum() == 0          # released at the end
    plant.set_finger_force(4.0)
    plant.advance(0.1)
    assert plant.saturated.all()
    assert np.ptp(traces[2].true_position_mm) > 0.3


def test_chunking_does_not_change_the_trajectory() -> None:
    """1-tick, odd-sized and one long advance give the same states (noise drawn in blocks)."""
    finals = []
    for chunk_s in (1e-4, 0.00137, 0.3):
        plant = ArrayTacPlant(n_units=16)
        plant.set_targets(np.linspace(1, 4, 16), 0.7, np.r_[np.zeros(8), np.full(8, 0.5)])
        plant.set_finger_force(np.r_[np.full(4, 3.0), np.zeros(12)])
        while plant.time_s < 0.3 - 1e-9:
            plant.advance(min(chunk_s, 0.3 - plant.time_s))
        finals.append((plant.true_position_mm, plant.position_mm, plant.drive_voltage_v))
    for other in finals[1:]:
        for a, b in zip(finals[0], other, strict=True):
            np.testing.assert_array_equal(a, b)


command = st.tuples(
    st.lists(st.floats(-1.0, 6.0), min_size=3, max_size=3),     # heights (some clamped)
    st.lists(st.floats(0.3, 1.2), min_size=3, max_size=3),      # k (some clamped)
    st.lists(st.sampled_from([0.0, 0.0, 0.3, 1.0, 1.5]), min_size=3, max_size=3),
    st.lists(st.floats(0.0, 6.0), min_size=3, max_size=3),      # finger force
    st.integers(1, 150),                                         # ticks to run
)


@settings(max_examples=30, deadline=None)
@given(commands=st.lists(command, min_size=1, max_size=6))
def test_random_commands_match_reference(
        commands: list[tuple[list[float], list[float], list[float], list[float], int]]) -> None:
    fast, ref = _pair(n_units=3)
    for height, k, f, force, ticks in commands:
        for plant in (fast, ref):
            plant.set_targets(np.array(height), np.array(k), np.array(f))
            plant.set_finger_force(np.array(force))
        _assert_same(fast.run(ticks * 1e-4), ref.run(ticks * 1e-4))
        np.testing.assert_array_equal(fast.saturated, ref.saturated)


def test_missing_numba_is_a_clear_config_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "numba", None)         # import numba -> ImportError
    monkeypatch.delitem(sys.modules, "local_site.arraytac_sim.kernel", raising=False)
    monkeypatch.delattr(arraytac_sim, "kernel", raising=False)
    with pytest.raises(ConfigError, match="numba"):
        ArrayTacPlant(engine="numba")
    ArrayTacPlant(engine="numpy").advance(0.001)            # the reference needs no numba
