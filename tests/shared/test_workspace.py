"""Platform <-> phantom workspace map: round trips, clamping, configuration."""

from __future__ import annotations

import cmath
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.errors import ConfigError, InputDataError
from shared.workspace import WorkspaceConfig, WorkspaceMap, load_workspace

WS = WorkspaceMap()
inside = st.tuples(st.floats(0, 60), st.floats(0, 60), st.floats(0, 185))
anywhere = st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), st.floats(-1e4, 1e4))
configs = st.builds(WorkspaceConfig, scale_xy=st.floats(0.2, 3.0),
                    offset_mm=st.tuples(st.floats(-20, 20), st.floats(-20, 20)),
                    scale_z=st.floats(0.02, 0.5), z_surface_mm=st.floats(0, 185),
                    max_press_depth_mm=st.floats(0, 10), max_lift_mm=st.floats(0, 50))


@settings(max_examples=200, deadline=None)
@given(p=inside, cfg=configs)
def test_inverse_of_forward_is_identity_where_nothing_clamps(p: tuple[float, float, float],
                                                             cfg: WorkspaceConfig) -> None:
    ws = WorkspaceMap(cfg)
    fwd = ws.forward(p)
    raw = ws.forward_unclamped(p)
    # "nothing clamps" exactly: a clip that leaves a value alone returns it bit for bit. With
    # np.allclose (atol 1e-8) a clamp of a few nm counted as none, and the inverse was then
    # rightly off by it (a fresh-clone CI found z clamped by 3.3e-9 mm)
    if np.array_equal(fwd, raw):
        np.testing.assert_allclose(ws.inverse(fwd), p, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(p=anywhere)
def test_forward_clamps_into_the_reachable_box(p: tuple[float, float, float]) -> None:
    out = WS.forward(p)
    lo, hi = WS.phantom_bounds_mm
    assert np.all(out >= np.asarray(lo) - 1e-12) and np.all(out <= np.asarray(hi) + 1e-12)
    np.testing.assert_allclose(out, WS.forward(WS.clamp_platform(p)))
    # inverse always lands inside the platform box
    back = WS.inverse(out)
    assert np.all(back >= -1e-9) and np.all(back <= np.array([60, 60, 185]) + 1e-9)


def test_default_mapping_numbers() -> None:
    np.testing.assert_allclose(WS.forward((30, 30, 40)), (0, 0, 0))
    np.testing.assert_allclose(WS.forward((0, 60, 0)), (-30, 30, -4))
    np.testing.assert_allclose(WS.forward((60, 0, 185)), (30, -30, 14.5))
    assert WS.phantom_xy_to_platform((10.0, -5.0)) == pytest.approx((40.0, 25.0))
    # vectorised
    assert WS.forward(np.zeros((5, 3))).shape == (5, 3)


def test_press_depth_is_limited() -> None:
    ws = WorkspaceMap(WorkspaceConfig(scale_z=0.5, max_press_depth_mm=3.0))
    assert ws.forward((30, 30, 0))[2] == -3.0


def test_bad_input_and_config(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(InputDataError):
        WS.forward((1.0, float("nan"), 2.0))
    with pytest.raises(InputDataError):
        WS.forward((1.0, 2.0))
    with pytest.raises(ConfigError):
        WorkspaceConfig(scale_xy=0.0)
    with pytest.raises(ConfigError):  # the z travel never reaches the allowed range
        WorkspaceMap(WorkspaceConfig(z_surface_mm=-500.0, max_lift_mm=1.0))
    monkeypatch.setenv("TELETOUCH_WORKSPACE_SCALE_XY", "0.5")
    ws = load_workspace(explicit={"offset_mm": (5.0, 0.0)})
    np.testing.assert_allclose(ws.forward((60, 30, 40)), (20.0, 0.0, 0.0))


@settings(max_examples=60, deadline=None)
@given(st.floats(-180, 180), st.floats(0.5, 2.0), st.floats(-10, 10), st.floats(-10, 10),
       st.tuples(st.floats(0, 60), st.floats(0, 60), st.floats(0, 185)))
def test_rotated_map_matches_an_independent_rotation(angle: float, scale: float, ox: float,
                                                     oy: float,
                                                     p: tuple[float, float, float]) -> None:
    ws = WorkspaceMap(WorkspaceConfig(rotation_deg=angle, scale_xy=scale, offset_mm=(ox, oy)))
    got = ws.forward_unclamped(list(p))
    # reference: complex multiplication is a rotation
    u = complex(p[0] - 30.0, p[1] - 30.0) * scale * cmath.exp(1j * math.radians(angle))
    assert got[0] == pytest.approx(u.real + ox, abs=1e-9)
    assert got[1] == pytest.approx(u.imag + oy, abs=1e-9)
    assert got[2] == pytest.approx(0.1 * (p[2] - 40.0))
    back = ws.inverse(got)
    if np.allclose(ws.clamp_phantom(got), got):
        assert np.allclose(back, p, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(st.floats(-5, 5), st.floats(-5, 5), st.floats(-10, 10), st.floats(-30, 30),
       st.tuples(st.floats(0, 60), st.floats(0, 60)))
def test_registered_map_is_the_map_followed_by_the_rigid_motion(
        dx: float, dy: float, yaw: float, base_angle: float, p: tuple[float, float]) -> None:
    ws = WorkspaceMap(WorkspaceConfig(rotation_deg=base_angle, offset_mm=(2.0, -1.0)))
    reg = ws.registered(dx, dy, yaw)
    q = ws.forward_unclamped([p[0], p[1], 40.0])
    expect = complex(q[0], q[1]) * cmath.exp(1j * math.radians(yaw)) + complex(dx, dy)
    a = reg.forward_unclamped([p[0], p[1], 40.0])
    assert (a[0], a[1]) == (pytest.approx(expect.real, abs=1e-9),
                            pytest.approx(expect.imag, abs=1e-9))


def test_rotation_is_validated() -> None:
    with pytest.raises(ConfigError, match="rotation_deg"):
        WorkspaceConfig(rotation_deg=200.0)
    with pytest.raises(ConfigError, match="finite"):
        WorkspaceConfig(rotation_deg=float("nan"))
