"""Fit a stiffness calibration from presses on reference samples of known hardness.

A lab presses the sensor pad straight down into reference blocks and logs, per reading,
the normal force and the pad's indentation past first contact. ``presses.csv`` has the
columns ``sample,shore00,force_n,indentation_mm``: ``sample`` names the block, ``shore00``
is its known hardness, or ``rigid`` for a rigid block (metal, glass) that measures the gel
alone. Every block needs readings with ``indentation_mm > 0``.

The fit, per block: the slope of force on indentation through the origin,
``k = sum(F d) / sum(d^2)`` (gel and block in series). The rigid blocks give the gel's
stiffness ``k_gel``; every other block's tissue stiffness is ``1 / (1/k - 1/k_gel)``
(:func:`~remote_site.stiffness.estimator.compensate_gel`'s model). The (tissue N/mm,
Shore 00) pairs, sorted, are the monotone N/mm -> Shore 00 curve; a harder block that
measures softer than a softer one is refused, as is a block as stiff as the rigid one.
"""

from __future__ import annotations

import csv
import itertools
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from shared.errors import CalibrationError, InputDataError
from shared.hardness import StiffnessShoreCurve
from shared.stiffness_calibration import ReferenceSample, StiffnessCalibration

__all__ = ["PRESS_COLUMNS", "PressRecord", "fit_stiffness_calibration", "read_presses_csv",
           "write_presses_csv"]

PRESS_COLUMNS = ("sample", "shore00", "force_n", "indentation_mm")
_RIGID = "rigid"


@dataclass(frozen=True)
class PressRecord:
    """One reading of a press on a reference block.

    Attributes:
        sample: the block's name.
        shore00: its known Shore 00 hardness, None for a rigid block.
        force_n: measured normal force (N).
        indentation_mm: pad travel past first contact (mm), > 0.
    """

    sample: str
    shore00: float | None
    force_n: float
    indentation_mm: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.force_n) and math.isfinite(self.indentation_mm)):
            raise InputDataError(f"press on {self.sample!r}: force and indentation must be "
                                 "finite")
        if self.indentation_mm <= 0 or self.force_n < 0:
            raise InputDataError(f"press on {self.sample!r}: need indentation_mm > 0 and "
                                 "force_n >= 0")
        if self.shore00 is not None and not (math.isfinite(self.shore00)
                                             and 0.0 <= self.shore00 <= 100.0):
            raise InputDataError(f"press on {self.sample!r}: Shore 00 must lie in [0, 100]")


def read_presses_csv(path: str | os.PathLike[str]) -> list[PressRecord]:
    """Read ``presses.csv`` (see the module docstring).

    Raises:
        CalibrationError: a missing or unreadable file, or missing columns.
        InputDataError: a row with invalid values.
    """
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            missing = set(PRESS_COLUMNS) - set(reader.fieldnames or ())
            if missing:
                raise CalibrationError(f"{path}: missing column(s) {sorted(missing)}; "
                                       f"expected {','.join(PRESS_COLUMNS)}")
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise CalibrationError(f"cannot read the presses file {path}: {err}") from err
    records = []
    for line, row in enumerate(rows, start=2):
        try:
            shore_text = row["shore00"].strip()
            shore = None if shore_text.lower() == _RIGID else float(shore_text)
            records.append(PressRecord(row["sample"].strip(), shore, float(row["force_n"]),
                                       float(row["indentation_mm"])))
        except (AttributeError, ValueError) as err:
            raise InputDataError(f"{path}, line {line}: {err}") from err
    return records


def write_presses_csv(path: str | os.PathLike[str], records: Iterable[PressRecord]) -> None:
    """Write press records as ``presses.csv``.

    Raises:
        CalibrationError: the file cannot be written.
    """
    try:
        with open(path, "w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(PRESS_COLUMNS)
            for r in records:
                shore = _RIGID if r.shore00 is None else repr(r.shore00)
                writer.writerow([r.sample, shore, repr(r.force_n), repr(r.indentation_mm)])
    except OSError as err:
        raise CalibrationError(f"cannot write the presses file {path}: {err}") from err


def _slope_through_origin(records: Sequence[PressRecord]) -> float:
    d = np.array([r.indentation_mm for r in records])
    f = np.array([r.force_n for r in records])
    return float(np.dot(f, d) / np.dot(d, d))


def fit_stiffness_calibration(records: Iterable[PressRecord],
                              source: str = "") -> StiffnessCalibration:
    """Fit the gel stiffness and the N/mm -> Shore 00 curve (see the module docstring).

    Args:
        records: press readings on the reference blocks.
        source: free text stored in the calibration.

    Returns:
        The calibration.

    Raises:
        CalibrationError: no rigid block, fewer than two hardness blocks, a block with two
            hardnesses, a block as stiff as the rigid one, or a non-monotone set.
    """
    by_sample: dict[str, list[PressRecord]] = {}
    for r in records:
        by_sample.setdefault(r.sample, []).append(r)
    for name, rs in by_sample.items():
        if len({r.shore00 for r in rs}) != 1:
            raise CalibrationError(f"reference sample {name!r} is given two hardnesses")
    rigid = [r for rs in by_sample.values() for r in rs if r.shore00 is None]
    if not rigid:
        raise CalibrationError("no press on a rigid block (shore00 = rigid): the gel's "
                               "stiffness cannot be measured")
    k_gel = _slope_through_origin(rigid)
    if not (math.isfinite(k_gel) and k_gel > 0):
        raise CalibrationError(f"the rigid block gives a gel stiffness of {k_gel} N/mm")
    samples = [ReferenceSample(name, None, len(rs), _slope_through_origin(rs), 0.0)
               for name, rs in by_sample.items() if rs[0].shore00 is None]
    blocks = sorted(((rs[0].shore00, name, rs) for name, rs in by_sample.items()
                     if rs[0].shore00 is not None), key=lambda t: (t[0], t[1]))
    if len(blocks) < 2:
        raise CalibrationError("need presses on at least two reference blocks of known "
                               "hardness")
    points = []
    for shore, name, rs in blocks:
        k_meas = _slope_through_origin(rs)
        inv = 1.0 / k_meas - 1.0 / k_gel if k_meas > 0 else math.inf
        if not (math.isfinite(inv) and inv > 0):
            raise CalibrationError(f"reference sample {name!r} measures {k_meas:.4g} N/mm, "
                                   f"not softer than the gel ({k_gel:.4g} N/mm)")
        samples.append(ReferenceSample(name, shore, len(rs), k_meas, 1.0 / inv))
        points.append((1.0 / inv, shore))
    for (k0, s0), (k1, s1) in itertools.pairwise(points):
        if not (k1 > k0 and s1 > s0):
            raise CalibrationError(f"reference samples are not monotone: Shore 00 {s0:g} -> "
                                   f"{k0:.4g} N/mm but Shore 00 {s1:g} -> {k1:.4g} N/mm")
    return StiffnessCalibration(k_gel, StiffnessShoreCurve.from_points(points),
                                tuple(samples), source)
