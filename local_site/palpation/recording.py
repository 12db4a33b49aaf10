"""What the local station received, as arrays: the input of the palpation analysis.

The station agent writes it with ``--record PATH.npz`` (format in ``docs/recording.md``);
:func:`load_recording` reads and validates it, and tests build a :class:`Recording`
directly.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from shared.errors import InputDataError

__all__ = ["Recording", "load_recording"]

_FRAME_KEYS = ("frame_rx_us", "frame_seq", "frame_center_mm", "frame_pitch_mm", "frame_contact",
               "frame_force_n", "frame_indentation_mm", "frame_height_mm")


@dataclass(frozen=True, eq=False)
class Recording:
    """Platform samples sent and tactile frames accepted by the local station.

    Attributes:
        platform_t_us: (P,) sample times (local clock).
        platform_mm: (P, 3) platform positions sent.
        frame_center_mm: (N, 2) patch centres, platform coordinates.
        frame_pitch_mm: (N,) patch pitch, platform mm.
        frame_contact: (N,) bool.
        frame_force_n: (N,) normal force.
        frame_indentation_mm: (N,) probe indentation.
        frame_height_mm: (N, H, W) height patches.
        frame_rx_us: (N,) receive times (local clock).
        frame_seq: (N,) tactile frame sequence numbers.
        meta: free-form metadata (session, workspace settings, counts).
    """

    platform_t_us: NDArray[np.int64]
    platform_mm: NDArray[np.float64]
    frame_center_mm: NDArray[np.float64]
    frame_pitch_mm: NDArray[np.float64]
    frame_contact: NDArray[np.bool_]
    frame_force_n: NDArray[np.float64]
    frame_indentation_mm: NDArray[np.float64]
    frame_height_mm: NDArray[np.float32]
    frame_rx_us: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    frame_seq: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.frame_center_mm.shape[0]
        checks = {
            "frame_center_mm": self.frame_center_mm.shape == (n, 2),
            "frame_pitch_mm": self.frame_pitch_mm.shape == (n,),
            "frame_contact": self.frame_contact.shape == (n,),
            "frame_force_n": self.frame_force_n.shape == (n,),
            "frame_indentation_mm": self.frame_indentation_mm.shape == (n,),
            "frame_height_mm": self.frame_height_mm.ndim == 3
            and self.frame_height_mm.shape[0] == n,
            "platform_mm": self.platform_mm.ndim == 2 and self.platform_mm.shape[1] == 3,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise InputDataError(f"recording arrays of inconsistent shape: {bad} ({n} frames)")
        for name in ("frame_center_mm", "frame_pitch_mm", "frame_force_n",
                     "frame_indentation_mm", "frame_height_mm", "platform_mm"):
            if not np.isfinite(getattr(self, name)).all():
                raise InputDataError(f"recording array {name} has NaN or Inf")
        if n and not (self.frame_pitch_mm > 0).all():
            raise InputDataError("recording frame_pitch_mm must be > 0")

    @property
    def frames(self) -> int:
        """Number of tactile frames."""
        return int(self.frame_center_mm.shape[0])


def load_recording(path: str | Path) -> Recording:
    """Read a recording written by the local station agent.

    Raises:
        InputDataError: missing file, missing keys, inconsistent or non-finite arrays.
    """
    p = Path(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            missing = [k for k in (*_FRAME_KEYS, "platform_t_us", "platform_mm") if k not in z]
            if missing:
                raise InputDataError(f"{p}: not a Tele-Touch recording, missing {missing}")
            meta_raw = str(z["meta_json"]) if "meta_json" in z else "{}"
            arrays = {k: np.asarray(z[k]) for k in (*_FRAME_KEYS, "platform_t_us", "platform_mm")}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise InputDataError(f"cannot read recording {p}: {err}") from err
    try:
        meta = json.loads(meta_raw)
    except json.JSONDecodeError as err:
        raise InputDataError(f"{p}: meta_json is not JSON: {err}") from err
    return Recording(
        platform_t_us=arrays["platform_t_us"].astype(np.int64),
        platform_mm=arrays["platform_mm"].astype(np.float64).reshape(-1, 3),
        frame_center_mm=arrays["frame_center_mm"].astype(np.float64).reshape(-1, 2),
        frame_pitch_mm=arrays["frame_pitch_mm"].astype(np.float64),
        frame_contact=arrays["frame_contact"].astype(bool),
        frame_force_n=arrays["frame_force_n"].astype(np.float64),
        frame_indentation_mm=arrays["frame_indentation_mm"].astype(np.float64),
        frame_height_mm=arrays["frame_height_mm"].astype(np.float32),
        frame_rx_us=arrays["frame_rx_us"].astype(np.int64),
        frame_seq=arrays["frame_seq"].astype(np.int64),
        meta=meta if isinstance(meta, dict) else {"meta": meta},
    )
