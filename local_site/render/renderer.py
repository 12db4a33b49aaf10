"""The tactile renderer: a scene seen through the 4 x 4 pin window -> one PinCommand.

The window is centred at the platform position (plus ``window_offset``) and holds the
16 pins at ``pitch_mm`` (layout in :mod:`local_site.render.pin_command`). Each pin takes
the scene's value at its own position, so moving the platform by less than a pitch
shifts what the pins show: features finer than 1.7 mm are felt by moving
(super-resolution), as long as the scene interpolates (grid scenes do, order >= 1).

Height: ``h_pin = height_offset_mm + height_gain * (h_scene - ref)`` clamped to
``[0, stroke_mm]``, where ``ref`` is 0 in ``absolute`` mode and the lowest scene height
under the window in ``relative`` mode (the lowest point then sits at the offset, so a
scene far above or below the stroke still shows its local relief). Stiffness: the
scene's k (scenes convert Shore 00 to k through the hardness table when built),
clipped to [0.5, 1]. Friction: passed through; values below ``friction_floor`` become
exactly 0 so interpolation dust does not start a vibration (``friction_active``).

Work skipped: when the same scene object, at the same ``version``, is rendered at a
position within ``move_threshold_mm`` of the last rendered one, the previous
:class:`PinCommand` object is returned untouched (``is`` the same), so the driver can
skip re-sending it. Bad input (non-finite position, NaN or out-of-range scene values)
raises :class:`~shared.errors.InputDataError` before any state changes.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numba import njit
from numpy.typing import NDArray

from local_site.render.interpolation import warm_up
from local_site.render.pin_command import (
    N_COLS,
    N_ROWS,
    PIN_PITCH_MM,
    STROKE_MM,
    PinCommand,
    pin_offsets_mm,
)
from shared.errors import ConfigError, InputDataError
from shared.hardness import K_MAX, K_MIN

if TYPE_CHECKING:
    from local_site.scenes.base import SceneSource

__all__ = ["HEIGHT_MODES", "RenderStats", "Renderer", "RendererConfig"]

log = logging.getLogger(__name__)

HEIGHT_MODES = ("absolute", "relative")
#: scene heights beyond this are rejected as corrupt (same bound as the scene sources)
_MAX_SCENE_HEIGHT_MM = 1000.0
#: slack for range checks on values that went through float arithmetic
_RANGE_TOL = 1e-9


@dataclass(frozen=True)
class RendererConfig:
    """Renderer settings (resolve with ``resolve_config(RendererConfig, "local.render")``).

    Attributes:
        pitch_mm: pin pitch.
        height_mode: ``"absolute"`` or ``"relative"`` (see the module docstring).
        height_gain: scene mm -> pin mm scale.
        height_offset_mm: pin height of scene height ``ref``.
        stroke_mm: pin heights are clamped to ``[0, stroke_mm]``.
        move_threshold_mm: re-render only when the window moved farther than this.
        skip_unchanged: reuse the previous command when nothing changed (off only to
            measure the saving).
        friction_floor: friction below this is rendered as exactly 0.
        window_offset_x_mm: added to the platform x to get the window centre.
        window_offset_y_mm: added to the platform y to get the window centre.
    """

    pitch_mm: float = PIN_PITCH_MM
    height_mode: str = "absolute"
    height_gain: float = 1.0
    height_offset_mm: float = 0.0
    stroke_mm: float = STROKE_MM
    move_threshold_mm: float = 0.01
    skip_unchanged: bool = True
    friction_floor: float = 1e-3
    window_offset_x_mm: float = 0.0
    window_offset_y_mm: float = 0.0

    def __post_init__(self) -> None:
        numbers = {k: getattr(self, k) for k in ("pitch_mm", "height_gain", "height_offset_mm",
                                                   "stroke_mm", "move_threshold_mm",
                                                   "friction_floor", "window_offset_x_mm",
                                                   "window_offset_y_mm")}
        for name, value in numbers.items():
            if isinstance(value, bool) or not isinstance(value, int | float) \
                    or not math.isfinite(value):
                raise ConfigError(f"local.render.{name} must be a finite number, got {value!r}")
        if self.height_mode not in HEIGHT_MODES:
            raise ConfigError(f"local.render.height_mode must be one of {HEIGHT_MODES}, "
                              f"got {self.height_mode!r}")
        if not 0.0 < self.pitch_mm <= 100.0:
            raise ConfigError("local.render.pitch_mm must lie in (0, 100]")
        if not 0.0 < self.stroke_mm <= STROKE_MM:
            raise ConfigError(f"local.render.stroke_mm must lie in (0, {STROKE_MM}]")
        if not 0.0 < abs(self.height_gain) <= 1.0e3:
            raise ConfigError("local.render.height_gain must be non-zero with |gain| <= 1000")
        if not 0.0 <= self.height_offset_mm <= self.stroke_mm:
            raise ConfigError("local.render.height_offset_mm must lie within the stroke")
        if not 0.0 <= self.move_threshold_mm <= 1.0:
            raise ConfigError("local.render.move_threshold_mm must lie in [0, 1] mm")
        if not 0.0 <= self.friction_floor < 1.0:
            raise ConfigError("local.render.friction_floor must lie in [0, 1)")


@dataclass
class RenderStats:
    """Counters of a renderer (read them for status lines and benchmarks).

    Attributes:
        rendered: commands computed from the scene.
        skipped: calls that returned the previous command unchanged.
        rejected: calls refused for bad input (position or scene data).
        clamped_pins: pin heights clamped to the stroke, summed over renders.
    """

    rendered: int = 0
    skipped: int = 0
    rejected: int = 0
    clamped_pins: int = 0


#: what :func:`_finish_kernel` found wrong (0: nothing), in the order it checks: NaN/Inf in
#: layer i is status i + 1 (layers in :data:`_LAYERS` order), then the three ranges
_LAYERS = ("height_mm", "stiffness_k", "friction")
_BAD_HEIGHT, _BAD_K, _BAD_F = 4, 5, 6
N_PINS = N_ROWS * N_COLS


@njit(cache=True, nogil=True)
def _finish_kernel(h: NDArray[np.float64], k: NDArray[np.float64], f: NDArray[np.float64],
                   relative: bool, offset: float, gain: float, stroke: float, k_lo: float,
                   k_hi: float, floor: float, max_height: float, tol: float,
                   out: NDArray[np.float64]
                   ) -> tuple[int, int, NDArray[np.float64], bool]:  # pragma: no cover - compiled
    """Check the sampled layers and turn them into pin values in one pass (the numpy
    version was about 20 array calls on 16 values each, most of a render's cost).

    ``out`` (3, n) gets height, k and friction. Returns (status, clamped pins, the six
    extremes hmin, hmax, kmin, kmax, fmin, fmax for the error message, whether any pin's
    friction is above 0); status 0 = valid,
    else one of the ``_BAD_*`` codes (then ``out`` is garbage). NaN/Inf in any layer is
    reported before any range, layers in the order height, k, friction.
    """
    ext = np.empty(6)
    for layer in range(3):
        values = h if layer == 0 else (k if layer == 1 else f)
        lo, hi = np.inf, -np.inf
        for v in values:
            if not np.isfinite(v):
                return layer + 1, 0, ext, False  # NaN/Inf in _LAYERS[layer]
            lo = min(lo, v)
            hi = max(hi, v)
        ext[2 * layer] = lo
        ext[2 * layer + 1] = hi
    if max(-ext[0], ext[1]) > max_height:
        return _BAD_HEIGHT, 0, ext, False
    if ext[2] < k_lo - tol or ext[3] > k_hi + tol:
        return _BAD_K, 0, ext, False
    if ext[4] < -tol or ext[5] > 1.0 + tol:
        return _BAD_F, 0, ext, False
    ref = ext[0] if relative else 0.0
    clamped = 0
    friction_active = False
    for i in range(h.size):
        target = offset + gain * (h[i] - ref)
        height = min(max(target, 0.0), stroke)
        if abs(target - height) > tol:
            clamped += 1
        out[0, i] = height
        out[1, i] = min(max(k[i], k_lo), k_hi)
        fi = min(max(f[i], 0.0), 1.0)
        out[2, i] = 0.0 if fi < floor else fi
        friction_active = friction_active or out[2, i] > 0.0
    return 0, clamped, ext, friction_active


def _position_xy(position_mm: Sequence[float] | np.ndarray) -> tuple[float, float]:
    try:
        values = [float(v) for v in position_mm]
    except (TypeError, ValueError) as err:
        raise InputDataError(f"platform position must be numbers, got {position_mm!r}") from err
    if len(values) not in (2, 3):
        raise InputDataError(f"platform position needs (x, y) or (x, y, z), got {len(values)} "
                             "values")
    if not all(math.isfinite(v) for v in values):
        raise InputDataError(f"platform position is not finite: {values}")
    return values[0], values[1]


class Renderer:
    """Samples a scene through the pin window and produces validated pin commands.

    One thread renders (the display loop's): a renderer keeps its last command and a
    work array between calls, so it is not shared between threads.

    Args:
        config: settings (defaults when None).

    Example::

        renderer = Renderer(RendererConfig(height_mode="relative", height_offset_mm=1.0))
        command = renderer.render(scene, platform_state.position_mm)
    """

    def __init__(self, config: RendererConfig | None = None) -> None:
        self.config = config or RendererConfig()
        self.stats = RenderStats()
        self._offsets = pin_offsets_mm(self.config.pitch_mm)  # (4, 4, 2)
        self._flat_offsets = self._offsets.reshape(N_PINS, 2)
        self._centre = np.zeros(2)
        self._finish_args = _finish_args(self.config)
        self._last: PinCommand | None = None
        self._last_scene: SceneSource | None = None
        self._last_version = -1
        self._last_xy = (math.nan, math.nan)
        # compile (or load from numba's cache) the 1 kHz path's kernels now, not in the
        # display loop's first render
        warm_up()
        one = np.zeros(1)
        _finish_kernel(one, np.full(1, K_MAX), one, *self._finish_args, np.empty((3, 1)))

    @property
    def last_command(self) -> PinCommand | None:
        """The most recent command returned, or None."""
        return self._last

    def pin_positions_mm(self, position_mm: Sequence[float] | np.ndarray) -> np.ndarray:
        """Scene coordinates ``(4, 4, 2)`` of the pins for a platform position.

        Raises:
            InputDataError: a non-finite or malformed position.
        """
        x, y = _position_xy(position_mm)
        cfg = self.config
        return self._offsets + np.array([x + cfg.window_offset_x_mm, y + cfg.window_offset_y_mm])

    def invalidate(self) -> None:
        """Forget the previous command so the next render recomputes."""
        self._last = None
        self._last_scene = None

    def render(self, scene: SceneSource, position_mm: Sequence[float] | np.ndarray) -> PinCommand:
        """Render ``scene`` at the platform position.

        Args:
            scene: any :class:`~local_site.scenes.base.SceneSource`.
            position_mm: platform ``(x, y)`` or ``(x, y, z)`` in mm (z is ignored here).

        Returns:
            The pin command; the previous object itself when nothing changed.

        Raises:
            InputDataError: a non-finite position or NaN / out-of-range scene values
                (nothing is updated; the previous command stays current).
        """
        try:
            x, y = _position_xy(position_mm)
        except InputDataError:
            self.stats.rejected += 1
            raise
        version = scene.version
        cfg = self.config
        if (cfg.skip_unchanged and self._last is not None and scene is self._last_scene
                and version == self._last_version
                and math.hypot(x - self._last_xy[0], y - self._last_xy[1])
                <= cfg.move_threshold_mm):
            self.stats.skipped += 1
            return self._last
        try:
            command = self._compute(scene, x, y, version)
        except InputDataError:
            self.stats.rejected += 1
            raise
        self._last, self._last_scene = command, scene
        self._last_version, self._last_xy = version, (x, y)
        self.stats.rendered += 1
        self.stats.clamped_pins += command.clamped_pins
        return command

    def _compute(self, scene: SceneSource, x: float, y: float, version: int) -> PinCommand:
        cfg = self.config
        cx, cy = x + cfg.window_offset_x_mm, y + cfg.window_offset_y_mm
        if not (math.isfinite(cx) and math.isfinite(cy)):  # a finite sum can overflow
            raise InputDataError(f"scene points contain NaN or Inf (window centre {cx}, {cy})")
        centre = self._centre  # the window centre, written in place (no array built)
        centre[0], centre[1] = cx, cy
        sample = scene.sample_flat(self._flat_offsets + centre)
        out = np.empty((3, N_PINS))
        status, clamped, ext, friction_active = _finish_kernel(
            sample.height_mm, sample.stiffness_k, sample.friction, *self._finish_args, out)
        if status:
            raise InputDataError(_bad_sample_message(type(scene).__name__, status, ext))
        out.setflags(write=False)  # the command's layers are read-only views of it
        height, stiffness, friction = out.reshape(3, N_ROWS, N_COLS)
        # the kernel checked what PinCommand's constructor would (finite, in range; the
        # shape is the pin window's), so the command is built without checking it again
        return PinCommand.checked(height, stiffness, friction, position_mm=(x, y),
                                  scene_version=version, clamped_pins=int(clamped),
                                  outside_pins=N_PINS - int(np.count_nonzero(sample.inside)),
                                  friction_active=friction_active)


_FinishArgs = tuple[bool, float, float, float, float, float, float, float, float]


def _finish_args(cfg: RendererConfig) -> _FinishArgs:
    """The settings as :func:`_finish_kernel` takes them, after its three layers: as the
    types it was compiled for (an int gain would compile another version inside the
    display loop)."""
    return (cfg.height_mode == "relative", float(cfg.height_offset_mm), float(cfg.height_gain),
            float(cfg.stroke_mm), float(K_MIN), float(K_MAX), float(cfg.friction_floor),
            float(_MAX_SCENE_HEIGHT_MM), float(_RANGE_TOL))


def _bad_sample_message(name: str, status: int, ext: NDArray[np.float64]) -> str:
    """The error for a :func:`_finish_kernel` status."""
    if status <= len(_LAYERS):
        return f"scene {name} gave NaN/Inf {_LAYERS[status - 1]}; pins not updated"
    if status == _BAD_HEIGHT:
        return f"scene {name} height beyond +-{_MAX_SCENE_HEIGHT_MM} mm"
    if status == _BAD_K:
        return (f"scene {name} stiffness k outside [{K_MIN}, {K_MAX}]: "
                f"[{ext[2]:.6g}, {ext[3]:.6g}]")
    return f"scene {name} friction outside [0, 1]: [{ext[4]:.6g}, {ext[5]:.6g}]"
