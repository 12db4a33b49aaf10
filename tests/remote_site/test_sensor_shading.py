"""The fused shading kernel against an independent numpy evaluation of the photometric model.

Tolerance: at most 1 DN per channel (float32 rounding order and half-up vs half-even at .5),
on at most 0.1 % of the values.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.sensor.photometric import PhotometricModel, PhotometricSettings


def _reference(model: PhotometricModel, depth_mm: np.ndarray) -> np.ndarray:
    """The model's formula spelled out with numpy (normals, lights, colour mix)."""
    s = model.settings
    elev = np.deg2rad(s.light_elevation_deg)
    az = np.deg2rad(s.light_azimuth_deg + np.array([0.0, 120.0, 240.0]))
    lights = np.stack([np.cos(az) * np.sin(elev), np.sin(az) * np.sin(elev),
                       np.full(3, np.cos(elev))], axis=1)
    surface = model.gel_surface_mm(depth_mm).astype(np.float64)
    gy, gx = np.gradient(surface, s.mm_per_px)
    norm = 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)
    normals = np.stack([-gx * norm, -gy * norm, norm], axis=-1)
    shade = np.maximum(normals @ lights.T, 0.0) / np.cos(elev) - 1.0
    rel = shade @ np.asarray(s.light_rgb)
    rows, cols = s.shape_hw
    yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float64)
    u, v = (xx + 0.5) / cols - 0.5, (yy + 0.5) / rows - 0.5
    illum = (1.0 - s.vignetting * 2.0 * (u**2 + v**2)) * (1.0 + s.illumination_tilt * u)
    background = illum[..., None] * np.asarray(s.gel_rgb)
    marker_gain = np.ones((rows, cols, 1))
    if s.marker_pitch_mm > 0:
        pitch_px = s.marker_pitch_mm / s.mm_per_px
        du, dv = (xx % pitch_px) - pitch_px / 2, (yy % pitch_px) - pitch_px / 2
        marker_gain[np.hypot(du, dv) < s.marker_radius_mm / s.mm_per_px] = 0.25
    image = background * (1.0 + s.shading_gain * rel) * marker_gain * np.asarray(s.brightness)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


@settings(max_examples=20, deadline=None)
@given(cx=st.floats(0, 320), cy=st.floats(0, 240), radius_px=st.floats(5, 150),
       height_mm=st.floats(0.0, 2.0), markers=st.booleans(),
       gain=st.tuples(st.floats(0.8, 1.2), st.floats(0.8, 1.2), st.floats(0.8, 1.2)))
def test_render_matches_numpy_reference(cx: float, cy: float, radius_px: float,
                                        height_mm: float, markers: bool,
                                        gain: tuple[float, float, float]) -> None:
    settings_ = PhotometricSettings(marker_pitch_mm=1.2 if markers else 0.0, brightness=gain)
    model = PhotometricModel(settings_)
    yy, xx = np.mgrid[0:240, 0:320]
    r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / radius_px**2
    depth = (height_mm * np.sqrt(np.maximum(1.0 - r2, 0.0))).astype(np.float32)
    rendered = model.render(depth, noise=False).astype(int)
    reference = _reference(model, depth).astype(int)
    diff = np.abs(rendered - reference)
    assert diff.max() <= 1
    assert np.count_nonzero(diff) <= 1e-3 * diff.size


@pytest.mark.parametrize("slope", [(0.3, 0.0), (0.0, -0.25), (0.2, 0.15), (-0.4, 0.35)])
def test_a_tilted_gel_matches_the_reference_on_every_row_and_column(
        slope: tuple[float, float]) -> None:
    # slopes everywhere, up to the frame's edges, where the differences are one-sided: the
    # border rows and columns are checked by themselves, not as a share of the frame
    model = PhotometricModel(PhotometricSettings(marker_pitch_mm=1.2, brightness=(1.1, 0.95, 1.0)))
    yy, xx = np.mgrid[0:240, 0:320].astype(np.float32) * np.float32(model.settings.mm_per_px)
    depth = (2.0 + slope[0] * xx + slope[1] * yy).astype(np.float32)
    depth -= min(float(depth.min()), 0.0)
    rendered = model.render(depth, noise=False).astype(int)
    diff = np.abs(rendered - _reference(model, depth).astype(int))
    assert diff.max() <= 1
    for edge in (diff[0], diff[-1], diff[:, 0], diff[:, -1]):
        assert np.count_nonzero(edge) <= 0.01 * edge.size
    assert np.count_nonzero(diff) <= 1e-3 * diff.size


def test_flat_gel_renders_the_background_and_noise_is_zero_mean() -> None:
    model = PhotometricModel(PhotometricSettings(noise_dn=2.0), seed=3)
    flat = np.zeros((240, 320), np.float32)
    np.testing.assert_array_equal(model.render(flat, noise=False), model.background_rgb)
    noisy = model.render(flat).astype(float) - model.background_rgb
    assert abs(noisy.mean()) < 0.05 and 1.5 < noisy.std() < 2.5


