"""Palpation maps and findings on input at and beyond its bounds: map grids sized by a
recording's workspace, degenerate (1 x N) maps, and every setting validated up front."""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from local_site.palpation import (
    DetectionConfig,
    MapConfig,
    Recording,
    analyse_recording,
    build_maps,
    find_tumors,
)
from local_site.palpation.maps import MAX_MAP_CELLS_PER_SIDE, PalpationMaps, map_grid, pad_profile
from shared.errors import ConfigError, InputDataError
from shared.workspace import WorkspaceConfig, WorkspaceMap, load_workspace


def _recording(n: int = 50, *, meta: dict | None = None, hw: tuple[int, int] = (8, 8),
               seed: int = 0) -> Recording:
    rng = np.random.default_rng(seed)
    return Recording(platform_t_us=np.arange(n, dtype=np.int64), platform_mm=np.zeros((n, 3)),
                     frame_center_mm=rng.uniform(0.0, 60.0, (n, 2)),
                     frame_pitch_mm=np.full(n, 0.5), frame_contact=np.ones(n, bool),
                     frame_force_n=np.full(n, 2.0), frame_indentation_mm=np.full(n, 1.0),
                     frame_height_mm=rng.uniform(0.1, 1.0, (n, *hw)).astype(np.float32),
                     meta=meta or {})


# --- the map grid is bounded before anything is allocated ---

def test_a_recorded_workspace_too_large_for_a_map_is_an_input_error() -> None:
    # a 1 km platform at 0.5 mm cells: 2000041^2 cells (29 TiB per map: MemoryError before)
    rec = _recording(meta={"workspace": {"platform_size_mm": [1e6, 1e6, 185.0]}})
    start = time.perf_counter()
    with pytest.raises(InputDataError, match=f"2000041 cells along x.*at most "
                                             f"{MAX_MAP_CELLS_PER_SIDE}"):
        analyse_recording(rec, lag_correction=False)
    assert time.perf_counter() - start < 10.0


def test_a_tiny_cell_is_refused_and_the_default_grid_is_unchanged() -> None:
    ws = WorkspaceMap()
    with pytest.raises(InputDataError, match="cells along x"):
        build_maps(_recording(), ws, MapConfig(cell_mm=1e-3))
    x_mm, y_mm = map_grid(ws)
    np.testing.assert_array_equal(x_mm, np.arange(-40.0, 40.0 + 0.25, 0.5))
    np.testing.assert_array_equal(y_mm, np.arange(-40.0, 40.0 + 0.25, 0.5))


@settings(max_examples=60, deadline=None)
@given(size=st.floats(1.0, 1e7), cell=st.floats(1e-4, 50.0), margin=st.floats(0.0, 100.0))
def test_map_grid_is_np_arange_or_refused_above_the_limit(size: float, cell: float,
                                                          margin: float) -> None:
    ws = WorkspaceMap(WorkspaceConfig(platform_size_mm=(size, size / 2, 185.0)))
    cfg = MapConfig(cell_mm=cell, margin_mm=margin)
    lo, hi = ws.phantom_bounds_mm
    steps = [(hi[a] + margin + cell / 2 - (lo[a] - margin)) / cell for a in (0, 1)]
    if max(steps) > 2 * MAX_MAP_CELLS_PER_SIDE:  # far too large: the reference is not built
        with pytest.raises(InputDataError, match="cells along"):
            map_grid(ws, cfg)
        return
    want = [np.arange(lo[a] - margin, hi[a] + margin + cell / 2, cell) for a in (0, 1)]
    if max(w.size for w in want) > MAX_MAP_CELLS_PER_SIDE:
        with pytest.raises(InputDataError, match="cells along"):
            map_grid(ws, cfg)
        return
    got = map_grid(ws, cfg)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)


# --- find_tumors on any map: degenerate grids give no finding, never a crash ---

@st.composite
def _maps(draw: st.DrawFn) -> PalpationMaps:
    ny, nx = draw(st.integers(1, 16)), draw(st.integers(1, 16))
    cell = draw(st.sampled_from([0.25, 0.5, 1.0]))
    relief = draw(arrays(np.float64, (ny, nx), elements=st.floats(-2, 5)))
    count = draw(arrays(np.int64, (ny, nx), elements=st.integers(0, 30)))
    return _palpation_maps(np.where(count > 0, relief, np.nan), count, cell,
                           draw(st.floats(0, 1)), draw(st.floats(0.1, 10)))


def _palpation_maps(relief: np.ndarray, count: np.ndarray, cell: float = 0.5,
                    std: float = 0.01, stiffness: float = 1.0) -> PalpationMaps:
    ny, nx = relief.shape
    return PalpationMaps(np.arange(nx, dtype=np.float64) * cell,
                         np.arange(ny, dtype=np.float64) * cell, relief, count,
                         np.where(count > 1, std, np.nan), np.where(count > 0, stiffness, np.nan),
                         int(count.sum()), 1.0)


_FULL = np.full((40, 40), 10, np.int64)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(maps=_maps())
@example(maps=_palpation_maps(np.array([[0.5]]), np.array([[10]])))
@example(maps=_palpation_maps(np.zeros((40, 1)), _FULL[:, :1]))
@example(maps=_palpation_maps(np.zeros((1, 40)), _FULL[:1]))
@example(maps=_palpation_maps(np.where(np.arange(40) % 9 < 4, 1.0, 0.0)[None], _FULL[:1]))
def test_find_tumors_never_crashes_and_its_findings_lie_on_the_grid(
        maps: PalpationMaps) -> None:
    with np.errstate(all="ignore"):
        found = find_tumors(maps)
    if min(maps.relief.shape) < 2:  # no cell size, no outline: nothing to find
        assert found == []
    for f in found:
        assert maps.x_mm[0] <= f.center_mm[0] <= maps.x_mm[-1]
        assert maps.y_mm[0] <= f.center_mm[1] <= maps.y_mm[-1]
        assert 0.0 <= f.confidence <= 1.0 and 0.5 <= f.type_confidence <= 1.0


