"""The local station's recording (``teletouch local --record PATH.npz``).

What the lead's palpation analysis reads (the agents contract), written once at exit with
``np.savez_compressed``:

==========================  ===============  ===========================================
key                         shape, dtype     content
==========================  ===============  ===========================================
``platform_t_us``           (P,) int64       sample time of each platform_state sent
``platform_mm``             (P, 3) float64   its position (platform frame)
``frame_rx_us``             (N,) int64       arrival time (``local.station_rx`` stamp)
``frame_seq``               (N,) int64       the tactile frame's ``seq``
``frame_center_mm``         (N, 2) float64   grid centre (platform frame)
``frame_pitch_mm``          (N,) float64     grid pitch
``frame_contact``           (N,) bool        probe in contact
``frame_force_n``           (N,) float64     measured normal force
``frame_indentation_mm``    (N,) float64     measured indentation
``frame_height_mm``         (N, H, W) f32    height layer
``frame_stiffness_k``       (N, H, W) f32    display k (1.0 where the frame had none)
``frame_stiffness_n_per_mm`` (N, H, W) f32   measured stiffness (0 where absent)
``meta_json``               str              JSON: session, workspace, layer shape, counts
==========================  ===============  ===========================================

Only frames the station ACCEPTED are recorded. All frames of a run share the first frame's
(H, W); a frame of another shape is not recorded and counted in
``frames_rejected_shape``. Memory is bounded: after ``max_frames`` frames (or
``max_platform_samples`` samples) recording stops and the overflow is counted.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from shared.errors import ConfigError, InputDataError
from shared.protocol import TactileFrame
from shared.report import to_jsonable

__all__ = ["RECORD_KEYS", "Recording", "SessionRecorder", "load_recording"]

log = logging.getLogger(__name__)

RECORD_KEYS = ("platform_t_us", "platform_mm", "frame_rx_us", "frame_seq", "frame_center_mm",
               "frame_pitch_mm", "frame_contact", "frame_force_n", "frame_indentation_mm",
               "frame_height_mm", "frame_stiffness_k", "frame_stiffness_n_per_mm",
               "meta_json")


class SessionRecorder:
    """Collects platform samples and accepted tactile frames; writes the contract's ``.npz``.

    Thread-safe: platform samples and frames may be added from different threads.

    Args:
        max_frames: tactile frames kept (then counted in ``frames_dropped_limit``).
        max_platform_samples: platform samples kept (then ``platform_dropped_limit``).

    Raises:
        ConfigError: negative limits.
    """

    def __init__(self, max_frames: int = 20_000, max_platform_samples: int = 1_000_000) -> None:
        if max_frames < 0 or max_platform_samples < 0:
            raise ConfigError("recording limits must be >= 0")
        self.max_frames = int(max_frames)
        self.max_platform_samples = int(max_platform_samples)
        self._lock = threading.Lock()
        self._platform_t: list[int] = []
        self._platform_mm: list[tuple[float, float, float]] = []
        self._frames: list[tuple[Any, ...]] = []
        self._shape: tuple[int, int] | None = None
        self.frames_dropped_limit = 0
        self.frames_rejected_shape = 0
        self.platform_dropped_limit = 0

    @property
    def frames(self) -> int:
        """Tactile frames recorded so far."""
        return len(self._frames)

    @property
    def platform_samples(self) -> int:
        """Platform samples recorded so far."""
        return len(self._platform_t)

    @property
    def layer_shape(self) -> tuple[int, int] | None:
        """(H, W) of the recorded layers (the first frame's), None before any frame."""
        return self._shape

    def add_platform(self, t_us: int, position_mm: Sequence[float]) -> bool:
        """Record one platform sample that was sent as a platform_state.

        Returns:
            False when the limit is reached (the sample is counted, not kept).
        """
        with self._lock:
            if len(self._platform_t) >= self.max_platform_samples:
                self.platform_dropped_limit += 1
                return False
            x, y, z = (float(v) for v in position_mm)
            self._platform_t.append(int(t_us))
            self._platform_mm.append((x, y, z))
            return True

    def add_frame(self, frame: TactileFrame, rx_us: int) -> bool:
        """Record one accepted tactile frame (its layers are copied).

        Args:
            frame: the frame, already accepted by the scene.
            rx_us: its arrival time (local wall clock, microseconds).

        Returns:
            False when it was not kept: limit reached, or a layer shape other than the
            first frame's (counted in ``frames_dropped_limit`` / ``frames_rejected_shape``).

        Raises:
            InputDataError: the frame has no 2-D ``height_mm`` layer.
        """
        height = frame.layers.get("height_mm")
        if not isinstance(height, np.ndarray) or height.ndim != 2:
            raise InputDataError("a recorded tactile frame needs a 2-D height_mm layer")
        shape = (int(height.shape[0]), int(height.shape[1]))
        k = frame.layers.get("stiffness_k")
        n = frame.layers.get("stiffness_n_per_mm")
        with self._lock:
            if len(self._frames) >= self.max_frames:
                self.frames_dropped_limit += 1
                return False
            if self._shape is None:
                self._shape = shape
            elif shape != self._shape:
                self.frames_rejected_shape += 1
                return False
            self._frames.append((
                int(rx_us), int(frame.seq), tuple(float(c) for c in frame.center_mm),
                float(frame.pitch_mm), bool(frame.contact), float(frame.force_n),
                float(frame.indentation_mm), height.astype(np.float32),
                (k.astype(np.float32) if isinstance(k, np.ndarray)
                 else np.ones(shape, np.float32)),
                (n.astype(np.float32) if isinstance(n, np.ndarray)
                 else np.zeros(shape, np.float32))))
            return True

    def counts(self) -> dict[str, int]:
        """Recorded and dropped counts (for the summary and ``meta_json``)."""
        return {"frames": self.frames, "platform_samples": self.platform_samples,
                "frames_dropped_limit": self.frames_dropped_limit,
                "frames_rejected_shape": self.frames_rejected_shape,
                "platform_dropped_limit": self.platform_dropped_limit}

    def arrays(self, meta: Mapping[str, Any] | None = None) -> dict[str, np.ndarray]:
        """The recording as the contract's arrays (``meta`` goes into ``meta_json``)."""
        with self._lock:
            frames = list(self._frames)
            p_t = np.asarray(self._platform_t, dtype=np.int64)
            p_mm = np.asarray(self._platform_mm, dtype=np.float64).reshape(-1, 3)
            shape = self._shape or (0, 0)
            counts = self.counts()
        cols = list(zip(*frames, strict=True)) if frames else [()] * 10

        def stack(i: int) -> np.ndarray:
            return (np.stack(cols[i]).astype(np.float32) if frames
                    else np.zeros((0, *shape), np.float32))

        meta_doc = dict(meta or {})
        meta_doc.update(layer_shape=list(shape), counts=counts)
        return {
            "platform_t_us": p_t, "platform_mm": p_mm,
            "frame_rx_us": np.asarray(cols[0], dtype=np.int64),
            "frame_seq": np.asarray(cols[1], dtype=np.int64),
            "frame_center_mm": np.asarray(cols[2], dtype=np.float64).reshape(-1, 2),
            "frame_pitch_mm": np.asarray(cols[3], dtype=np.float64),
            "frame_contact": np.asarray(cols[4], dtype=bool),
            "frame_force_n": np.asarray(cols[5], dtype=np.float64),
            "frame_indentation_mm": np.asarray(cols[6], dtype=np.float64),
            "frame_height_mm": stack(7), "frame_stiffness_k": stack(8),
            "frame_stiffness_n_per_mm": stack(9),
            "meta_json": np.asarray(json.dumps(to_jsonable(meta_doc), allow_nan=False,
                                               sort_keys=True)),
        }

    def save(self, path: str | os.PathLike[str], meta: Mapping[str, Any] | None = None) -> Path:
        """Write the recording with ``np.savez_compressed``.

        Args:
            path: destination (``.npz`` is appended by numpy when missing).
            meta: session, workspace and anything else for ``meta_json``.

        Returns:
            The path written.

        Raises:
            ConfigError: the file cannot be written.
        """
        out = Path(path)
        if out.suffix != ".npz":
            out = out.with_name(out.name + ".npz")
        try:
            np.savez_compressed(out, **self.arrays(meta))  # type: ignore[arg-type]
        except OSError as err:
            raise ConfigError(f"cannot write the recording {out}: {err}") from err
        log.info("recording written to %s (%d platform samples, %d tactile frames)", out,
                 self.platform_samples, self.frames)
        return out


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
        frame_stiffness_k: (N, H, W) display k, or None when not recorded.
        frame_stiffness_n_per_mm: (N, H, W) measured stiffness, or None.
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
    frame_stiffness_k: NDArray[np.float32] | None = None
    frame_stiffness_n_per_mm: NDArray[np.float32] | None = None
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


def load_recording(path: str | os.PathLike[str]) -> Recording:
    """Read and validate a recording written by :class:`SessionRecorder`.

    Raises:
        InputDataError: an unreadable file, missing keys, inconsistent or non-finite arrays.
    """
    p = Path(path)
    try:
        with np.load(p, allow_pickle=False) as data:
            missing = sorted(set(RECORD_KEYS) - set(data.files))
            if missing:
                raise InputDataError(f"{p}: not a local-station recording, missing {missing}")
            raw: dict[str, Any] = {k: data[k] for k in RECORD_KEYS}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise InputDataError(f"cannot read the recording {p}: {err}") from err
    try:
        meta = json.loads(str(raw["meta_json"]))
    except json.JSONDecodeError as err:
        raise InputDataError(f"{p}: meta_json is not JSON: {err}") from err
    return Recording(
        platform_t_us=raw["platform_t_us"].astype(np.int64),
        platform_mm=raw["platform_mm"].astype(np.float64).reshape(-1, 3),
        frame_center_mm=raw["frame_center_mm"].astype(np.float64).reshape(-1, 2),
        frame_pitch_mm=raw["frame_pitch_mm"].astype(np.float64),
        frame_contact=raw["frame_contact"].astype(bool),
        frame_force_n=raw["frame_force_n"].astype(np.float64),
        frame_indentation_mm=raw["frame_indentation_mm"].astype(np.float64),
        frame_height_mm=raw["frame_height_mm"].astype(np.float32),
        frame_rx_us=raw["frame_rx_us"].astype(np.int64),
        frame_seq=raw["frame_seq"].astype(np.int64),
        frame_stiffness_k=raw["frame_stiffness_k"].astype(np.float32),
        frame_stiffness_n_per_mm=raw["frame_stiffness_n_per_mm"].astype(np.float32),
        meta=meta if isinstance(meta, dict) else {"meta": meta},
    )
