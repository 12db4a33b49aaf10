"""ArrayTacPlant: interface, clamping, bad input, stability, fast path vs per-step path."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from local_site.arraytac_sim import ArrayTacPlant, PlantParams
from shared.errors import ConfigError, InputDataError


def test_interface_shapes_and_clamping() -> None:
    plant = ArrayTacPlant()
    plant.set_targets(np.linspace(-1, 7, 16), np.linspace(0, 2, 16), np.linspace(-1, 2, 16))
    h, k, f = plant.commands
    assert h.min() == 0.0 and h.max() == 5.0
    assert k.min() == 0.5 and k.max() == 1.0
    assert f.min() == 0.0 and f.max() == 1.0
    plant.set_finger_force(-3.0)
    plant.advance(0.01)
    for arr in (plant.position_mm, plant.true_position_mm, plant.drive_voltage_v):
        assert arr.shape == (16,) and np.all(np.isfinite(arr))
    assert plant.saturated.dtype == bool and plant.saturated.shape == (16,)
    assert plant.time_s == pytest.approx(0.01)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_commands_rejected(bad: float) -> None:
    plant = ArrayTacPlant()
    h = np.ones(16)
    h[3] = bad
    with pytest.raises(InputDataError):
        plant.set_targets(h, 1.0, 0.0)
    with pytest.raises(InputDataError):
        plant.set_finger_force(bad)
    with pytest.raises(InputDataError):
        plant.advance(bad)
    with pytest.raises(InputDataError):
        plant.set_targets(np.ones(15), 1.0, 0.0)


@pytest.mark.parametrize("engine", ["numba", "numpy"])
def test_rejected_command_changes_nothing(engine: str) -> None:
    plant = ArrayTacPlant(n_units=4, engine=engine)
    plant.set_targets(np.full(4, 2.0), 0.75, 0.5)
    plant.set_finger_force(1.0)
    before = plant.commands
    with pytest.raises(InputDataError):
        plant.set_targets(np.full(4, 3.0), np.array([0.6, np.nan, 0.6, 0.6]), 0.0)
    with pytest.raises(InputDataError):
        plant.set_targets(np.full(4, 3.0), 0.6, float("inf"))
    with pytest.raises(InputDataError):
        plant.set_finger_force(float("nan"))
    for a, b in zip(before, plant.commands, strict=True):
        np.testing.assert_array_equal(a, b)
    plant.set_targets(7.0, 0.2, 3.0)                    # scalars clamp like arrays
    h, k, f = plant.commands
    assert np.all(h == 5.0) and np.all(k == 0.5) and np.all(f == 1.0)


def test_bad_config_rejected() -> None:
    with pytest.raises(ConfigError):
        ArrayTacPlant(integrator="leapfrog")
    with pytest.raises(ConfigError):
        ArrayTacPlant(engine="cython")
    with pytest.raises(ConfigError):
        PlantParams(u_max_v=10.0)
    with pytest.raises(ConfigError):
        PlantParams(kp_v_per_mm=float("nan"))


def test_time_does_not_drift_over_many_small_advances() -> None:
    plant = ArrayTacPlant(n_units=2)
    for _ in range(333):
        plant.advance(0.00033)
    assert plant.time_s == pytest.approx(333 * 0.00033, abs=0.5e-4)


def test_tracks_targets_with_zero_steady_state_error() -> None:
    plant = ArrayTacPlant()
    target = np.linspace(0.5, 4.5, 16)
    plant.set_targets(target, 1.0, 0.0)
    plant.advance(0.3)
    tr = plant.run(0.05)
    assert np.abs(tr.position_mm.mean(axis=0) - target).max() < 2e-4
    # the true height differs only by the cubic calibration's residual
    resid = plant.sensor.calibration_residual_mm(target)
    assert np.abs(tr.true_position_mm.mean(axis=0) + resid - target).max() < 5e-4


def test_fast_path_matches_per_step_path() -> None:
    """The numpy engine's block path against its per-step path (Hall linearisation only)."""
    results = []
    for fast in (True, False):
        plant = ArrayTacPlant(fast_path=fast, engine="numpy")
        plant.set_targets(np.linspace(1, 4, 16), 1.0, 0.0)
        plant.advance(0.3)
        plant.set_targets(np.linspace(1, 4, 16) + 0.01, 1.0, 0.0)
        plant.advance(0.2)
        results.append(plant.true_position_mm)
        if fast:
            assert plant.fast_ticks > 0.5 * (plant.fast_ticks + plant.slow_ticks)
    assert np.abs(results[0] - results[1]).max() < 2e-3