@pytest.mark.parametrize("grid", ["descending", "uneven", "x_and_y_differ", "shape"])
def test_find_tumors_refuses_a_grid_it_cannot_measure_on(grid: str) -> None:
    """A descending grid gave the gradients and the smoothing a negative cell size and was
    analysed as if nothing were wrong (found by review)."""
    count = _FULL[:10, :12]
    good = _palpation_maps(np.zeros((10, 12)), count)
    x, y = good.x_mm.copy(), good.y_mm.copy()
    if grid == "descending":
        x, y = x[::-1].copy(), y[::-1].copy()
    elif grid == "uneven":
        x[5:] += 0.1
    elif grid == "x_and_y_differ":
        y = y * 2.0
    else:
        x = x[:-1]
    bad = dataclasses.replace(good, x_mm=x, y_mm=y)
    with pytest.raises(ValueError, match="grid"):
        find_tumors(bad)
    find_tumors(good)


def test_empty_patches_are_an_input_error() -> None:
    with pytest.raises(InputDataError, match="patches"):
        pad_profile(np.zeros((5, 0, 0), np.float32))
    with pytest.raises(InputDataError, match="patches"):
        build_maps(_recording(hw=(0, 0)), WorkspaceMap())


# --- every setting validated with its name ---

@pytest.mark.parametrize("field, bad", [
    ("cell_mm", 0.0), ("cell_mm", -0.5), ("cell_mm", math.nan), ("cell_mm", math.inf),
    ("cell_mm", True), ("cell_mm", "0.5"),
    ("core_fraction", 1.5), ("core_fraction", 0.0), ("core_fraction", -0.1),
    ("core_fraction", math.nan),
    ("margin_mm", -1000.0), ("margin_mm", math.inf), ("margin_mm", None),
    ("min_indentation_mm", -1.0), ("min_indentation_mm", math.nan),
    ("min_signal_fraction", -0.1), ("min_signal_fraction", math.nan)])
def test_map_config_is_validated(field: str, bad: object) -> None:
    with pytest.raises(ConfigError, match=f"MapConfig.{field}"):
        MapConfig(**{field: bad})  # type: ignore[arg-type]


@given(cell=st.floats(1e-6, 1e6) | st.integers(1, 100), core=st.floats(1e-9, 1.0),
       margin=st.floats(0.0, 1e6), indent=st.floats(0.0, 1e3), frac=st.floats(0.0, 10.0))
def test_map_config_accepts_its_whole_range(cell: float, core: float, margin: float,
                                            indent: float, frac: float) -> None:
    cfg = MapConfig(cell_mm=cell, core_fraction=core, margin_mm=margin,
                    min_indentation_mm=indent, min_signal_fraction=frac)
    assert (cfg.cell_mm, cfg.core_fraction) == (cell, core)


_DETECTION_BAD = [
    ("smooth_mm", -0.5), ("smooth_mm", math.nan), ("min_relief", -1.0),
    ("noise_k", math.inf), ("min_area_mm2", -8.0), ("stiffness_smooth_mm", -2.0),
    ("coverage_margin_mm", math.nan), ("min_coverage", 1.5), ("min_coverage", -0.1),
    ("malignant_ref_edge_mm", 0.0), ("malignant_ref_rim_relief", -1.0),
    ("malignant_rim_exponent", -1.0), ("type_uncertain_k", 0.0), ("min_boundary_coverage", 2.0),
    ("type_se_scale", 0.0), ("type_se_scale", "1.5"), ("malignant_size_exponent", -0.5),
    ("malignant_ref_radius_mm", 0.0), ("min_samples", 0), ("min_samples", 2.5),
    ("min_samples", True), ("edge_sampled_arc_only", 1), ("edge_band_mm", (1.0, 4.0)),
    ("edge_band_mm", (-1.0, math.nan)), ("edge_band_mm", (-1.0,)), ("rim_band_mm", (-0.5, -2.5)),
    ("rim_band_mm", [-2.5, -0.5])]


@pytest.mark.parametrize("field, bad", _DETECTION_BAD)
def test_detection_config_is_validated(field: str, bad: object) -> None:
    with pytest.raises(ConfigError, match=f"DetectionConfig.{field}"):
        DetectionConfig(**{field: bad})  # type: ignore[arg-type]


def test_detection_defaults_and_edges_of_the_ranges_are_accepted() -> None:
    DetectionConfig()
    DetectionConfig(smooth_mm=0.0, min_relief=0.0, noise_k=0.0, min_area_mm2=0.0,
                    min_coverage=1.0, min_boundary_coverage=1.0, malignant_rim_exponent=0.0,
                    malignant_size_exponent=0.0, min_samples=1, edge_band_mm=(-0.1, 0.1),
                    rim_band_mm=(1.0, 2.0))


def test_a_bad_map_config_fails_before_the_maps_are_built() -> None:
    # these crashed deep inside build_maps/find_tumors (ZeroDivisionError, IndexError)
    ws = load_workspace(explicit=None)
    for bad in ({"cell_mm": 0.0}, {"core_fraction": 1.5}, {"margin_mm": -1000.0}):
        with pytest.raises(ConfigError):
            build_maps(_recording(), ws, MapConfig(**bad))
