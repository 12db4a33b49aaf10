"""Encoding of view fields: rounded finite numbers, height patches as quantised bytes.

Shared by the local station's view and the relay's, so the page reads one format.
"""

from __future__ import annotations

import base64
import math
from typing import Any

import numpy as np

from shared.protocol import TactileFrame
from shared.timebase import now_us

__all__ = ["encode_patch", "num", "nums"]


def num(value: float | None, digits: int = 4) -> float | None:
    """``value`` rounded, or None when it is missing or not finite (JSON has no NaN)."""
    if value is None or not math.isfinite(value):
        return None
    return round(float(value), digits)


def nums(values: Any, digits: int = 4) -> list[float | None]:
    """Every element of ``values`` through :func:`num`, flattened."""
    return [num(float(v), digits) for v in np.asarray(values, dtype=np.float64).ravel()]


def encode_patch(frame: TactileFrame, rx_us: int, position_mm: tuple[float, ...] | None,
                 pin_pitch_mm: float | None) -> dict[str, Any] | None:
    """A frame's height layer as bytes (0 = no data, 1..255 = lo..hi) with its metadata.

    Args:
        frame: the tactile frame.
        rx_us: when it arrived (wall clock, us): gives ``age_ms``.
        position_mm: the platform (x, y) the pins sit at, or None.
        pin_pitch_mm: the pins' pitch; with ``position_mm``, ``window`` is the pins'
            footprint (+-2 pitches about the position) in the patch's column/row indices.

    Returns:
        The patch document, or None when the frame has no 2-D height layer.
    """
    height = frame.layers.get("height_mm")
    if not isinstance(height, np.ndarray) or height.ndim != 2 or height.size == 0:
        return None
    h = np.asarray(height, dtype=np.float64)
    finite = np.isfinite(h)
    lo = float(h[finite].min()) if finite.any() else 0.0
    hi = float(h[finite].max()) if finite.any() else 0.0
    span = hi - lo if hi > lo else 1.0
    q = np.where(finite, 1 + np.rint(np.clip((h - lo) / span, 0, 1) * 254), 0).astype(np.uint8)
    rows, cols = h.shape
    window = None
    if position_mm is not None and pin_pitch_mm is not None:
        half = 2.0 * pin_pitch_mm  # the 4 x 4 pins' footprint: +-2 pitches around the centre
        to_col = (position_mm[0] - frame.center_mm[0]) / frame.pitch_mm + (cols - 1) / 2.0
        to_row = (position_mm[1] - frame.center_mm[1]) / frame.pitch_mm + (rows - 1) / 2.0
        r = half / frame.pitch_mm
        window = [num(to_col - r, 3), num(to_row - r, 3), num(to_col + r, 3),
                  num(to_row + r, 3)]
    return {"w": cols, "h": rows, "lo_mm": num(lo), "hi_mm": num(hi),
            "data": base64.b64encode(q.tobytes()).decode("ascii"),
            "pitch_mm": num(frame.pitch_mm), "center_mm": nums(frame.center_mm, 3),
            "window": window, "seq": int(frame.seq), "contact": bool(frame.contact),
            "force_n": num(frame.force_n), "indentation_mm": num(frame.indentation_mm),
            "age_ms": num((now_us() - rx_us) / 1e3, 1)}
