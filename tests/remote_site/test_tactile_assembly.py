"""Tactile frame assembly against analytic cases: flat, a sphere cap, the inverse map, stiffness."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.phantom.phantom import Phantom
from remote_site.phantom.reference_presses import sim_stiffness_calibration
from remote_site.reconstruction.reconstructor import Reconstructor
from remote_site.sensor.shapes import ball_depth_mm
from remote_site.sensor.sim_calibration import simulated_calibration
from remote_site.sensor.simulator import SimulatedSensor
from remote_site.stiffness.stiffness_map import MapBounds, StiffnessMap
from remote_site.tactile import (
    AppliedCommand,
    TactileAssembler,
    crop_centered,
    patch_offsets_mm,
    sample_stiffness_map,
)
from shared.errors import ConfigError, InputDataError
from shared.protocol import PlatformState, TactileFrame, decode, encode
from shared.protocol.messages import LAYER_RANGES, Hop
from shared.workspace import WorkspaceConfig, WorkspaceMap

TO_K = sim_stiffness_calibration().stiffness_to_k()


def _assembler(workspace: WorkspaceMap | None = None) -> TactileAssembler:
    return TactileAssembler(workspace or WorkspaceMap(), stiffness_to_k=TO_K)


PITCH_MM = 0.0634 * 8  # the sim sensor pixel pooled 8x: the default patch pitch


@pytest.fixture(scope="module")
def reconstructor() -> Reconstructor:
    return Reconstructor(simulated_calibration())


def _assemble(assembler: TactileAssembler, height: np.ndarray, probe=(0.0, 0.0, -1.0),
              stiffness_map: StiffnessMap | None = None, current: float | None = None,
              source: AppliedCommand | None = None, pitch: float = PITCH_MM,
              arrival_us: int | None = None):
    return assembler.assemble(seq=1, frame_ts_us=1_000, height_mm=height, pitch_mm=pitch,
                              probe_mm=probe, force_n=1.0, contact=True,
                              stiffness_map=stiffness_map, current_n_per_mm=current,
                              source=source, tactile_ready_us=2_000,
                              sensor_arrival_us=arrival_us)


def test_flat_phantom_without_contact_gives_a_zero_patch(reconstructor: Reconstructor) -> None:
    phantom = Phantom()  # no tumors: a flat silicone layer
    sensor = SimulatedSensor(seed=1)
    depth = phantom.contact((0.0, 0.0, 0.5)).depth_map_mm  # hovering above the surface
    assert not depth.any()
    hm = reconstructor.height_map(sensor.render(depth), out_pitch_mm=0.5)
    assert hm.skipped
    frame = _assemble(_assembler(), hm.height_mm, pitch=hm.mm_per_px)
    assert frame.layers["height_mm"].shape == (30, 40)
    assert np.all(frame.layers["height_mm"] == 0.0)
    assert np.all(frame.layers["friction"] == 0.0)


def test_sphere_patch_matches_the_depth_map_at_the_patch_pitch(
        reconstructor: Reconstructor) -> None:
    depth = ball_depth_mm((240, 320), 0.0634, 159.5, 119.5, 3.0, 0.5)
    hm = reconstructor.height_map(SimulatedSensor(seed=2).render(depth), out_pitch_mm=0.5)
    assert hm.mm_per_px == pytest.approx(PITCH_MM)
    frame = _assemble(_assembler(), hm.height_mm, pitch=hm.mm_per_px)
    patch = frame.layers["height_mm"]
    reference = cv2.resize(depth, (40, 30), interpolation=cv2.INTER_AREA)  # area mean per cell
    err = patch - reference
    assert float(np.sqrt(np.mean(err**2))) < 0.02
    assert float(np.abs(err).max()) < 0.08
    # the peak sits at the patch centre (the pad centre), as the sphere does
    r, c = np.unravel_index(np.argmax(patch), patch.shape)
    assert abs(r - 14.5) <= 1 and abs(c - 19.5) <= 1


def test_sphere_off_centre_shows_up_where_it_is_in_platform_coordinates() -> None:
    ws = WorkspaceMap()
    depth = ball_depth_mm((240, 320), 0.0634, 240.0, 60.0, 2.0, 0.4)
    pooled = cv2.resize(depth, (40, 30), interpolation=cv2.INTER_AREA)
    frame = _assemble(_assembler(ws), pooled, probe=(3.0, -2.0, -0.5))
    r, c = np.unravel_index(np.argmax(frame.layers["height_mm"]), (30, 40))
    x = frame.center_mm[0] + (c - 19.5) * frame.pitch_mm
    y = frame.center_mm[1] + (r - 14.5) * frame.pitch_mm
    # sphere centre in phantom mm: probe + pixel offset; platform = phantom + 30 (scale 1)
    x_expected = 3.0 + (240.0 - 159.5) * 0.0634 + 30.0
    y_expected = -2.0 + (60.0 - 119.5) * 0.0634 + 30.0
    assert abs(x - x_expected) <= frame.pitch_mm and abs(y - y_expected) <= frame.pitch_mm


@pytest.mark.parametrize("scale_xy,offset", [(1.0, (0.0, 0.0)), (0.5, (4.0, -3.0)),
                                             (2.0, (-10.0, 7.5))])
def test_center_is_the_inverse_workspace_map_and_pitch_is_in_platform_mm(
        scale_xy: float, offset: tuple[float, float]) -> None:
    ws = WorkspaceMap(WorkspaceConfig(scale_xy=scale_xy, offset_mm=offset))
    probe = (offset[0] + 3.0 * scale_xy, offset[1] - 5.0 * scale_xy, -0.8)
    frame = _assemble(_assembler(ws), np.zeros((30, 40), np.float32), probe=probe)
    # independent formula: x_pl = (x_ph - offset) / scale + platform centre (30 mm)
    assert frame.center_mm == pytest.approx((33.0, 25.0))
    assert frame.pitch_mm == pytest.approx(PITCH_MM / scale_xy)
    assert frame.indentation_mm == pytest.approx(0.8)
    back = ws.forward([*frame.center_mm, ws.inverse(probe)[2]])
    assert back[:2] == pytest.approx(probe[:2])


def test_hops_follow_the_contract_and_survive_the_wire() -> None:
    state = PlatformState(seq=7, ts_us=100, position_mm=(30.0, 30.0, 40.0), hops=(
        Hop("local", "capture", 100), Hop("relay", "relay_in", 150),
        Hop("relay", "relay_out", 160), Hop("remote", "station_rx", 170)))
    frame = _assemble(_assembler(), np.zeros((30, 40), np.float32),
                      source=AppliedCommand(state, 180), arrival_us=1_300)
    assert [f"{h.clock}.{h.stage}" for h in frame.hops] == [
        "local.capture", "relay.relay_in", "relay.relay_out", "remote.station_rx",
        "remote.arm_command", "remote.sensor_frame", "remote.sensor_arrival",
        "remote.tactile_ready"]
    assert [h.t_us for h in frame.hops][-4:] == [180, 1_000, 1_300, 2_000]
    assert (frame.source_seq, frame.source_ts_us, frame.ts_us) == (7, 100, 1_000)
    back = decode(encode(frame))
    assert isinstance(back, TactileFrame)
    assert back.hops == frame.hops and back.layers["height_mm"].shape == (30, 40)


def test_without_a_source_only_the_remote_stamps_are_present() -> None:
    frame = _assemble(_assembler(), np.zeros((30, 40), np.float32))
    assert [h.stage for h in frame.hops] == ["sensor_frame", "sensor_arrival", "tactile_ready"]
    # a source that stamps as it delivers: the image arrived when it was stamped
    assert [h.t_us for h in frame.hops] == [1_000, 1_000, 2_000]
    assert frame.source_seq is None and frame.source_ts_us is None


def test_stiffness_layers_come_from_the_map_and_the_current_estimate() -> None:
    assembler = TactileAssembler(WorkspaceMap(), stiffness_to_k=TO_K)
    smap = StiffnessMap(MapBounds(cell_mm=2.0))
    zeros = np.zeros((30, 40), np.float32)
    assert "stiffness_k" not in _assemble(assembler, zeros, stiffness_map=smap).layers
    smap.add(0.5, 0.5, 3.0)  # one cell: x, y in [0, 2)
    frame = _assemble(assembler, zeros, probe=(0.0, 0.0, -1.0), stiffness_map=smap,
                      current=1.5)
    n_per_mm = frame.layers["stiffness_n_per_mm"]
    xs, ys = patch_offsets_mm((30, 40), PITCH_MM)
    inside = ((ys >= 0) & (ys < 2))[:, None] & ((xs >= 0) & (xs < 2))[None, :]
    assert np.all(n_per_mm[inside] == pytest.approx(3.0))
    assert np.all(n_per_mm[~inside] == pytest.approx(1.5))
    k = frame.layers["stiffness_k"]
    assert k[inside][0] == pytest.approx(float(TO_K.k(3.0)), abs=1e-6)
    assert k[~inside][0] == pytest.approx(float(TO_K.k(1.5)), abs=1e-6)
    assert k[inside][0] > k[~inside][0]
    # without a current estimate the rest is filled with the known cells' mean
    frame = _assemble(assembler, zeros, stiffness_map=smap, current=None)
    assert np.all(frame.layers["stiffness_n_per_mm"] == pytest.approx(3.0))


def test_sample_stiffness_map_matches_value_lookups() -> None:
    smap = StiffnessMap(MapBounds(-10, 10, -10, 10, 2.5))
    rng = np.random.default_rng(0)
    for x, y, k in rng.uniform([-10, -10, 0.1], [10, 10, 5], size=(30, 3)):
        smap.add(float(x), float(y), float(k))
    xs, ys = np.linspace(-12, 12, 37), np.linspace(-11, 11, 23)
    values, known = sample_stiffness_map(smap, xs, ys)
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            ref = smap.value(float(x), float(y))
            assert known[i, j] == (ref is not None)
            if ref is not None:
                assert values[i, j] == pytest.approx(ref)


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(2, 80), cols=st.integers(2, 80),
       size_x=st.floats(0.0, 60.0), size_y=st.floats(0.0, 60.0),
       pitch=st.floats(0.05, 3.0))
def test_crop_keeps_the_patch_centred(rows: int, cols: int, size_x: float, size_y: float,
                                      pitch: float) -> None:
    xs, ys = patch_offsets_mm((rows, cols), pitch)
    grid_x = np.broadcast_to(xs[None, :], (rows, cols))
    grid_y = np.broadcast_to(ys[:, None], (rows, cols))
    cx = crop_centered(grid_x, (size_x, size_y), pitch)
    cy = crop_centered(grid_y, (size_x, size_y), pitch)
    assert cx.shape == cy.shape and cx.size > 0
    assert abs(float(cx.mean())) < 1e-9 * max(1.0, pitch * cols)
    assert abs(float(cy.mean())) < 1e-9 * max(1.0, pitch * rows)
    if size_x > 0 and size_x / pitch + 1 < cols - 2:
        assert (cx.shape[1] - 1) * pitch <= size_x + 2 * pitch


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-50.0, 50.0), min_size=12, max_size=12),
       st.floats(0.0, 200.0), st.floats(-1e3, 1e3, allow_nan=False))
def test_layers_are_finite_and_in_range_for_any_heights(values: list[float], k: float,
                                                         z: float) -> None:
    assembler = TactileAssembler(WorkspaceMap(), stiffness_to_k=TO_K)
    smap = StiffnessMap()
    smap.add(0.0, 0.0, k)
    frame = _assemble(assembler, np.asarray(values, np.float32).reshape(3, 4),
                      probe=(0.0, 0.0, z), stiffness_map=smap)
    for name, layer in frame.layers.items():
        assert np.isfinite(layer).all(), name
    assert frame.layers["height_mm"].min() >= -10 and frame.layers["height_mm"].max() <= 10
    assert 0.5 <= frame.layers["stiffness_k"].min() <= frame.layers["stiffness_k"].max() <= 1.0
    assert frame.indentation_mm == pytest.approx(min(max(0.0, -z), 100.0))
    decode(encode(frame))  # the wire accepts every layer


def test_non_finite_input_is_refused() -> None:
    assembler = TactileAssembler(WorkspaceMap(), stiffness_to_k=TO_K)
    bad = np.zeros((30, 40), np.float32)
    bad[3, 3] = math.nan
    with pytest.raises(InputDataError):
        _assemble(assembler, bad)
    with pytest.raises(InputDataError):
        _assemble(assembler, np.zeros((30, 40)), probe=(0.0, math.inf, 0.0))
    with pytest.raises(ConfigError):
        TactileAssembler(WorkspaceMap(), stiffness_to_k=TO_K, friction=1.5)
    with pytest.raises(ConfigError):
        TactileAssembler(WorkspaceMap(), stiffness_to_k=TO_K,
                         patch_size_mm=(-1.0, 2.0))


@settings(max_examples=40, deadline=None)
@given(yaw=st.floats(-25.0, 25.0), bx=st.floats(-5.0, 5.0), by=st.floats(-4.0, 4.0),
       px=st.floats(-20.0, 20.0), py=st.floats(-20.0, 20.0))
def test_a_turned_map_puts_a_bump_where_the_platform_meets_it(
        yaw: float, bx: float, by: float, px: float, py: float) -> None:
    """A bump ``(bx, by)`` mm off the pad centre on the arm's (sensor's) axes, with the map
    registered to a phantom turned by ``yaw``: in the sent frame it sits at the platform
    offset the workspace map itself gives for that arm point (``inverse``), not at the
    unturned offset."""
    workspace = WorkspaceMap().registered(1.0, -2.0, yaw)
    rows, cols = 31, 41
    xs, ys = patch_offsets_mm((rows, cols), PITCH_MM)
    height = 0.4 * np.exp(-((xs[None, :] - bx) ** 2 + (ys[:, None] - by) ** 2) / (2 * 0.8 ** 2))
    probe = (px, py, -1.0)
    frame = _assemble(_assembler(workspace), height, probe=probe)
    sent = frame.layers["height_mm"]
    # sub-cell peak: the centroid of the top of the bump
    top = np.clip(sent - 0.6 * sent.max(), 0.0, None)
    rr, cc = np.mgrid[0:sent.shape[0], 0:sent.shape[1]]
    got = np.array([((cc * top).sum() / top.sum() - (sent.shape[1] - 1) / 2.0),
                    ((rr * top).sum() / top.sum() - (sent.shape[0] - 1) / 2.0)]) * frame.pitch_mm
    want = (workspace.inverse([px + bx, py + by, -1.0])[:2]
            - workspace.inverse([px, py, -1.0])[:2])
    assert got == pytest.approx(want, abs=0.15)
    # resampled bicubically, not smeared away (bilinear keeps 83 % of this 1.58-cell bump's
    # peak half a cell off both ways)
    assert float(sent.max()) >= 0.9 * float(height.max())


def test_turned_layers_stay_in_their_wire_ranges() -> None:
    """Bicubic resampling overshoots at a step; the frame must still pass validation."""
    height = np.zeros((31, 41))
    height[:, 20:] = 0.5
    stiffness = StiffnessMap(MapBounds(cell_mm=2.0))
    for x in np.arange(-29.0, 30.0, 2.0):
        for y in np.arange(-29.0, 30.0, 2.0):  # k at both ends of its range, a step at x = 0
            stiffness.add(float(x), float(y), 1e4 if x > 0 else 0.0)
    frame = _assemble(_assembler(WorkspaceMap().registered(0.0, 0.0, 17.0)), height,
                      stiffness_map=stiffness, current=1.0)
    assert float(TO_K.k(1e4)) == 1.0 and float(TO_K.k(0.0)) == 0.5  # the range's ends
    for name, layer in frame.layers.items():
        lo, hi = LAYER_RANGES[name]
        assert lo <= float(layer.min()) and float(layer.max()) <= hi, name
    assert decode(encode(frame)) == frame


def test_an_unturned_map_sends_the_patch_untouched() -> None:
    height = np.random.default_rng(3).random((31, 41)) * 0.1
    frame = _assemble(_assembler(WorkspaceMap().registered(1.0, -2.0, 0.0)), height)
    np.testing.assert_array_equal(frame.layers["height_mm"], height.astype(np.float32))
