"""Loading-only streaming over a simulated arm, the stiffness map, the Shore 00 conversion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.arm.sim import SimArm, SimArmConfig
from remote_site.phantom import SensorPad, SiliconeLayer, make_scene
from remote_site.phantom.durometer import durometer_modulus_kpa
from remote_site.phantom.mechanics import punch_modulus_kpa, punch_stiffness_n_per_mm
from remote_site.phantom.reference_presses import sim_stiffness_calibration
from remote_site.stiffness import MapBounds, StiffnessConfig, StiffnessMap, StiffnessTracker
from shared.errors import ConfigError, InputDataError
from shared.hardness import StiffnessShoreCurve

#: the simulated pad's true gel (a station reads it from its stiffness calibration)
SIM_CFG = StiffnessConfig(gel_stiffness_n_per_mm=SensorPad().gel_stiffness_n_per_mm)


def test_sim_arm_presses_give_one_estimate_each_from_loading_only() -> None:
    ph = make_scene("breast", 4)
    arm = SimArm(ph, SimArmConfig(realtime=False, force_noise_n=0.02, seed=1))
    arm.connect()
    tracker = StiffnessTracker(SIM_CFG)
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
        StiffnessTracker(SIM_CFG).update(0.0, (0.0, float("nan"), 0.0), 1.0)
    with pytest.raises(InputDataError):
        StiffnessTracker(SIM_CFG).update(0.0, (0.0, 0.0, 0.0), float("inf"))


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


def test_a_map_of_more_than_a_million_cells_is_refused() -> None:
    from remote_site.stiffness.stiffness_map import MAX_CELLS

    assert MAX_CELLS == 1_000_000
    assert MapBounds(0, 100, 0, 100, 0.1).shape == (1000, 1000)  # the most: 24 MB
    for cell_mm in (0.0999, 1e-300):  # (1e-300: cells beyond any float, no OverflowError)
        with pytest.raises(ConfigError, match=r"^a stiffness map of 100 x 100 mm in cells of "
                                              r".+ mm would hold .+ cells, more than "
                                              r"1,000,000: the cells must be larger "
                                              r"\(remote\.agent\.stiffness_cell_mm\)$"):
            MapBounds(0, 100, 0, 100, cell_mm)
    # counted as the map is made, each side rounded up: 1001 x 1000 (a review)
    with pytest.raises(ConfigError, match=r"would hold 1,001,000 cells"):
        MapBounds(0, 99.95, 0, 100.04, 0.1)


@settings(max_examples=50, deadline=None)
@given(points=st.lists(st.tuples(st.floats(-12, 12), st.floats(-12, 12), st.floats(0, 50)),
                       max_size=40),
       rows=st.lists(st.integers(0, 9), min_size=1, max_size=6),
       cols=st.lists(st.integers(0, 9), min_size=1, max_size=6))
def test_the_mean_at_some_cells_is_the_whole_map_s_there(
        points: list[tuple[float, float, float]], rows: list[int], cols: list[int]) -> None:
    m = StiffnessMap(MapBounds(-10, 10, -10, 10, 2.0))
    for x, y, k in points:
        m.add(x, y, k)
    r, c = np.asarray(rows)[:, None], np.asarray(cols)[None, :]
    np.testing.assert_array_equal(m.mean_at(r, c), m.mean_n_per_mm()[r, c])


def test_durometer_model_round_trip_and_monotone() -> None:
    """The simulated probe's calibration inverts the simulator's physics (punch + durometer)."""
    to_k = sim_stiffness_calibration().stiffness_to_k()
    pad_radius_mm, thickness_mm = SensorPad().effective_radius_mm, SiliconeLayer().thickness_mm
    shore = np.linspace(1, 99, 50)
    mod = durometer_modulus_kpa(shore)
    assert np.all(np.diff(mod) > 0)
    k = punch_stiffness_n_per_mm(mod, pad_radius_mm, thickness_mm)
    np.testing.assert_allclose(to_k.shore00(k), shore, atol=0.05)
    # stiffness -> modulus inverts the punch model exactly
    k80 = punch_stiffness_n_per_mm(80.0, pad_radius_mm, thickness_mm)
    assert punch_modulus_kpa(k80, pad_radius_mm, thickness_mm) == pytest.approx(80.0)


@settings(max_examples=100, deadline=None)
@given(k=st.floats(0.0, 1e5))
def test_display_k_is_clamped_and_monotone(k: float) -> None:
    to_k = sim_stiffness_calibration().stiffness_to_k()
    kd = float(to_k.k(k))
    assert 0.5 <= kd <= 1.0
    assert 0.0 <= float(to_k.shore00(k)) <= 100.0
    assert float(to_k.k(k * 1.5 + 0.1)) >= kd


def test_shore_conversion_rejects_bad_values() -> None:
    to_k = sim_stiffness_calibration().stiffness_to_k()
    with pytest.raises(InputDataError):
        to_k.shore00(float("nan"))
    with pytest.raises(InputDataError):
        durometer_modulus_kpa(100.0)
    with pytest.raises(ConfigError):
        StiffnessShoreCurve(((1.0, 50.0), (2.0, 40.0)))
