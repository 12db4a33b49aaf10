"""Loading-only streaming over a simulated arm, the stiffness map, the Shore 00 conversion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.arm.sim import SimArm, SimArmConfig
from remote_site.phantom import make_scene
from remote_site.phantom.mechanics import punch_stiffness_n_per_mm
from remote_site.stiffness import (
    MapBounds,
    ShoreConversion,
    StiffnessMap,
    StiffnessTracker,
    durometer_modulus_kpa,
)
from shared.errors import ConfigError, InputDataError


def test_sim_arm_presses_give_one_estimate_each_from_loading_only() -> None:
    ph = make_scene("breast", 4)
    arm = SimArm(ph, SimArmConfig(realtime=False, force_noise_n=0.02, seed=1))
    arm.connect()
    tracker = StiffnessTracker()
    spots = [(-20.0, 10.0), (5.0, -15.0), tuple(ph.ground_truth()["tumors"][0]["center_mm"])]
    results = []
    for x, y in spots:
        for target, dur in (((x, y, 2.0), 0.6), ((x, y, -3.0), 1.0), ((x, y, -3.0), 0.3),
                            ((x, y, 2.0), 0.6)):
            arm.move_to(target)
            arm.advance(dur)
            for t, px, py, pz, f in arm.drain_samples():
                r = tracker.update(t, (px, py, pz), f)
                if r is not None:
                    results.append(r)
    last = tracker.flush()
    if last is not None:
        results.append(last)
    valid = [r for r in results if r.estimate.valid]
    assert len(valid) == 3
    for r, (x, y) in zip(valid, spots, strict=True):
        assert math.hypot(r.x_mm - x, r.y_mm - y) < 0.1
        k_true = ph.tissue_stiffness_n_per_mm(x, y)
        assert r.estimate.k_tissue_n_per_mm == pytest.approx(k_true, rel=0.05)
    # travel, dwell and unloading were skipped
    assert tracker.skipped > tracker.used > 0


def test_tracker_rejects_nan() -> None:
    with pytest.raises(InputDataError):
        StiffnessTracker().update(0.0, (0.0, float("nan"), 0.0), 1.0)
    with pytest.raises(InputDataError):
        StiffnessTracker().update(0.0, (0.0, 0.0, 0.0), float("inf"))


def test_stiffness_map_statistics() -> None:
    m = StiffnessMap(MapBounds(-10, 10, -10, 10, 2.0))
    assert m.count.shape == (10, 10)
    for k in (1.0, 2.0, 3.0):
        assert m.add(0.5, 0.5, k)
    assert not m.add(50.0, 0.0, 1.0)
    assert m.value(0.9, 1.9) == pytest.approx(2.0)
    assert m.value(-5.0, -5.0) is None
    row, col = m.cell_of(0.5, 0.5)  # type: ignore[misc]
    assert m.std_n_per_mm()[row, col] == pytest.approx(1.0)
    conf = m.confidence()
    assert 0 < conf[row, col] < 1 and conf.sum() == conf[row, col]
    xs, ys = m.cell_centers_mm()
    assert xs[col] == pytest.approx(1.0) and ys[row] == pytest.approx(1.0)
    with pytest.raises(InputDataError):
        m.add(0.0, 0.0, float("nan"))
    with pytest.raises(ConfigError):
        MapBounds(0, 0, 0, 1)


def test_durometer_model_round_trip_and_monotone() -> None:
    conv = ShoreConversion()
    shore = np.linspace(1, 99, 50)
    mod = durometer_modulus_kpa(shore)
    assert np.all(np.diff(mod) > 0)
    np.testing.assert_allclose(conv.shore00_from_modulus(mod), shore, atol=0.05)
    # stiffness -> modulus inverts the punch model exactly
    k = punch_stiffness_n_per_mm(80.0, conv.pad_radius_mm, conv.layer_thickness_mm)
    assert conv.modulus_kpa(k) == pytest.approx(80.0)


@settings(max_examples=100, deadline=None)
@given(k=st.floats(0.0, 1e5))
def test_display_k_is_clamped_and_monotone(k: float) -> None:
    conv = ShoreConversion()
    kd = float(conv.display_k(k))
    assert 0.5 <= kd <= 1.0
    assert 0.0 <= float(conv.shore00(k)) <= 100.0
    assert float(conv.display_k(k * 1.5 + 0.1)) >= kd


def test_shore_conversion_rejects_bad_values() -> None:
    conv = ShoreConversion()
    with pytest.raises(InputDataError):
        conv.shore00(float("nan"))
    with pytest.raises(InputDataError):
        durometer_modulus_kpa(100.0)
    with pytest.raises(ConfigError):
        ShoreConversion(spring_full_n=0.1)
