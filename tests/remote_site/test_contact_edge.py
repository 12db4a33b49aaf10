"""The contact edge of a press from its colour change alone, and the calibration's use of it
(the kit's real presses: ``benchmarks/results/label_agreement.md`` and the real-video test)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.reconstruction.calibration import fit_calibration
from remote_site.reconstruction.contact_edge import (
    MAX_MOVE_FRACTION,
    MIN_RAYS,
    fit_contact_edge,
    refine_centre,
)
from remote_site.reconstruction.features import relative_change
from remote_site.reconstruction.labels import BallLabel
from remote_site.sensor.photometric import PhotometricModel, PhotometricSettings
from remote_site.sensor.sim_calibration import SIM_BALL_DIAMETER_MM, render_ball_presses
from shared.errors import CalibrationError

H, W = 160, 200
OTHER_LIGHTS = PhotometricSettings(shape_hw=(300, 400), mm_per_px=0.05,
                                   gel_rgb=(95.0, 135.0, 115.0), light_elevation_deg=55.0,
                                   light_azimuth_deg=30.0, noise_dn=1.5, vignetting=0.35,
                                   illumination_tilt=-0.1)


def step_ring(cx: float, cy: float, radius: float, width: float = 1.5, noise: float = 0.3,
              seed: int = 0) -> np.ndarray:
    """A colour change that falls off as a symmetric step at ``radius``: its gradient is
    largest exactly on the circle (the analytic reference)."""
    rows, cols = np.mgrid[0:H, 0:W]
    r = np.hypot(cols - cx, rows - cy)
    amp = 15.0 * (1.0 - np.tanh((r - radius) / width))
    rng = np.random.default_rng(seed)
    change = amp[..., None] * np.array([0.6, 0.5, 0.4]) + rng.normal(0, noise, (H, W, 3))
    return change.astype(np.float32)


@settings(max_examples=40, deadline=None)
@given(cx=st.floats(45, W - 45), cy=st.floats(45, H - 45), radius=st.floats(12, 35),
       off=st.floats(0, 4), angle=st.floats(0, 2 * np.pi), scale=st.floats(0.9, 1.15),
       seed=st.integers(0, 1000))
def test_the_circle_of_a_step_is_found_wherever_the_search_starts(
        cx: float, cy: float, radius: float, off: float, angle: float, scale: float,
        seed: int) -> None:
    start = BallLabel("p.png", cx + off * np.cos(angle), cy + off * np.sin(angle),
                      radius * scale)
    edge = fit_contact_edge(step_ring(cx, cy, radius, seed=seed), start)
    assert edge is not None
    assert np.hypot(edge.center_x - cx, edge.center_y - cy) < 0.15
    assert abs(edge.radius_px - radius) < 0.3
    assert edge.rays >= MIN_RAYS


@pytest.mark.parametrize("settings_", [PhotometricSettings(), OTHER_LIGHTS],
                         ids=["default-sensor", "other-lights"])
def test_simulated_ball_presses_give_their_true_centres(settings_: PhotometricSettings) -> None:
    """Rendered presses (directional lights, vignetting, camera noise) with exact circles:
    the search starts 4 px and 15 % off and ends within a quarter pixel."""
    model = PhotometricModel(settings_, seed=3)
    background = model.background_rgb.astype(np.float32)
    for frame, label in render_ball_presses(model, 8, 9.47, seed=7,
                                            depth_range_mm=(0.3, 0.66)):
        start = dataclasses.replace(label, center_x=label.center_x + 4.0,
                                    center_y=label.center_y - 2.5,
                                    radius_px=1.15 * label.radius_px)
        edge = fit_contact_edge(relative_change(frame.astype(np.float32), background), start)
        assert edge is not None
        assert np.hypot(edge.center_x - label.center_x,
                        edge.center_y - label.center_y) < 0.25, label


def test_refine_centre_moves_a_label_a_few_pixels_off_onto_the_edge() -> None:
    label = BallLabel("p.png", 103.0, 78.0, 25.0)
    refined = refine_centre(step_ring(100.0, 80.0, 25.0), label)
    assert refined is not None
    assert refined.image == "p.png" and refined.radius_px == 25.0  # the radius is kept
    assert np.hypot(refined.center_x - 100.0, refined.center_y - 80.0) < 0.15


def test_refine_centre_keeps_a_label_whose_edge_is_far_or_missing() -> None:
    # the press is elsewhere: whatever the search finds is not this label's contact
    far = BallLabel("p.png", 60.0, 60.0, 20.0)
    assert refine_centre(step_ring(140.0, 100.0, 20.0), far) is None
    # flat gel: noise only
    flat = np.random.default_rng(1).normal(0, 0.3, (H, W, 3)).astype(np.float32)
    assert refine_centre(flat, BallLabel("p.png", 100.0, 80.0, 20.0)) is None
    # a contact whose circle lies mostly beyond the frame: too few rays stay inside
    beyond = BallLabel("p.png", -15.0, 80.0, 30.0)
    assert fit_contact_edge(step_ring(-15.0, 80.0, 30.0), beyond) is None
    assert refine_centre(step_ring(-15.0, 80.0, 30.0), beyond) is None


def test_a_degenerate_start_gives_no_fit_not_an_error() -> None:
    ring = step_ring(100.0, 80.0, 20.0)
    for start in (BallLabel("p.png", 100.0, 80.0, 0.5), BallLabel("p.png", np.nan, 80.0, 20.0),
                  BallLabel("p.png", 100.0, 80.0, np.inf)):
        assert fit_contact_edge(ring, start) is None
        assert refine_centre(ring, start) is None


def test_half_a_circle_inside_the_frame_is_enough() -> None:
    edge = fit_contact_edge(step_ring(2.0, 80.0, 30.0), BallLabel("p.png", 4.0, 78.0, 28.0))
    assert edge is not None and MIN_RAYS <= edge.rays < 60
    assert np.hypot(edge.center_x - 2.0, edge.center_y - 80.0) < 0.3


def test_a_move_beyond_the_limit_is_refused() -> None:
    radius = 20.0
    beyond = (MAX_MOVE_FRACTION * radius) + 1.5
    label = BallLabel("p.png", 100.0 + beyond, 80.0, radius)
    assert refine_centre(step_ring(100.0, 80.0, radius), label) is None


def test_the_calibration_trains_on_the_edge_centres_by_default() -> None:
    """Labels 3 px off their simulated presses: moved back (stats say by how much), and the
    colour-to-slope fit is tighter than on the labels as given."""
    model = PhotometricModel(seed=2)
    presses = [(frame, dataclasses.replace(label, center_x=label.center_x + 3.0))
               for frame, label in render_ball_presses(model, 10, SIM_BALL_DIAMETER_MM,
                                                        seed=4)]
    edge = fit_calibration(model.background_rgb, presses, SIM_BALL_DIAMETER_MM,
                           model.settings.mm_per_px, trim_px=2.0)
    as_labelled = fit_calibration(model.background_rgb, presses, SIM_BALL_DIAMETER_MM,
                                  model.settings.mm_per_px, trim_px=2.0, centres="label")
    assert edge.stats["centres_moved_to_edge"] == 10
    assert 2.7 < edge.stats["centre_moved_mean_px"] < 3.3
    assert as_labelled.stats["centres_moved_to_edge"] == 0
    assert edge.stats["train_slope_rmse"] < 0.7 * as_labelled.stats["train_slope_rmse"]


def test_an_unknown_centres_setting_is_refused() -> None:
    model = PhotometricModel(seed=2)
    presses = render_ball_presses(model, 2, SIM_BALL_DIAMETER_MM, seed=4)
    with pytest.raises(CalibrationError, match="centres must be one of"):
        fit_calibration(model.background_rgb, presses, SIM_BALL_DIAMETER_MM,
                        model.settings.mm_per_px, centres="fitted")
