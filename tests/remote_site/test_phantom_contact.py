"""Phantom contact model: analytic checks, consistency, scenes and bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from remote_site.phantom import Phantom, PixelGrid, SensorPad, SiliconeLayer, Tumor, make_scene
from remote_site.phantom.mechanics import (
    depth_weight_integral,
    punch_modulus_kpa,
    punch_stiffness_n_per_mm,
    thin_layer_correction,
)
from shared.errors import ConfigError, InputDataError

SMALL_GRID = PixelGrid(80, 60, 0.25)


def test_depth_weight_integral_matches_quadrature() -> None:
    a = 7.0
    for z in (0.0, 0.5, 3.0, 10.0, 40.0):
        ref, _ = quad(lambda t: 1.0 - t ** 3 / (a * a + t * t) ** 1.5, 0.0, z)
        assert depth_weight_integral(z, a) == pytest.approx(ref, abs=1e-9)
    assert depth_weight_integral(1e9, a) == pytest.approx(2 * a, rel=1e-7)


def test_punch_formula_half_space_and_inverse() -> None:
    # half-space limit: k = 8/3 a E (E in N/mm^2)
    assert punch_stiffness_n_per_mm(30.0, 5.0, np.inf) == pytest.approx(8 / 3 * 5.0 * 0.03)
    assert thin_layer_correction(5.0, 10.0) > 1.0
    k = punch_stiffness_n_per_mm(55.0, 7.0, 20.0)
    assert punch_modulus_kpa(k, 7.0, 20.0) == pytest.approx(55.0)
    with pytest.raises(InputDataError):
        punch_stiffness_n_per_mm(float("nan"), 7.0, 20.0)


def test_homogeneous_phantom_matches_analytic_punch() -> None:
    layer = SiliconeLayer(modulus_kpa=40.0, thickness_mm=15.0)
    pad = SensorPad()
    ph = Phantom(layer=layer, pad=pad)
    k_ref = float(punch_stiffness_n_per_mm(40.0, pad.effective_radius_mm, 15.0))
    for xy in ((0.0, 0.0), (12.3, -20.1), (-30.0, 25.0)):
        assert ph.tissue_stiffness_n_per_mm(*xy) == pytest.approx(k_ref, rel=1e-9)
    k_series = 1 / (1 / k_ref + 1 / pad.gel_stiffness_n_per_mm)
    assert ph.force_n((0.0, 0.0, -2.0)) == pytest.approx(2.0 * k_series, rel=1e-9)
    c = ph.contact((0.0, 0.0, -2.0))
    inner = c.depth_map_mm[100:140, 140:180]
    assert np.ptp(inner) == pytest.approx(0.0, abs=1e-12)  # flat tissue: flat plateau
    # gel compression in the flat part = F / k_gel_area per unit area
    assert inner[0, 0] == pytest.approx(c.force_n / (pad.gel_stiffness_per_area * pad.area_mm2),
                                        rel=0.02)


def test_contact_force_is_the_integral_of_the_depth_map() -> None:
    ph = make_scene("breast", 2)
    gt = ph.ground_truth()
    x, y = gt["tumors"][1]["center_mm"]
    grid = PixelGrid()
    c = ph.contact((x, y, -2.5), grid)
    assert c.force_n == pytest.approx(ph.force_n((x, y, -2.5)))
    integral = c.depth_map_mm.sum() * ph.pad.gel_stiffness_per_area * grid.mm_per_px ** 2
    assert integral == pytest.approx(c.force_n, rel=1e-6)  # float32 depth map
    assert c.depth_map_mm.shape == (240, 320)
    assert np.all(c.depth_map_mm >= 0) and np.isfinite(c.depth_map_mm).all()
    assert c.tissue_indentation_mm < c.indentation_mm == pytest.approx(2.5)


def test_tumor_shows_as_a_raised_bump_and_higher_stiffness() -> None:
    t = Tumor("T", "benign", (0.0, 0.0), depth_mm=6.0, radius_mm=4.0, modulus_kpa=500.0)
    ph = Phantom(tumors=(t,))
    c = ph.contact((0.0, 0.0, -2.0), SMALL_GRID)
    centre = c.depth_map_mm[30, 40]
    rim = c.depth_map_mm[30, 40 + 24]  # 6 mm from the tumor centre, still under the pad
    assert centre > 1.5 * rim > 0
    k_over = ph.tissue_stiffness_n_per_mm(0.0, 0.0)
    k_far = ph.tissue_stiffness_n_per_mm(35.0, 35.0)
    assert k_over > 1.1 * k_far
    # a deeper tumor is felt less
    deep = Phantom(tumors=(Tumor("T", "benign", (0.0, 0.0), 12.0, 4.0, 500.0),))
    assert k_far < deep.tissue_stiffness_n_per_mm(0.0, 0.0) < k_over


def test_malignant_boundary_is_graded_benign_is_sharp() -> None:
    sharp = Tumor("b", "benign", (0.0, 0.0), 6.0, 5.0, 400.0, boundary_width_mm=0.05)
    graded = Tumor("m", "malignant", (0.0, 0.0), 6.0, 5.0, 400.0, boundary_width_mm=1.5)
    xs = np.linspace(-10, 10, 801)
    profiles = [Phantom(tumors=(t,)).column_modulus_kpa(xs, np.array([0.0]))[0]
                for t in (sharp, graded)]
    # distinct boundary = steep edge: the steepest relative slope is far larger when sharp
    slopes = [np.abs(np.diff(p)).max() / np.ptp(p) / (xs[1] - xs[0]) for p in profiles]
    assert slopes[0] > 3 * slopes[1]


def test_no_contact_above_surface_and_off_phantom() -> None:
    ph = make_scene("localization", 0)
    c = ph.contact((0.0, 0.0, 0.5))
    assert c.force_n == 0.0 and not c.in_contact and not c.depth_map_mm.any()
    assert ph.force_n((500.0, 0.0, -3.0)) == 0.0


@pytest.mark.parametrize("pose", [(0.0, 0.0, float("nan")), (0.0, math.inf, -1.0), (1.0, 2.0),
                                  "abc"])
def test_bad_poses_are_rejected(pose: object) -> None:
    ph = make_scene("localization", 0)
    with pytest.raises(InputDataError):
        ph.contact(pose)  # type: ignore[arg-type]
    with pytest.raises(InputDataError):
        ph.force_n(pose)  # type: ignore[arg-type]


@settings(max_examples=60, deadline=None)
# subnormal depths keep only a few significant bits, so no product with them is linear
@given(x=st.floats(-80, 80), y=st.floats(-80, 80), d1=st.floats(0, 6, allow_subnormal=False),
       d2=st.floats(0, 6, allow_subnormal=False))
def test_force_finite_nonnegative_and_linear_in_depth(x: float, y: float, d1: float,
                                                      d2: float) -> None:
    ph = _BREAST
    f1, f2 = ph.force_n((x, y, -d1)), ph.force_n((x, y, -d2))
    assert math.isfinite(f1) and f1 >= 0
    if d1 > 0:
        assert f2 == pytest.approx(f1 * d2 / d1, rel=1e-9, abs=1e-12)


_BREAST = make_scene("breast", 5)


def test_scenes_are_seeded_and_ground_truth_is_json(tmp_path: Path) -> None:
    a, b, c = make_scene("severity", 7), make_scene("severity", 7), make_scene("severity", 8)
    assert a.ground_truth() == b.ground_truth() != c.ground_truth()
    path = a.write_ground_truth(tmp_path / "gt.json")
    data = json.loads(path.read_text())
    assert data["scene"] == "severity" and len(data["tumors"]) == 4
    with pytest.raises(ConfigError):
        make_scene("nope", 0)


@pytest.mark.parametrize("seed", range(4))
def test_scene_contents(seed: int) -> None:
    loc = make_scene("localization", seed).ground_truth()["tumors"]
    assert len(loc) == 2 and loc[0]["radius_mm"] == loc[1]["radius_mm"]
    assert math.dist(loc[0]["center_mm"], loc[1]["center_mm"]) >= 22.0
    sev = make_scene("severity", seed).ground_truth()["tumors"]
    by_rank = sorted(sev, key=lambda t: t["severity_rank"])
    ks = [t["stiffness_n_per_mm"] for t in by_rank]
    assert ks == sorted(ks) and len(set(ks)) == 4  # felt stiffness follows severity
    assert {t["material"] for t in sev} == {"silicone", "pla"}
    breast = make_scene("breast", seed).ground_truth()["tumors"]
    kinds = {t["kind"]: t for t in breast}
    assert set(kinds) == {"benign", "malignant"}
    assert kinds["malignant"]["modulus_kpa"] > kinds["benign"]["modulus_kpa"]
    assert kinds["malignant"]["harmonics"] and not kinds["benign"]["harmonics"]


def test_bad_configuration_is_rejected() -> None:
    with pytest.raises(ConfigError):
        Tumor("x", "weird", (0.0, 0.0), 5.0, 3.0, 100.0)
    with pytest.raises(ConfigError):
        SiliconeLayer(thickness_mm=0.0)
    with pytest.raises(ConfigError):
        Phantom(tumors=(Tumor("x", "benign", (90.0, 0.0), 5.0, 3.0, 100.0),))
    with pytest.raises(ConfigError):
        PixelGrid(0, 10, 0.1)
