"""Bad input never crashes and never yields NaN: frames, calibrations, labels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from lab.cli import main as cli_main
from remote_site.reconstruction.calibration import CALIBRATION_VERSION, Calibration, fit_calibration
from remote_site.reconstruction.frames import load_rgb, validate_frame
from remote_site.reconstruction.labels import BallLabel, read_labels_csv
from remote_site.reconstruction.reconstructor import ReconstructionSettings, Reconstructor
from remote_site.sensor.photometric import PhotometricModel
from remote_site.sensor.sim_calibration import SIM_CALIBRATION_PATH, simulated_calibration
from shared.errors import CalibrationError, ConfigError, InputDataError


@pytest.fixture(scope="module")
def rec() -> Reconstructor:
    return Reconstructor(simulated_calibration())


@pytest.fixture(scope="module")
def background() -> np.ndarray:
    return PhotometricModel().background_rgb


# --------------------------------------------------------------------------- frames


@pytest.mark.parametrize("frame", [
    np.zeros((240, 320), np.uint8),
    np.zeros((240, 320, 4), np.uint8),
    np.full((120, 160, 3), 120, np.uint8),
    np.full((240, 320, 3), 120, np.int32),
    np.full((240, 320, 3), 300.0),
    [[1, 2, 3]],
])
def test_wrong_frames_rejected(rec: Reconstructor, frame: object) -> None:
    with pytest.raises(InputDataError):
        rec.height_map(frame)  # type: ignore[arg-type]


def test_saturated_and_black_frames_rejected(rec: Reconstructor) -> None:
    with pytest.raises(InputDataError, match="saturated"):
        rec.height_map(np.full((240, 320, 3), 255, np.uint8))
    with pytest.raises(InputDataError, match="black"):
        rec.height_map(np.zeros((240, 320, 3), np.uint8))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_anywhere_rejected(rec: Reconstructor, background: np.ndarray, bad: float) -> None:
    frame = background.astype(np.float64)
    frame[17, 200, 1] = bad
    with pytest.raises(InputDataError, match="NaN"):
        rec.height_map(frame)
    with pytest.raises(InputDataError, match="NaN"):
        rec.height_map(background, background=frame)


def test_float_frames_accepted(rec: Reconstructor, background: np.ndarray) -> None:
    hm = rec.height_map(background.astype(np.float32))
    assert hm.skipped and np.isfinite(hm.height_mm).all()


def test_foreign_background_rejected(rec: Reconstructor, background: np.ndarray) -> None:
    with pytest.raises(InputDataError):
        rec.height_map(background, background=background[:100])


@pytest.mark.parametrize("pitch", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_output_pitch_rejected(rec: Reconstructor, background: np.ndarray,
                                   pitch: float) -> None:
    with pytest.raises(InputDataError):
        rec.height_map(background, out_pitch_mm=pitch)


def test_huge_output_pitch_is_clamped(rec: Reconstructor, background: np.ndarray) -> None:
    hm = rec.height_map(background, out_pitch_mm=1e6)
    assert min(hm.height_mm.shape) >= 2


def test_bad_settings_rejected() -> None:
    with pytest.raises(ConfigError):
        ReconstructionSettings(solver="sor")
    with pytest.raises(ConfigError):
        ReconstructionSettings(contact_threshold_mm=float("nan"))


@settings(max_examples=30, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(level=st.integers(20, 230), shape=st.sampled_from([(8, 8), (9, 31), (240, 320),
                                                          (480, 640)]))
def test_flat_frames_give_zero_height(level: int, shape: tuple[int, int]) -> None:
    bg = np.full((*shape, 3), level, np.uint8)
    drift = np.clip(np.rint(bg * 0.9), 0, 255).astype(np.uint8)  # global brightness drift
    calib = simulated_calibration()
    calib = Calibration(calib.model, bg, calib.mm_per_px, calib.blur_sigma_px, calib.noise_pct)
    hm = Reconstructor(calib).height_map(drift)
    assert hm.height_mm.shape == shape
    assert np.abs(hm.height_mm).max() == 0.0 and not hm.contact


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(noise=arrays(np.uint8, (240, 320, 3), elements=st.integers(4, 250)))
def test_arbitrary_frames_give_finite_bounded_heights(rec: Reconstructor,
                                                       noise: np.ndarray) -> None:
    try:
        hm = rec.height_map(noise)
    except InputDataError:
        return  # implausible brightness gain: rejected, fine
    assert np.isfinite(hm.height_mm).all()
    # slopes are clipped to 5: heights are bounded by the frame's extent
    assert np.abs(hm.height_mm).max() < 5 * 0.0634 * (240 + 320)


def test_extreme_contrast_frame_stays_finite(rec: Reconstructor, background: np.ndarray) -> None:
    frame = background.copy()
    frame[100:140, 100:180] = [250, 5, 250]  # far outside the calibrated colours
    # it reads 8.7 mm deep: more than a gel is thick, so it is refused by name ...
    with pytest.raises(InputDataError, match="max_height_mm"):
        rec.height_map(frame)
    # ... and without that check the heights are still finite
    unchecked = Reconstructor(rec.calibration, ReconstructionSettings(max_height_mm=np.inf))
    hm = unchecked.height_map(frame)
    assert np.isfinite(hm.height_mm).all() and hm.contact


# --------------------------------------------------------------------------- calibration files


def test_missing_calibration_file(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="not found"):
        Reconstructor.from_file(tmp_path / "nope.npz")


def test_garbage_calibration_file(tmp_path: Path) -> None:
    path = tmp_path / "garbage.npz"
    path.write_bytes(b"not an npz")
    with pytest.raises(CalibrationError):
        Calibration.load(path)


def _rewrite(tmp_path: Path, **changes: np.ndarray) -> Path:
    with np.load(SIM_CALIBRATION_PATH) as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update(changes)
    for key in [k for k, v in changes.items() if v is None]:
        del arrays[key]
    path = tmp_path / "changed.npz"
    np.savez(path, **arrays)
    return path


def test_wrong_version_rejected(tmp_path: Path) -> None:
    path = _rewrite(tmp_path, version=np.array(CALIBRATION_VERSION + 1))
    with pytest.raises(CalibrationError, match="version"):
        Calibration.load(path)


def test_a_rim_calibration_says_version_2_and_version_1_cannot_claim_it(tmp_path: Path) -> None:
    calib = Calibration.load(SIM_CALIBRATION_PATH)
    calib.save(tmp_path / "plane.npz")
    assert int(np.load(tmp_path / "plane.npz")["version"]) == 1  # older readers read it
    rim = _rewrite(tmp_path, version=np.array(1), relief=np.array("rim"),
                   rim_factors=np.array([1], np.int64), rim_extension_mm=np.array([0.01]))
    with pytest.raises(CalibrationError, match="version 1"):
        Calibration.load(rim)
    calib.relief, calib.rim_extension_mm = "rim", {1: 0.01}
    calib.save(tmp_path / "rim.npz")
    assert int(np.load(tmp_path / "rim.npz")["version"]) == 2
    assert Calibration.load(tmp_path / "rim.npz").relief == "rim"


def test_mismatched_background_shape_rejected(tmp_path: Path) -> None:
    path = _rewrite(tmp_path, background_rgb=np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(CalibrationError, match="shape"):
        Calibration.load(path)


def test_missing_key_rejected(tmp_path: Path) -> None:
    path = _rewrite(tmp_path, noise_pct=None)  # type: ignore[arg-type]
    with pytest.raises(CalibrationError, match="missing"):
        Calibration.load(path)


def test_model_array_mismatch_rejected(tmp_path: Path) -> None:
    path = _rewrite(tmp_path, model_coef=np.zeros((7, 2), np.float32))
    with pytest.raises(CalibrationError):
        Calibration.load(path)


def test_frame_of_other_sensor_size_rejected(rec: Reconstructor) -> None:
    with pytest.raises(InputDataError, match="does not match"):
        rec.height_map(np.full((300, 400, 3), 120, np.uint8))


# --------------------------------------------------------------------------- labels


@pytest.mark.parametrize("label", [
    BallLabel("a.png", 400.0, 100.0, 30.0),     # centre outside the frame
    BallLabel("a.png", 100.0, -5.0, 30.0),
    BallLabel("a.png", 100.0, 100.0, 2.0),      # too small after trimming
    BallLabel("a.png", 100.0, float("nan"), 30.0),
])
def test_labels_that_do_not_fit_rejected(background: np.ndarray, label: BallLabel) -> None:
    with pytest.raises(InputDataError):
        fit_calibration(background, [(background, label)], 4.0, 0.0634)


def test_contact_larger_than_ball_rejected(background: np.ndarray) -> None:
    with pytest.raises(CalibrationError):
        fit_calibration(background, [(background, BallLabel("a.png", 100, 100, 60))], 4.0, 0.0634)


def test_press_of_wrong_size_rejected(background: np.ndarray) -> None:
    with pytest.raises(InputDataError):
        fit_calibration(background, [(background[:200], BallLabel("a.png", 100, 100, 20))],
                        4.0, 0.0634)


@pytest.mark.parametrize(("text", "match"), [
    ("image,center_x,center_y\na.png,1,2\n", "missing column"),
    ("image,center_x,center_y,radius_px\na.png,1,x,3\n", "bad number"),
    ("image,center_x,center_y,radius_px\na.png,1,2,3\na.png,1,2,3\n", "twice"),
    ("image,center_x,center_y,radius_px\n", "no labels"),
])
def test_bad_labels_csv(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "labels.csv"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=match):
        read_labels_csv(path)


def test_cli_calibrate_with_missing_image_fails_cleanly(tmp_path: Path,
                                                       background: np.ndarray) -> None:
    import cv2

    cv2.imwrite(str(tmp_path / "bg.png"), background[:, :, ::-1])
    (tmp_path / "labels.csv").write_text(
        "image,center_x,center_y,radius_px\nmissing.png,50,50,20\n")
    rc = cli_main(["sensor", "calibrate", "--background", str(tmp_path / "bg.png"), "--images",
                   str(tmp_path), "--labels", str(tmp_path / "labels.csv"),
                   "--ball-diameter-mm", "4", "--mm-per-px", "0.0634",
                   "--out", str(tmp_path / "c.npz")])
    assert rc == 1
    assert not (tmp_path / "c.npz").exists()


def test_load_rgb_errors(tmp_path: Path) -> None:
    with pytest.raises(InputDataError):
        load_rgb(tmp_path / "none.png")
    (tmp_path / "x.png").write_bytes(b"no png")
    with pytest.raises(InputDataError):
        load_rgb(tmp_path / "x.png")


def test_validate_frame_returns_float32(background: np.ndarray) -> None:
    out = validate_frame(background)
    assert out.dtype == np.float32 and out.shape == background.shape


def test_the_sensor_cli_offers_every_relief_mode() -> None:
    import argparse

    from remote_site.reconstruction.relief import RELIEF_MODES
    from remote_site.sensor_cli import configure_parser

    parser = argparse.ArgumentParser()
    configure_parser(parser)
    for mode in RELIEF_MODES:
        args = parser.parse_args(["calibrate", "--background", "b.png", "--images", "i",
                                  "--labels", "l.csv", "--ball-diameter-mm", "4",
                                  "--mm-per-px", "0.06", "--out", "c.npz", "--relief", mode])
        assert args.relief == mode


def test_the_sensor_cli_offers_every_centres_setting_and_defaults_to_the_edge() -> None:
    import argparse

    from remote_site.reconstruction.calibration import CENTRES
    from remote_site.sensor_cli import configure_parser

    parser = argparse.ArgumentParser()
    configure_parser(parser)
    base = ["calibrate", "--background", "b.png", "--images", "i", "--labels", "l.csv",
            "--ball-diameter-mm", "4", "--mm-per-px", "0.06", "--out", "c.npz"]
    assert parser.parse_args(base).centres == CENTRES[0] == "edge"
    for centres in CENTRES:
        assert parser.parse_args([*base, "--centres", centres]).centres == centres


@pytest.mark.parametrize("pitch", [None, 1.0])
def test_a_background_passed_is_used_as_it_is_now(background: np.ndarray,
                                                  pitch: float | None) -> None:
    """The background given with a frame is the one used, at full resolution and pooled:
    a buffer updated in place is read again, and a new temporary that takes a freed array's
    address is not taken for it (found by an audit: both reconstructed against the old one,
    0.46 mm of relief from a frame equal to its background)."""
    rec = Reconstructor(simulated_calibration())
    pressed = background.astype(np.float32)
    pressed[100:140, 140:180] = np.clip(pressed[100:140, 140:180] * [1.3, 0.8, 1.1], 0, 255)
    assert np.abs(rec.height_map(pressed, out_pitch_mm=pitch).height_mm).max() > 0.01
    buf = background.astype(np.float32)
    assert np.abs(rec.height_map(pressed, background=buf, out_pitch_mm=pitch)
                  .height_mm).max() > 0.01
    buf[:] = pressed  # a running background that caught up with the frame
    assert np.abs(rec.height_map(pressed, background=buf, out_pitch_mm=pitch)
                  .height_mm).max() == 0.0
    for _ in range(3):  # temporaries, each freed after its call
        rec.height_map(pressed, background=background.astype(np.float32), out_pitch_mm=pitch)
        flat = rec.height_map(pressed, background=pressed.copy(), out_pitch_mm=pitch)
        assert np.abs(flat.height_mm).max() == 0.0
