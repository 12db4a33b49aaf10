"""Stiffness calibration of a probe: its gel compliance and its N/mm -> Shore 00 curve.

Made by ``teletouch sensor calibrate-stiffness`` from presses on reference samples of known
hardness (see :mod:`remote_site.stiffness.calibrate`), read by the remote station
(``--stiffness-calibration FILE``) and, for its N/mm -> k fallback, by the local station.

File format (JSON, UTF-8)::

    {
      "format": "teletouch-stiffness-calibration",
      "version": 1,
      "gel_stiffness_n_per_mm": 10.28,          # the sensor gel as one series spring
      "shore00_curve": [[0.05, 0.0], ...],      # (tissue N/mm, Shore 00), both increasing
      "reference_samples": [                    # what the fit saw (informative)
        {"sample": "block_20", "shore00": 20.0, "presses": 3,
         "k_measured_n_per_mm": 0.61, "k_tissue_n_per_mm": 0.65}, ...],
      "source": "free text: who/what produced it"
    }

Only ``format``, ``version``, ``gel_stiffness_n_per_mm`` and ``shore00_curve`` are
required. Any defect (unreadable file, other format or version, missing or invalid field)
raises :class:`~shared.errors.CalibrationError`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from shared.errors import CalibrationError, ConfigError
from shared.hardness import HardnessTable, StiffnessShoreCurve, StiffnessToK

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "ReferenceSample", "StiffnessCalibration"]

FORMAT_NAME = "teletouch-stiffness-calibration"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class ReferenceSample:
    """One reference sample as the calibration fit saw it.

    Attributes:
        sample: the sample's name.
        shore00: its known hardness (None: the rigid block that measures the gel alone).
        presses: how many press records it had.
        k_measured_n_per_mm: fitted force / indentation slope (gel and sample in series).
        k_tissue_n_per_mm: after removing the gel (0 for the rigid block).
    """

    sample: str
    shore00: float | None
    presses: int
    k_measured_n_per_mm: float
    k_tissue_n_per_mm: float


@dataclass(frozen=True)
class StiffnessCalibration:
    """A probe's stiffness calibration (see the module docstring for the file).

    Attributes:
        gel_stiffness_n_per_mm: the sensor gel as a series spring.
        shore_curve: tissue stiffness (N/mm) -> Shore 00.
        reference_samples: the fit's per-sample results (informative).
        source: free text describing the origin.

    Raises:
        CalibrationError: a non-finite or non-positive gel stiffness.
    """

    gel_stiffness_n_per_mm: float
    shore_curve: StiffnessShoreCurve
    reference_samples: tuple[ReferenceSample, ...] = ()
    source: str = ""
    version: int = field(default=FORMAT_VERSION)

    def __post_init__(self) -> None:
        gel = self.gel_stiffness_n_per_mm
        if not (isinstance(gel, int | float) and math.isfinite(gel) and gel > 0):
            raise CalibrationError(f"gel stiffness must be finite and > 0, got {gel!r}")

    def stiffness_to_k(self, table: HardnessTable | None = None) -> StiffnessToK:
        """The N/mm -> display k mapping with this calibration's curve."""
        return StiffnessToK(self.shore_curve, table or HardnessTable())

    def to_json(self) -> dict[str, Any]:
        """The file's content as a JSON-able dict."""
        return {
            "format": FORMAT_NAME,
            "version": self.version,
            "gel_stiffness_n_per_mm": self.gel_stiffness_n_per_mm,
            "shore00_curve": [list(p) for p in self.shore_curve.points],
            "reference_samples": [asdict(s) for s in self.reference_samples],
            "source": self.source,
        }

    def save(self, path: str | Path) -> Path:
        """Write the calibration file.

        Raises:
            CalibrationError: the file cannot be written.
        """
        out = Path(path)
        try:
            out.write_text(json.dumps(self.to_json(), indent=2) + "\n", encoding="utf-8")
        except OSError as err:
            raise CalibrationError(f"cannot write the stiffness calibration {out}: {err}") from err
        return out

    @classmethod
    def from_json(cls, data: Any, where: str = "stiffness calibration") -> StiffnessCalibration:
        """Validate and build a calibration from parsed JSON.

        Raises:
            CalibrationError: another format or version, a missing or invalid field.
        """
        if not isinstance(data, Mapping):
            raise CalibrationError(f"{where}: expected a JSON object")
        if data.get("format") != FORMAT_NAME:
            raise CalibrationError(f"{where}: not a {FORMAT_NAME} file "
                                   f"(format={data.get('format')!r})")
        if data.get("version") != FORMAT_VERSION:
            raise CalibrationError(f"{where}: unsupported version {data.get('version')!r} "
                                   f"(this build reads version {FORMAT_VERSION})")
        for key in ("gel_stiffness_n_per_mm", "shore00_curve"):
            if key not in data:
                raise CalibrationError(f"{where}: missing field {key!r}")
        gel = data["gel_stiffness_n_per_mm"]
        if isinstance(gel, bool) or not isinstance(gel, int | float):
            raise CalibrationError(f"{where}: gel_stiffness_n_per_mm must be a number")
        try:
            curve = StiffnessShoreCurve.from_points(_pairs(data["shore00_curve"]))
            samples = tuple(ReferenceSample(**s) for s in data.get("reference_samples", ()))
        except (ConfigError, TypeError, ValueError) as err:
            raise CalibrationError(f"{where}: {err}") from err
        return cls(float(gel), curve, samples, str(data.get("source", "")))

    @classmethod
    def load(cls, path: str | Path) -> StiffnessCalibration:
        """Read and validate a calibration file.

        Raises:
            CalibrationError: a missing or unreadable file, or invalid content.
        """
        src = Path(path)
        try:
            data = json.loads(src.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise CalibrationError(f"cannot read the stiffness calibration {src}: {err}") from err
        return cls.from_json(data, str(src))


def _pairs(value: Any) -> Sequence[Sequence[float]]:
    if not isinstance(value, list) or not all(isinstance(p, list) and len(p) == 2
                                              for p in value):
        raise ValueError("shore00_curve must be a list of [n_per_mm, shore00] pairs")
    return value