def test_flat_gel_fast_path_equals_the_fused_kernel_with_the_same_noise() -> None:
    # without contact the shading is computed once and only the noise added per frame: the
    # frames must be those the fused kernel renders for a flat surface with that noise
    from remote_site.sensor.shading import shade_frame

    settings_ = PhotometricSettings(noise_dn=2.1, marker_pitch_mm=1.2, brightness=(1.1, 0.9, 1.0))
    fast, fused = PhotometricModel(settings_, seed=5), PhotometricModel(settings_, seed=5)
    flat = np.zeros((240, 320), np.float32)
    gain = np.array([1.03, 0.97, 1.0])
    for _ in range(5):  # the same bytes: the same row arithmetic (see shading's docstring)
        got = fast.render(flat, gain=gain)
        noise = fused._noise_sample()
        np.testing.assert_array_equal(got, shade_frame(
            flat, settings_.mm_per_px, fused._albedo, fused._weights, fused._lights, noise,
            gain))
    np.testing.assert_array_equal(fast.render(flat, noise=False),
                                  shade_frame(flat, settings_.mm_per_px, fused._albedo,
                                              fused._weights, fused._lights, None))
    # a press after flat frames still goes through the full shading
    press = np.zeros((240, 320), np.float32)
    press[100:140, 140:180] = 0.5
    assert not np.array_equal(fast.render(press, noise=False), fast.render(flat, noise=False))


@settings(max_examples=10, deadline=None)
@given(gain=st.tuples(st.floats(0.9, 1.1), st.floats(0.9, 1.1), st.floats(0.9, 1.1)),
       pressed=st.booleans(), seed=st.integers(0, 100))
def test_brightness_gain_in_the_kernel_equals_cv2_multiply(
        gain: tuple[float, float, float], pressed: bool, seed: int) -> None:
    # the LED drift used to be a cv2.multiply of the rendered frame; the kernels apply it in
    # their pass and must give the same bytes (float32 gain as the simulator computes it)
    import cv2

    g32 = np.asarray(gain, np.float32)
    settings_ = PhotometricSettings(noise_dn=2.1)
    a, b = PhotometricModel(settings_, seed=seed), PhotometricModel(settings_, seed=seed)
    depth = np.zeros((240, 320), np.float32)
    if pressed:
        depth[80:160, 100:220] = 0.4
    got = a.render(depth, gain=g32.astype(np.float64))
    plain = b.render(depth)
    want = cv2.multiply(plain, (float(g32[0]), float(g32[1]), float(g32[2]), 0.0),  # type: ignore[call-overload,unused-ignore]
                        dtype=cv2.CV_8U)
    np.testing.assert_array_equal(got, np.asarray(want))


@pytest.mark.parametrize("shape_hw", [(9, 13), (320, 240), (31, 257)])
def test_other_frame_shapes_match_the_reference(shape_hw: tuple[int, int]) -> None:
    rows, cols = shape_hw
    model = PhotometricModel(PhotometricSettings(shape_hw=shape_hw, marker_pitch_mm=0.3))
    yy, xx = np.mgrid[0:rows, 0:cols]
    r2 = ((xx - cols / 3) ** 2 + (yy - rows / 2) ** 2) / (0.4 * max(rows, cols)) ** 2
    depth = (0.3 * np.sqrt(np.maximum(1.0 - r2, 0.0))).astype(np.float32)
    diff = np.abs(model.render(depth, noise=False).astype(int)
                  - _reference(model, depth).astype(int))
    assert diff.max() <= 1 and np.count_nonzero(diff) <= max(2, 1e-3 * diff.size)


def test_rounding_clipping_and_gain_at_the_ends_of_the_range() -> None:
    # what the default optics never reach: values below 0 and above 255 before the gain,
    # a gain that saturates, and a product exactly on .5 (cv2.multiply rounds half to even)
    from remote_site.sensor.shading import finish_frame

    values = np.array([[[3.0, 250.0, 299.6], [-4.0, 2.5, 100.2]]], np.float32)
    gain = np.array([1.5, 1.2, 0.5])
    # 3 * 1.5 = 4.5 -> 4; 300 clipped to 255 before the gain: 127.5 -> 128 (not 150)
    np.testing.assert_array_equal(finish_frame(values, None, gain), [[[4, 255, 128], [0, 4, 50]]])
    noise = np.array([[[0.0, 10.0, -0.3], [-10.0, 0.0, 300.0]]], np.float32)
    np.testing.assert_array_equal(finish_frame(values, noise), [[[3, 255, 255], [0, 3, 255]]])
    np.testing.assert_array_equal(finish_frame(values, noise, gain),
                                  [[[4, 255, 128], [0, 4, 128]]])


def test_shapes_the_kernels_would_read_past_are_refused() -> None:
    from remote_site.sensor.shading import finish_frame, shade_frame

    model = PhotometricModel()
    surface = np.zeros((240, 320), np.float32)
    with pytest.raises(ValueError, match="noise"):
        shade_frame(surface, 0.06, model._albedo, model._weights, model._lights,
                    np.zeros((120, 320, 3), np.float32))
    with pytest.raises(ValueError, match="image"):
        shade_frame(surface, 0.06, model._albedo[:100], model._weights, model._lights, None)
    with pytest.raises(ValueError, match="weights"):
        shade_frame(surface, 0.06, model._albedo, model._weights[:3], model._lights, None)
    with pytest.raises(ValueError, match="noise"):
        finish_frame(np.zeros((4, 4, 3), np.float32), np.zeros((4, 3, 3), np.float32))
