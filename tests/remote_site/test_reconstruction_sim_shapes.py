"""Reconstruction of analytic shapes rendered by the simulator, on two different sensors.

The second sensor differs in size, scale, light layout, gel colour and noise, and its presses
are captured with a brightness drift against the background: the same calibration procedure
must work unchanged.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lab.reconstruction_metrics import evaluate_press
from remote_site.reconstruction.calibration import fit_calibration
from remote_site.reconstruction.reconstructor import Reconstructor
from remote_site.sensor.photometric import PhotometricModel, PhotometricSettings
from remote_site.sensor.shapes import ball_depth_mm, cone_depth_mm, flat_punch_depth_mm
from remote_site.sensor.sim_calibration import (
    SIM_BALL_DIAMETER_MM,
    render_ball_presses,
    simulated_calibration,
)

OTHER = PhotometricSettings(shape_hw=(300, 400), mm_per_px=0.05, gel_rgb=(95.0, 135.0, 115.0),
                            light_elevation_deg=55.0, light_azimuth_deg=30.0, noise_dn=1.5,
                            vignetting=0.35, illumination_tilt=-0.1)
DRIFT = (0.93, 0.97, 0.9)


@pytest.fixture(scope="session")
def default_sensor() -> tuple[PhotometricModel, Reconstructor]:
    return PhotometricModel(seed=5), Reconstructor(simulated_calibration())


@pytest.fixture(scope="session")
def drifting_sensor() -> tuple[PhotometricModel, Reconstructor]:
    """Another sensor, calibrated on presses captured with a brightness drift."""
    clean = PhotometricModel(OTHER, seed=1)
    drifted = PhotometricModel(dataclasses.replace(OTHER, brightness=DRIFT), seed=2)
    presses = render_ball_presses(drifted, 16, SIM_BALL_DIAMETER_MM, seed=3)
    calib = fit_calibration(clean.background_rgb, presses, SIM_BALL_DIAMETER_MM,
                            OTHER.mm_per_px, trim_px=2.0)
    return drifted, Reconstructor(calib)


def _surface_error(model: PhotometricModel, rec: Reconstructor,
                   depth: np.ndarray) -> tuple[float, float, np.ndarray]:
    """(shape RMSE in the contact, max abs error, height) against the rendered gel surface."""
    truth = model.gel_surface_mm(depth)
    hm = rec.height_map(model.render(depth))
    inside = truth > 0.02
    err = hm.height_mm - truth
    return float(np.sqrt(np.mean((err[inside] - err[inside].mean()) ** 2))), float(
        np.abs(err).max()), hm.height_mm


@pytest.mark.parametrize("which", ["default_sensor", "drifting_sensor"])
def test_sphere(which: str, request: pytest.FixtureRequest) -> None:
    model, rec = request.getfixturevalue(which)
    rows, cols = model.settings.shape_hw
    depth = ball_depth_mm((rows, cols), model.settings.mm_per_px, cols * 0.4, rows * 0.55,
                          3.0, 0.4)
    shape_rmse, max_err, height = _surface_error(model, rec, depth)
    assert shape_rmse < 0.012
    assert max_err < 0.06
    assert height.max() == pytest.approx(0.4, abs=0.05)


@pytest.mark.parametrize("which", ["default_sensor", "drifting_sensor"])
def test_cone(which: str, request: pytest.FixtureRequest) -> None:
    model, rec = request.getfixturevalue(which)
    rows, cols = model.settings.shape_hw
    depth = cone_depth_mm((rows, cols), model.settings.mm_per_px, cols * 0.6, rows * 0.4,
                          75.0, 0.3)
    shape_rmse, max_err, _ = _surface_error(model, rec, depth)
    assert shape_rmse < 0.02
    assert max_err < 0.08


def test_flat_punch_is_flat_on_top(default_sensor: tuple) -> None:
    model, rec = default_sensor
    rows, cols = model.settings.shape_hw
    depth = flat_punch_depth_mm((rows, cols), model.settings.mm_per_px, cols / 2, rows / 2,
                                2.0, 0.2)
    hm = rec.height_map(model.render(depth))
    r = np.hypot(*np.mgrid[0:rows, 0:cols] - np.array([rows / 2, cols / 2])[:, None, None])
    top = hm.height_mm[r * model.settings.mm_per_px < 1.5]
    assert np.ptp(top) < 0.05
    assert top.mean() == pytest.approx(0.2, abs=0.04)


@pytest.mark.parametrize("which", ["default_sensor", "drifting_sensor"])
def test_no_contact_is_zero_and_skipped(which: str, request: pytest.FixtureRequest) -> None:
    model, rec = request.getfixturevalue(which)
    hm = rec.height_map(model.render(np.zeros(model.settings.shape_hw, np.float32)))
    assert hm.skipped and not hm.contact
    assert not hm.height_mm.any()


def test_ball_press_metrics_on_drifting_sensor(drifting_sensor: tuple) -> None:
    model, rec = drifting_sensor
    for frame, label in render_ball_presses(model, 4, SIM_BALL_DIAMETER_MM, seed=11):
        hm = rec.height_map(frame)
        m = evaluate_press(hm.height_mm, hm.mm_per_px, label, model.settings.mm_per_px,
                           SIM_BALL_DIAMETER_MM / 2, trim_px=2.0)
        assert m.shape_rmse_mm < 0.02
        assert abs(m.radius_error(SIM_BALL_DIAMETER_MM / 2)) < 0.08  # 2 mm ball, draped rim
        assert m.flat_p99_mm < 0.01


@pytest.mark.parametrize(("pitch_mm", "tol_mm"), [(0.127, 0.02), (0.254, 0.03), (1.7, 0.1)])
def test_downsampled_output_matches_full_resolution(default_sensor: tuple, pitch_mm: float,
                                                    tol_mm: float) -> None:
    model, rec = default_sensor
    rows, cols = model.settings.shape_hw
    depth = ball_depth_mm((rows, cols), model.settings.mm_per_px, cols / 2, rows / 2, 3.0, 0.4)
    frame = model.render(depth)
    full = rec.height_map(frame)
    coarse = rec.height_map(frame, out_pitch_mm=pitch_mm)
    f = rec.pool_factor(pitch_mm)
    assert coarse.height_mm.shape == (rows // f, cols // f)
    assert coarse.mm_per_px == pytest.approx(f * model.settings.mm_per_px)
    r0, c0 = rows % f // 2, cols % f // 2  # the pixels left over are cut on both sides
    pooled = full.height_mm[r0: r0 + rows // f * f, c0: c0 + cols // f * f].reshape(
        rows // f, f, cols // f, f).mean(axis=(1, 3))
    # the cost of pooling the colour change before the (non-linear) model; see the benchmark
    assert np.abs(coarse.height_mm - pooled).max() < tol_mm
    assert coarse.contact


def test_simulated_calibration_matches_default_sensor() -> None:
    calib = simulated_calibration()
    assert calib.shape_hw == PhotometricSettings().shape_hw
    assert calib.mm_per_px == pytest.approx(PhotometricSettings().mm_per_px)


@pytest.mark.parametrize("pitch_mm", [0.4, 0.8])  # pooled by 8 and by 16
def test_a_pooled_map_is_centred_on_the_frame(
        drifting_sensor: tuple[PhotometricModel, Reconstructor], pitch_mm: float) -> None:
    """A ball pressed at the frame's centre is at the pooled map's centre (the station places
    the map centred on the pad). The other sensor has 300 rows: pooled by 16, 12 rows are
    left over; cutting them all at the end put the ball 0.3 mm off the map's centre."""
    model, rec = drifting_sensor
    rows, cols = model.settings.shape_hw
    depth = ball_depth_mm((rows, cols), model.settings.mm_per_px, (cols - 1) / 2,
                          (rows - 1) / 2, 3.0, 0.4)
    hm = rec.height_map(model.render(depth), out_pitch_mm=pitch_mm)
    h = np.clip(hm.height_mm, 0.0, None) * hm.mask
    r, c = np.indices(h.shape)
    centroid = (float((h * r).sum() / h.sum()), float((h * c).sum() / h.sum()))
    centre = ((h.shape[0] - 1) / 2, (h.shape[1] - 1) / 2)
    for got, want in zip(centroid, centre, strict=True):
        assert abs(got - want) * hm.mm_per_px <= model.settings.mm_per_px, (centroid, centre)
