"""Counters kept as frozen dataclasses of numbers (``DisplayStats``, ``PlatformStats``,
``RenderStats``): totals over connections or child processes are their field-wise sums."""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

__all__ = ["add_counters"]

_T = TypeVar("_T")


def add_counters(a: _T, b: _T) -> _T:
    """``a`` and ``b`` (two snapshots of one dataclass of numbers) added field by field."""
    fields = dataclasses.fields(a)  # type: ignore[arg-type]
    out: Any = type(a)(**{f.name: getattr(a, f.name) + getattr(b, f.name) for f in fields})
    return out
