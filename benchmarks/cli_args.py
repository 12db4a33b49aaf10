"""Argument types the benchmarks' command lines share: a bad value is a usage error."""

from __future__ import annotations

import argparse
import math


def count(text: str) -> int:
    """A whole number >= 1 (rounds, repeats)."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number >= 1")
    return int(text)


def positive(text: str) -> float:
    """A finite number > 0 (rates, durations)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"{text!r}: a finite number > 0")
    return value
