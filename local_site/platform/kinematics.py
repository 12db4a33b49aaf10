"""Encoder counts <-> platform millimetres: geometry, counter unwrapping, workspace clamping.

Conventions (stated once, used everywhere): platform coordinates in millimetres, origin at the
zero pose set by :meth:`~local_site.platform.base.XYZPlatform.zero` (by default the
low corner: x left, y front, z lowest); z positive up, so pressing lowers z.
Each encoder has 1024 pulses per revolution (PPR); the board decodes quadrature x4, so one
revolution is 4096 counts. X and Y are rack and pinion, Z a timing belt; each axis's travel
per revolution (``mm_per_rev``) is configurable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from shared.errors import ConfigError

__all__ = [
    "DEFAULT_MM_PER_REV",
    "DEFAULT_WORKSPACE_MM",
    "PlatformGeometry",
    "WrapUnwrapper",
]

#: X/Y: module-0.5 rack, 24-tooth pinion (pitch circle 12 mm) -> pi * 12 mm per rev.
#: Z: GT2 belt (2 mm pitch) on a 20-tooth pulley -> 40 mm per rev.
DEFAULT_MM_PER_REV: tuple[float, float, float] = (math.pi * 12.0, math.pi * 12.0, 40.0)
#: Travel of the paper's sliding platform, X-Y-Z.
DEFAULT_WORKSPACE_MM: tuple[float, float, float] = (60.0, 60.0, 185.0)


@dataclass(frozen=True, slots=True)
class PlatformGeometry:
    """Mechanics of the three axes.

    Attributes:
        pulses_per_rev: encoder lines per revolution (1024 on the paper's platform).
        decoding: quadrature decoding factor (4: every edge of A and B counts).
        mm_per_rev: linear travel per encoder revolution for x, y, z.
        direction: +1 or -1 per axis (wiring may invert an axis).
        workspace_mm: travel per axis; positions are clamped to [0, workspace_mm].
    """

    pulses_per_rev: int = 1024
    decoding: int = 4
    mm_per_rev: tuple[float, float, float] = DEFAULT_MM_PER_REV
    direction: tuple[int, int, int] = (1, 1, 1)
    workspace_mm: tuple[float, float, float] = DEFAULT_WORKSPACE_MM

    def __post_init__(self) -> None:
        ppr = self.pulses_per_rev
        # an integer the board's INFO frame can state (uint16): a NaN, a bool or 1024.5 gave
        # nonsense millimetres before, a string a TypeError
        if not (isinstance(ppr, int) and not isinstance(ppr, bool) and 0 < ppr <= 0xFFFF) \
                or self.decoding not in (1, 2, 4) or isinstance(self.decoding, bool):
            raise ConfigError(f"pulses_per_rev must be an integer in 1..65535 and decoding 1, "
                              f"2 or 4; got {ppr!r}, {self.decoding!r}")
        for name, vec in (("mm_per_rev", self.mm_per_rev), ("workspace_mm", self.workspace_mm)):
            if len(vec) != 3 or not all(math.isfinite(v) and v > 0 for v in vec):
                raise ConfigError(f"{name} must be three finite positive numbers, got {vec}")
        if len(self.direction) != 3 or any(d not in (1, -1) for d in self.direction):
            raise ConfigError(f"direction must be three of +1/-1, got {self.direction}")

    @property
    def counts_per_rev(self) -> int:
        """Counts per revolution after quadrature decoding (4096 by default)."""
        return self.pulses_per_rev * self.decoding

    @property
    def mm_per_count(self) -> tuple[float, float, float]:
        """Resolution per axis, signed by ``direction`` (about 9.2 um on X/Y, 9.8 um on Z)."""
        cpr = self.counts_per_rev
        return tuple(d * p / cpr for d, p in zip(self.direction, self.mm_per_rev, strict=True))  # type: ignore[return-value]

    def counts_to_mm(self, counts: tuple[int, int, int]) -> tuple[float, float, float]:
        """Unclamped position of (already unwrapped, zero-referenced) counts."""
        return tuple(c * s for c, s in zip(counts, self.mm_per_count, strict=True))  # type: ignore[return-value]

    def mm_to_counts(self, position_mm: tuple[float, float, float]) -> tuple[int, int, int]:
        """Nearest counts of a position (what an ideal encoder would read)."""
        return tuple(round(p / s) for p, s in zip(position_mm, self.mm_per_count, strict=True))  # type: ignore[return-value]

    def clamp(self, position_mm: tuple[float, float, float]) \
            -> tuple[tuple[float, float, float], bool]:
        """Clamp to the workspace; return the clamped position and whether anything moved."""
        out = tuple(min(max(p, 0.0), w)
                    for p, w in zip(position_mm, self.workspace_mm, strict=True))
        return out, out != tuple(position_mm)  # type: ignore[return-value]


class WrapUnwrapper:
    """Turns a wrapping fixed-width counter into an unbounded Python int.

    Consecutive readings are assumed to differ by less than half the range (2^31 counts is
    ~29 km of travel at 9 um per count, so this holds for any platform sample rate).

    Args:
        bits: width of the counter.
        signed: whether the raw value is two's complement signed.
    """

    def __init__(self, bits: int = 32, *, signed: bool = True) -> None:
        self._modulus = 1 << bits
        self._half = 1 << (bits - 1)
        self._signed = signed
        self._last_raw: int | None = None
        self._value = 0

    def update(self, raw: int) -> int:
        """Feed the next raw reading; return the unwrapped value."""
        if self._last_raw is None:
            self._value = raw
        else:
            delta = ((raw - self._last_raw + self._half) % self._modulus) - self._half
            self._value += delta
        self._last_raw = raw
        return self._value

    def reset(self) -> None:
        """Forget the history (the next reading starts a new track)."""
        self._last_raw = None
        self._value = 0
