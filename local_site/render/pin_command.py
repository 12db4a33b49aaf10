"""The renderer's output: one command for the whole 4 x 4 ArrayTac array.

Pin layout (the convention every local-site module uses): ``array[row, col]``, row index
along +y and column index along +x of the platform frame. Pin ``(0, 0)`` sits at
``(-1.5 * pitch, -1.5 * pitch)`` from the window centre and pin ``(3, 3)`` at
``(+1.5 * pitch, +1.5 * pitch)``; with the 1.7 mm pitch the pins span 5.1 mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.errors import InputDataError
from shared.hardness import K_MAX, K_MIN

__all__ = [
    "FRICTION_MAX",
    "FRICTION_MIN",
    "N_COLS",
    "N_ROWS",
    "PIN_PITCH_MM",
    "STROKE_MM",
    "PinCommand",
    "pin_offsets_mm",
]

N_ROWS = 4
N_COLS = 4
#: centre-to-centre distance of neighbouring pins (paper: 1.7 mm)
PIN_PITCH_MM = 1.7
#: pin stroke: piezo 40 um x 125 lever = 5 mm; pin heights live in [0, STROKE_MM]
STROKE_MM = 5.0
FRICTION_MIN = 0.0
FRICTION_MAX = 1.0


def pin_offsets_mm(pitch_mm: float = PIN_PITCH_MM) -> NDArray[np.float64]:
    """Pin positions relative to the window centre.

    Args:
        pitch_mm: pin pitch.

    Returns:
        Array ``(4, 4, 2)``: ``[row, col] -> (x, y)`` in mm, row along +y, col along +x,
        pin (0, 0) at ``(-1.5 pitch, -1.5 pitch)``.
    """
    idx = (np.arange(N_COLS, dtype=float) - (N_COLS - 1) / 2.0) * pitch_mm
    idy = (np.arange(N_ROWS, dtype=float) - (N_ROWS - 1) / 2.0) * pitch_mm
    gx, gy = np.meshgrid(idx, idy)  # gx[row, col] = x of col, gy[row, col] = y of row
    return np.stack([gx, gy], axis=-1)


def _frozen_layer(value: ArrayLike, name: str, lo: float, hi: float) -> NDArray[np.float64]:
    arr = np.array(value, dtype=np.float64)  # private copy
    if arr.shape != (N_ROWS, N_COLS):
        raise InputDataError(f"PinCommand.{name} must have shape ({N_ROWS}, {N_COLS}), "
                             f"got {arr.shape}")
    # NaN and +-Inf reach min/max, so two reductions check finiteness and range (the 1 kHz
    # display path builds one command per moved millisecond: numpy calls are its cost)
    amin, amax = float(arr.min()), float(arr.max())
    if not (math.isfinite(amin) and math.isfinite(amax)):
        raise InputDataError(f"PinCommand.{name} contains NaN or Inf")
    if amin < lo or amax > hi:
        raise InputDataError(f"PinCommand.{name} must lie in [{lo}, {hi}], got "
                             f"[{amin:.6g}, {amax:.6g}]")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class PinCommand:
    """Heights, stiffness and friction for the 16 pins (validated, read-only arrays).

    Args:
        height_mm: ``(4, 4)`` pin heights in [0, 5] mm.
        stiffness_k: ``(4, 4)`` normalized stiffness k in [0.5, 1].
        friction: ``(4, 4)`` normalized friction f in [0, 1].
        position_mm: window centre (x, y) in scene coordinates it was rendered at.
        scene_version: the scene's ``version`` when rendered.
        clamped_pins: how many pin heights were clamped to the stroke.
        outside_pins: how many pins fell outside the scene's data (degraded values).

    Attributes:
        friction_active: False when every friction value is exactly 0, so the display
            synthesises no vibration at all.

    Raises:
        InputDataError: a wrong shape, NaN/Inf or an out-of-range value.
    """

    height_mm: NDArray[np.float64]
    stiffness_k: NDArray[np.float64]
    friction: NDArray[np.float64]
    position_mm: tuple[float, float] = (0.0, 0.0)
    scene_version: int = 0
    clamped_pins: int = 0
    outside_pins: int = 0
    friction_active: bool = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "height_mm",
                           _frozen_layer(self.height_mm, "height_mm", 0.0, STROKE_MM))
        object.__setattr__(self, "stiffness_k",
                           _frozen_layer(self.stiffness_k, "stiffness_k", K_MIN, K_MAX))
        object.__setattr__(self, "friction",
                           _frozen_layer(self.friction, "friction", FRICTION_MIN, FRICTION_MAX))
        object.__setattr__(self, "friction_active", bool(np.any(self.friction > 0.0)))

    @classmethod
    def checked(cls, height_mm: NDArray[np.float64], stiffness_k: NDArray[np.float64],
                friction: NDArray[np.float64], *, position_mm: tuple[float, float] = (0.0, 0.0),
                scene_version: int = 0, clamped_pins: int = 0, outside_pins: int = 0,
                friction_active: bool) -> PinCommand:
        """A command from layers the caller has already checked, without checking again.

        For the renderer's 1 kHz path, whose compiled pass checks exactly what the
        constructor would. The caller guarantees: float64 arrays of shape (4, 4), read-only,
        finite, inside the pin ranges, and ``friction_active`` true exactly when a friction
        value is above 0 (tests compare both paths); anyone else uses the constructor.
        """
        command = object.__new__(cls)
        command.__dict__.update(height_mm=height_mm, stiffness_k=stiffness_k, friction=friction,
                                position_mm=position_mm, scene_version=scene_version,
                                clamped_pins=clamped_pins, outside_pins=outside_pins,
                                friction_active=friction_active)
        return command

    @classmethod
    def flat(cls, height_mm: float = 0.0, stiffness_k: float = K_MAX,
             friction: float = 0.0) -> PinCommand:
        """A uniform command (all pins equal), e.g. the display's flat safe state.

        Raises:
            InputDataError: a value outside the pin ranges.
        """
        shape = (N_ROWS, N_COLS)
        return cls(np.full(shape, float(height_mm)), np.full(shape, float(stiffness_k)),
                   np.full(shape, float(friction)))

    def arrays(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """``(height_mm, stiffness_k, friction)``, in the argument order of
        ``ArrayTacDisplay.send_command`` (which accepts (4, 4) arrays in this layout)."""
        return self.height_mm, self.stiffness_k, self.friction

    def max_difference(self, other: PinCommand) -> float:
        """Largest absolute change of any pin value (height in mm, k and f unitless).

        A driver can use it to skip re-sending pins that did not change.
        """
        return float(max(np.max(np.abs(self.height_mm - other.height_mm)),
                         np.max(np.abs(self.stiffness_k - other.stiffness_k)),
                         np.max(np.abs(self.friction - other.friction))))
