"""Presses on simulated reference blocks, and the simulated world's stiffness calibration.

A lab calibrates the probe's stiffness by pressing the pad into reference blocks of known
Shore 00 hardness and into a rigid block (``teletouch sensor calibrate-stiffness``). The
simulator does the same with its own physics: each block is a plain
:class:`~remote_site.phantom.phantom.Phantom` (no tumors) whose silicone has the modulus that
reads that hardness on a type 00 durometer (:func:`durometer_modulus_kpa`), as thick as the
scenes' silicone layer, pressed at its centre by the default :class:`SensorPad`; the rigid
block has a modulus of 1e12 kPa (the gel then reads within 1e-8). The records go through the
calibration command; the result ships as package data,
``remote_site/phantom/data/sim_stiffness_calib.json`` (with the presses beside it),
regenerated with::

    python -m remote_site.phantom.reference_presses
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from remote_site.phantom.durometer import durometer_modulus_kpa
from remote_site.phantom.phantom import Phantom, SensorPad, SiliconeLayer
from remote_site.stiffness.calibrate import PressRecord, write_presses_csv
from shared.stiffness_calibration import StiffnessCalibration

__all__ = ["REFERENCE_SHORE00", "SIM_PRESSES_PATH", "SIM_STIFFNESS_CALIBRATION_PATH",
           "make_sim_stiffness_calibration", "reference_press_records",
           "sim_stiffness_calibration"]

log = logging.getLogger(__name__)

_DATA = Path(__file__).resolve().parent / "data"
SIM_STIFFNESS_CALIBRATION_PATH = _DATA / "sim_stiffness_calib.json"
SIM_PRESSES_PATH = _DATA / "sim_stiffness_presses.csv"
#: hardness of the simulated reference blocks (a dense set: simulated blocks are free)
REFERENCE_SHORE00: tuple[float, ...] = tuple(float(s) for s in np.arange(0.0, 100.0, 1.0))
RIGID_MODULUS_KPA = 1.0e12
PRESS_DEPTHS_MM: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0)
_BLOCK_SIZE_MM = (40.0, 40.0)


def _press(block: Phantom, name: str, shore00: float | None,
           depths_mm: Sequence[float]) -> list[PressRecord]:
    return [PressRecord(name, shore00, block.force_n((0.0, 0.0, -d)), float(d))
            for d in depths_mm]


def reference_press_records(shore00: Sequence[float] = REFERENCE_SHORE00,
                            pad: SensorPad | None = None,
                            thickness_mm: float | None = None,
                            depths_mm: Sequence[float] = PRESS_DEPTHS_MM) -> list[PressRecord]:
    """Press the simulated pad into a rigid block and into one block per hardness.

    Args:
        shore00: hardness of the reference blocks.
        pad: the sensor pad (default: the simulated sensor's).
        thickness_mm: block thickness (default: the scenes' silicone layer).
        depths_mm: indentations of the presses on every block.

    Returns:
        The press records, rigid block first.
    """
    pad = pad or SensorPad()
    thickness = SiliconeLayer().thickness_mm if thickness_mm is None else thickness_mm

    def block(modulus_kpa: float) -> Phantom:
        return Phantom(SiliconeLayer(_BLOCK_SIZE_MM, thickness, modulus_kpa), pad=pad,
                       name="reference_block", table_step_mm=1.0)

    records = _press(block(RIGID_MODULUS_KPA), "rigid", None, depths_mm)
    for shore, modulus in zip(shore00, durometer_modulus_kpa(shore00), strict=True):
        records += _press(block(float(modulus)), f"shore00_{shore:g}", float(shore), depths_mm)
    return records


def make_sim_stiffness_calibration(out: str | Path, presses_out: str | Path | None = None
                                   ) -> StiffnessCalibration:
    """Write the simulated presses and run ``teletouch sensor calibrate-stiffness`` on them.

    Args:
        out: the calibration file to write (JSON).
        presses_out: where to keep the presses CSV (a temporary file when None).

    Returns:
        The calibration written.
    """
    from remote_site import sensor_cli  # the same code path as the command line

    with tempfile.TemporaryDirectory() as tmp:
        presses = Path(presses_out) if presses_out else Path(tmp) / "presses.csv"
        write_presses_csv(presses, reference_press_records())
        parser = argparse.ArgumentParser()
        sensor_cli.configure_parser(parser)
        args = parser.parse_args(["calibrate-stiffness", "--presses", str(presses),
                                  "--out", str(out), "--source",
                                  "simulated reference blocks (remote_site.phantom."
                                  "reference_presses)", "--quiet"])
        sensor_cli.run(args)
    return StiffnessCalibration.load(out)


def sim_stiffness_calibration() -> StiffnessCalibration:
    """The shipped stiffness calibration of the simulated probe (the sim world's default).

    Raises:
        CalibrationError: the shipped file is missing or invalid.
    """
    return StiffnessCalibration.load(SIM_STIFFNESS_CALIBRATION_PATH)


def main() -> int:
    """Regenerate the shipped simulated stiffness calibration and its presses."""
    logging.basicConfig(level=logging.INFO)
    make_sim_stiffness_calibration(SIM_STIFFNESS_CALIBRATION_PATH, SIM_PRESSES_PATH)
    log.info("wrote %s and %s", SIM_STIFFNESS_CALIBRATION_PATH, SIM_PRESSES_PATH)
    return 0


if __name__ == "__main__":
    sys.exit(main())