def test_long_run_is_bounded() -> None:
    plant = ArrayTacPlant()
    rng = np.random.default_rng(1)
    for i in range(20):  # 10 s with a new random scene every 0.5 s, loaded every 4th
        plant.set_targets(rng.uniform(0, 5, 16), rng.uniform(0.5, 1, 16),
                          rng.choice([0.0, 1.0], 16) * rng.uniform(0, 1, 16))
        plant.set_finger_force(rng.uniform(0, 4, 16) if i % 4 == 0 else 0.0)
        plant.advance(0.5)
        y = plant.true_position_mm
        assert np.all(np.isfinite(y)) and y.min() >= 0.0 and y.max() <= 5.25
        u = plant.drive_voltage_v
        assert u.min() >= 15.0 - 1e-9 and u.max() <= 150.0 + 1e-9
    assert plant.time_s == pytest.approx(10.0)


def test_friction_off_synthesises_no_vibration() -> None:
    plant = ArrayTacPlant()
    plant.set_targets(np.full(16, 2.0), 1.0, 0.0)
    plant.advance(0.1)
    assert plant.vibration_ticks == 0
    plant.set_targets(np.full(16, 2.0), 1.0, np.r_[np.zeros(15), 1.0])
    tr = plant.run(0.1)
    assert plant.vibration_ticks == 1000
    vib = tr.reference_mm[:, 15] - 2.0
    assert np.abs(vib).max() == pytest.approx(0.2, rel=0.02)   # f = 1: 0.2 mm
    spectrum = np.abs(np.fft.rfft(vib))
    freq = np.fft.rfftfreq(vib.size, 1e-4)
    assert freq[np.argmax(spectrum)] == pytest.approx(200.0, abs=10.0)   # f = 1: 200 Hz
    assert np.all(tr.reference_mm[:, :15] == 2.0)
    assert np.ptp(tr.true_position_mm[-500:, 15]) > 0.1       # the pin really vibrates


def test_finger_load_saturates_and_releases() -> None:
    plant = ArrayTacPlant(n_units=2)
    plant.set_targets(np.full(2, 3.0), np.array([0.5, 1.0]), 0.0)
    plant.advance(0.2)
    plant.set_finger_force(np.array([1.0, 1.0]))       # below both yield forces: region A
    plant.advance(0.3)
    assert not plant.saturated.any()
    assert np.abs(plant.position_mm - 3.0).max() < 5e-3
    plant.set_finger_force(np.array([2.5, 2.5]))       # beyond both: region B
    plant.advance(0.5)
    assert plant.saturated.all()
    comp = 3.0 - plant.true_position_mm
    assert comp[0] > comp[1] > 0.3                     # softer k compresses more
    plant.set_finger_force(0.0)
    plant.advance(0.5)
    assert not plant.saturated.any()
    assert np.abs(plant.position_mm - 3.0).max() < 5e-3


@settings(max_examples=25, deadline=None)
@given(height=st.floats(-10, 10), k=st.floats(-1, 3), f=st.floats(-1, 2),
       force=st.floats(0, 50), duration=st.floats(0, 0.02))
def test_any_command_stays_finite_and_in_range(height: float, k: float, f: float,
                                                force: float, duration: float) -> None:
    plant = ArrayTacPlant(n_units=2)
    plant.set_targets(np.array([height, 5 - height]), k, f)
    plant.set_finger_force(np.array([force, 0.0]))
    plant.advance(duration)
    plant.advance(0.01)
    y = plant.true_position_mm
    assert np.all(np.isfinite(y)) and np.all(np.isfinite(plant.position_mm))
    assert y.min() >= 0.0 and y.max() <= 5.25
