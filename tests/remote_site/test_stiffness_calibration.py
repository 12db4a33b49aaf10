"""Stiffness calibration: fit from reference presses, the file, the command, the sim's file."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from lab.cli import main as teletouch
from remote_site.phantom.durometer import durometer_modulus_kpa
from remote_site.phantom.mechanics import punch_stiffness_n_per_mm
from remote_site.phantom.phantom import SensorPad, SiliconeLayer
from remote_site.phantom.reference_presses import (
    SIM_STIFFNESS_CALIBRATION_PATH,
    make_sim_stiffness_calibration,
    sim_stiffness_calibration,
)
from remote_site.stiffness.calibrate import (
    PressRecord,
    fit_stiffness_calibration,
    read_presses_csv,
    write_presses_csv,
)
from shared.errors import CalibrationError, InputDataError
from shared.hardness import HardnessTable
from shared.stiffness_calibration import StiffnessCalibration

K_GEL = 8.0
#: (Shore 00, tissue N/mm) of three made-up reference blocks
BLOCKS = ((10.0, 0.5), (40.0, 2.0), (80.0, 6.0))


def _records(noise: float = 0.0, seed: int = 0) -> list[PressRecord]:
    rng = np.random.default_rng(seed)
    records = []
    for d in (0.5, 1.0, 1.5):
        records.append(PressRecord("steel", None, K_GEL * d + rng.normal(0, noise), d))
        for shore, k_t in BLOCKS:
            k_series = 1.0 / (1.0 / k_t + 1.0 / K_GEL)
            records.append(PressRecord(f"block{shore:g}", shore,
                                       k_series * d + rng.normal(0, noise), d))
    return records


def test_fit_recovers_gel_and_curve_and_round_trips(tmp_path: Path) -> None:
    calib = fit_stiffness_calibration(_records(), source="unit test")
    assert calib.gel_stiffness_n_per_mm == pytest.approx(K_GEL)
    np.testing.assert_allclose(calib.shore_curve.points, [(k, s) for s, k in BLOCKS])
    to_k = calib.stiffness_to_k()
    assert to_k.shore00([0.5, 2.0, 6.0]).tolist() == pytest.approx([10.0, 40.0, 80.0])
    assert to_k.shore00([0.0, 0.1, 100.0]).tolist() == pytest.approx([10.0, 10.0, 80.0])
    assert to_k.shore00(1.0) == pytest.approx(10.0 + 30.0 * math.log(2.0) / math.log(4.0))
    path = calib.save(tmp_path / "stiffness.json")
    assert StiffnessCalibration.load(path) == calib
    presses = tmp_path / "presses.csv"
    write_presses_csv(presses, _records())
    assert read_presses_csv(presses) == _records()


def test_fit_refuses_unusable_reference_sets() -> None:
    records = _records()
    with pytest.raises(CalibrationError, match="rigid"):
        fit_stiffness_calibration([r for r in records if r.shore00 is not None])
    with pytest.raises(CalibrationError, match="at least two"):
        fit_stiffness_calibration([r for r in records if r.shore00 in (None, 10.0)])
    swapped = [PressRecord(r.sample, 90.0 if r.shore00 == 10.0 else r.shore00, r.force_n,
                           r.indentation_mm) for r in records]
    with pytest.raises(CalibrationError, match="not monotone"):
        fit_stiffness_calibration(swapped)
    too_stiff = [*records, PressRecord("glass", 95.0, K_GEL * 1.0, 1.0)]
    with pytest.raises(CalibrationError, match="not softer than the gel"):
        fit_stiffness_calibration(too_stiff)
    with pytest.raises(InputDataError):
        PressRecord("x", 20.0, 1.0, 0.0)
    with pytest.raises(InputDataError):
        PressRecord("x", 120.0, 1.0, 1.0)


def test_bad_files_are_calibration_errors(tmp_path: Path) -> None:
    good = fit_stiffness_calibration(_records()).to_json()
    cases = {
        "missing.json": None,
        "garbage.json": "{not json",
        "format.json": json.dumps({**good, "format": "something-else"}),
        "version.json": json.dumps({**good, "version": 99}),
        "no_gel.json": json.dumps({k: v for k, v in good.items()
                                   if k != "gel_stiffness_n_per_mm"}),
        "bad_gel.json": json.dumps({**good, "gel_stiffness_n_per_mm": -1.0}),
        "bad_curve.json": json.dumps({**good, "shore00_curve": [[1.0, 50.0], [2.0, 40.0]]}),
        "short_curve.json": json.dumps({**good, "shore00_curve": [[1.0, 50.0]]}),
    }
    for name, text in cases.items():
        path = tmp_path / name
        if text is not None:
            path.write_text(text)
        with pytest.raises(CalibrationError):
            StiffnessCalibration.load(path)
    bad_csv = tmp_path / "presses.csv"
    bad_csv.write_text("sample,force_n\nx,1.0\n")
    with pytest.raises(CalibrationError, match="missing column"):
        read_presses_csv(bad_csv)
    bad_csv.write_text("sample,shore00,force_n,indentation_mm\nx,soft,1.0,1.0\n")
    with pytest.raises(InputDataError, match="line 2"):
        read_presses_csv(bad_csv)


def test_calibrate_stiffness_command(tmp_path: Path) -> None:
    presses, out = tmp_path / "presses.csv", tmp_path / "stiffness.json"
    write_presses_csv(presses, _records(noise=0.002))
    assert teletouch(["sensor", "calibrate-stiffness", "--presses", str(presses),
                      "--out", str(out), "--quiet"]) == 0
    calib = StiffnessCalibration.load(out)
    assert calib.gel_stiffness_n_per_mm == pytest.approx(K_GEL, rel=1e-3)
    assert [p[1] for p in calib.shore_curve.points] == [10.0, 40.0, 80.0]


def test_shipped_sim_calibration_is_reproduced_by_the_command(tmp_path: Path) -> None:
    shipped = sim_stiffness_calibration()
    fresh = make_sim_stiffness_calibration(tmp_path / "sim.json", tmp_path / "presses.csv")
    assert fresh.gel_stiffness_n_per_mm == pytest.approx(shipped.gel_stiffness_n_per_mm,
                                                         rel=1e-9)
    np.testing.assert_allclose(fresh.shore_curve.points, shipped.shore_curve.points,
                               rtol=1e-9)
    assert SIM_STIFFNESS_CALIBRATION_PATH.is_file()
    # the sim gel is the simulated pad's, to the rigid block's 1e-8
    assert shipped.gel_stiffness_n_per_mm == pytest.approx(
        SensorPad().gel_stiffness_n_per_mm, rel=1e-8)


def _previous_remote_k(k_n_per_mm: np.ndarray) -> np.ndarray:
    """The remote mapping before calibration data: the phantom's punch model inverted with
    the sim pad and layer, then the durometer model, then the hardness table."""
    unit = float(punch_stiffness_n_per_mm(1.0, SensorPad().effective_radius_mm,
                                          SiliconeLayer().thickness_mm))
    shore_tab = np.linspace(0.0, 99.9, 2000)
    mod_tab = durometer_modulus_kpa(shore_tab)
    e = k_n_per_mm / unit
    shore = np.interp(np.log(np.maximum(e, 1e-9)), np.log(mod_tab), shore_tab,
                      left=0.0, right=100.0)
    return np.clip(HardnessTable().shore00_to_k(shore), 0.5, 1.0)


def _previous_local_k(k_n_per_mm: np.ndarray) -> np.ndarray:
    """The local scene's former linear mapping of (0.05, 2.0) N/mm onto k in [0.5, 1]."""
    return 0.5 + 0.5 * np.clip((k_n_per_mm - 0.05) / (2.0 - 0.05), 0.0, 1.0)


def test_one_mapping_renders_what_the_remote_rendered() -> None:
    """The pins rendered the remote's mapping (frames carry stiffness_k); the shared mapping
    with the shipped sim calibration reproduces it; the local fallback differed."""
    grid = np.concatenate([[0.0], np.geomspace(1e-3, 1e4, 4000)])
    new_k = sim_stiffness_calibration().stiffness_to_k().k(grid)
    np.testing.assert_allclose(new_k, _previous_remote_k(grid), atol=1e-4)
    assert np.abs(new_k - _previous_local_k(grid)).max() > 0.1
