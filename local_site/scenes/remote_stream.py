"""The remote stream: a scene rebuilt from each incoming ``tactile_frame``.

Each :class:`~shared.protocol.TactileFrame` carries layers on a metric grid of
``pitch_mm`` centred on ``center_mm`` (platform frame; row index along +y, column along
+x). :meth:`TactileFrameScene.update` validates a frame and replaces the content with
it (latest arrival wins; the relay already forwards tactile frames latest-wins, and a
remote restart resets ``seq``, so arrival order is the only safe order). It records the
frame's ``seq``/``ts_us``/``source_seq`` and the local monotonic time of the update, so
the station can judge staleness (:meth:`TactileFrameScene.age_s`).

Validation goes beyond the wire decoder (frames built in-process skip it): a known
layer set with ``height_mm``, 2-D float layers of one shape (at least 2 x 2), finite
values inside :data:`shared.protocol.messages.LAYER_RANGES`, a finite centre and a
positive pitch. A bad frame raises :class:`~shared.errors.InputDataError` and leaves the
previous content (and therefore the pins) untouched.

Stiffness: ``stiffness_k`` is used as is (the remote station computes it with the
project's one N/mm -> k mapping, :class:`shared.hardness.StiffnessToK`). A frame with only
``stiffness_n_per_mm`` (measured force / indentation) goes through the same mapping when
the scene was given one (``stiffness_to_k``, built from the probe's stiffness
calibration); without a mapping, or without either layer, k = ``default_stiffness_k``.
Friction defaults to 0 (the paper's palpation setting).

Where the window leaves the frame's extent (the probe's patch is small), the scene
degrades per pin through its :class:`~local_site.scenes.base.OutsidePolicy`: ``flat``
(default: height 0, rigid, no friction) or ``edge`` (continue the border values).
Before the first frame, and after :meth:`clear`, every point is outside.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from local_site.render.interpolation import DEFAULT_ORDER, MAX_GRID_DIM, GridLayers
from local_site.scenes.base import OutsidePolicy
from local_site.scenes.grid_scene import GridScene
from shared.errors import ConfigError, InputDataError
from shared.hardness import K_MAX, K_MIN, StiffnessToK
from shared.protocol.messages import LAYER_RANGES, TactileFrame
from shared.timebase import monotonic_s

__all__ = ["TactileFrameScene"]

log = logging.getLogger(__name__)

_COORD_LIMIT_MM = 1.0e4


class TactileFrameScene(GridScene):
    """A scene fed by tactile frames from the relay.

    Args:
        order: interpolation order (0, 1, 3).
        outside: per-pin policy outside the frame's extent (default flat).
        default_stiffness_k: k when a frame carries no stiffness layer.
        stiffness_to_k: the N/mm -> k mapping for frames with only ``stiffness_n_per_mm``
            (None: such frames render at ``default_stiffness_k``).

    Raises:
        ConfigError: invalid settings.
    """

    kind: ClassVar[str] = "remote"

    def __init__(self, *, order: int = DEFAULT_ORDER, outside: OutsidePolicy | None = None,
                 default_stiffness_k: float = K_MAX,
                 stiffness_to_k: StiffnessToK | None = None) -> None:
        super().__init__(order=order, outside=outside)
        if not K_MIN <= default_stiffness_k <= K_MAX:
            raise ConfigError(f"default_stiffness_k must lie in [{K_MIN}, {K_MAX}]")
        if stiffness_to_k is not None and not isinstance(stiffness_to_k, StiffnessToK):
            raise ConfigError("stiffness_to_k must be a shared.hardness.StiffnessToK")
        self.default_stiffness_k = float(default_stiffness_k)
        self.stiffness_to_k = stiffness_to_k
        self.frames_accepted = 0
        self.frames_rejected = 0
        self.last_frame: TactileFrame | None = None
        self.last_update_s: float | None = None

    # ------------------------------------------------------------------ stream state
    @property
    def last_seq(self) -> int | None:
        """``seq`` of the frame in use, or None."""
        return None if self.last_frame is None else self.last_frame.seq

    @property
    def last_ts_us(self) -> int | None:
        """Capture timestamp (remote clock, us) of the frame in use, or None."""
        return None if self.last_frame is None else self.last_frame.ts_us

    @property
    def last_source_seq(self) -> int | None:
        """``source_seq`` (the platform_state it answers) of the frame in use, or None."""
        return None if self.last_frame is None else self.last_frame.source_seq

    def age_s(self, now_s: float | None = None) -> float | None:
        """Seconds since the last accepted update (local monotonic clock), None if none.

        Args:
            now_s: current :func:`shared.timebase.monotonic_s` (read when None).
        """
        if self.last_update_s is None:
            return None
        return (monotonic_s() if now_s is None else now_s) - self.last_update_s

    # ------------------------------------------------------------------ updates
    def update(self, frame: TactileFrame, *, now_s: float | None = None,
               prepared: GridLayers | InputDataError | None = None) -> None:
        """Replace the content with ``frame`` (latest wins).

        Args:
            frame: the tactile frame.
            now_s: local monotonic time of arrival (read when None).
            prepared: what :meth:`prepare` gave for ``frame`` (its grid, or the error it
                raised), when another thread ran it; None: prepared here.

        Raises:
            InputDataError: the frame is malformed (content unchanged).
        """
        try:
            if isinstance(prepared, InputDataError):
                raise prepared
            grid = self.prepare(frame) if prepared is None else prepared
        except InputDataError:
            self.frames_rejected += 1
            raise
        self.last_frame = frame
        self.last_update_s = monotonic_s() if now_s is None else now_s
        self.frames_accepted += 1
        self._set_grid(grid)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("tactile frame seq=%d accepted (version %d)", frame.seq, self.version)

    def prepare(self, frame: TactileFrame) -> GridLayers:
        """Validate ``frame`` and build the grid :meth:`update` would swap in.

        Changes nothing (reads only the settings fixed at construction), so any thread may
        run it: the station prepares each frame where it arrives, and the display loop only
        swaps the grid in (:class:`~local_site.agent.display_loop.FrameSlot`).

        Raises:
            InputDataError: the frame is malformed.
        """
        return self._grid_from_frame(frame)

    def clear(self) -> None:
        """Forget the content (e.g. on link loss): every point becomes outside."""
        self.last_frame = None
        self.last_update_s = None
        self._set_grid(None)

    def _layer(self, layers: Mapping[str, Any], name: str,
               shape: tuple[int, ...] | None) -> NDArray[np.float64]:
        arr = layers[name]
        if not isinstance(arr, np.ndarray) or arr.dtype.kind != "f":
            raise InputDataError(f"tactile frame layer {name!r} must be a float ndarray")
        if arr.ndim != 2:
            raise InputDataError(f"tactile frame layer {name!r} must be 2-D, got {arr.shape}")
        if shape is not None and arr.shape != shape:
            raise InputDataError(f"tactile frame layer {name!r} has shape {arr.shape}, "
                                 f"height_mm has {shape}")
        if not (2 <= arr.shape[0] <= MAX_GRID_DIM and 2 <= arr.shape[1] <= MAX_GRID_DIM):
            raise InputDataError(f"tactile frame layers need 2..{MAX_GRID_DIM} samples per "
                                 f"side, got {arr.shape}")
        # two passes, not three: a NaN makes min or max NaN and an Inf leaves the (finite)
        # range, so both fail the range check, which then tells them apart
        lo, hi = LAYER_RANGES[name]
        least, most = arr.min(), arr.max()
        if not (lo <= least and most <= hi):
            if not np.isfinite(arr).all():
                raise InputDataError(f"tactile frame layer {name!r} contains NaN or Inf")
            raise InputDataError(f"tactile frame layer {name!r} must lie in [{lo}, {hi}], got "
                                 f"[{least:.6g}, {most:.6g}]")
        return arr.astype(np.float64, copy=False)

    def _grid_from_frame(self, frame: TactileFrame) -> GridLayers:
        if not isinstance(frame, TactileFrame):
            raise InputDataError(f"expected a TactileFrame, got {type(frame).__name__}")
        layers = frame.layers
        if not isinstance(layers, Mapping) or "height_mm" not in layers:
            raise InputDataError("tactile frame has no height_mm layer")
        unknown = sorted(str(k) for k in layers if k not in LAYER_RANGES)
        if unknown:
            raise InputDataError(f"tactile frame has unknown layer(s) {unknown}")
        height = self._layer(layers, "height_mm", None)
        shape = height.shape
        if "stiffness_k" in layers:
            k = self._layer(layers, "stiffness_k", shape)
        elif "stiffness_n_per_mm" in layers and self.stiffness_to_k is not None:
            n = self._layer(layers, "stiffness_n_per_mm", shape)
            k = self.stiffness_to_k.k(n)
        else:
            k = np.full(shape, self.default_stiffness_k)
        if "stiffness_n_per_mm" in layers and ("stiffness_k" in layers
                                               or self.stiffness_to_k is None):
            self._layer(layers, "stiffness_n_per_mm", shape)  # still validated
        friction = (self._layer(layers, "friction", shape) if "friction" in layers
                    else np.zeros(shape))
        try:
            cx, cy = (float(c) for c in frame.center_mm)
            pitch = float(frame.pitch_mm)
        except (TypeError, ValueError) as err:
            raise InputDataError(f"tactile frame centre/pitch are not numbers: {err}") from err
        if not (np.isfinite([cx, cy, pitch]).all() and abs(cx) <= _COORD_LIMIT_MM
                and abs(cy) <= _COORD_LIMIT_MM and 0.0 < pitch <= 100.0):
            raise InputDataError(f"tactile frame centre {frame.center_mm} / pitch "
                                 f"{frame.pitch_mm} out of range")
        ny, nx = shape
        return GridLayers(np.stack([height, k, friction]),
                          x0_mm=cx - 0.5 * (nx - 1) * pitch, y0_mm=cy - 0.5 * (ny - 1) * pitch,
                          dx_mm=pitch, dy_mm=pitch)
