"""The one place CLI output goes through (library code never prints).

Commands print results with :func:`emit` (human text) or :func:`emit_json` (one JSON
object on stdout, for ``--json``), and live status with :class:`StatusLine`, which
redraws a single terminal line when stderr is a TTY and prints at most once per
``min_interval_s`` otherwise (so logs of headless runs stay readable).
"""

from __future__ import annotations

import json
import math
import sys
import time
from typing import Any, TextIO

__all__ = ["StatusLine", "emit", "emit_json", "format_table", "to_jsonable"]


def to_jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays, tuples and non-finite floats to plain JSON values.

    NaN and infinities become ``None`` so the output is strict JSON.
    """
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if hasattr(obj, "tolist") and callable(obj.tolist):  # numpy arrays and scalars
        return to_jsonable(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def emit(text: str = "", *, stream: TextIO | None = None) -> None:
    """Print human-readable output of a command."""
    print(text, file=stream or sys.stdout, flush=True)


def emit_json(obj: Any, *, stream: TextIO | None = None) -> None:
    """Print one JSON object (strict: no NaN) on one line."""
    print(json.dumps(to_jsonable(obj), allow_nan=False, sort_keys=True), file=stream or sys.stdout,
          flush=True)


def format_table(rows: list[dict[str, Any]], columns: list[str] | None = None) -> str:
    """Format rows of dicts as a Markdown table (used by benchmarks and reports)."""
    if not rows:
        return "(no rows)"
    cols = columns or list(rows[0])

    def cell(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}" if math.isfinite(v) else "n/a"
        return str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    lines += ["| " + " | ".join(cell(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


class StatusLine:
    """A live one-line status on stderr.

    Args:
        min_interval_s: when stderr is not a terminal, print at most this often.
        stream: where to write (stderr by default).
    """

    def __init__(self, min_interval_s: float = 5.0, stream: TextIO | None = None) -> None:
        self._stream = stream or sys.stderr
        self._tty = bool(getattr(self._stream, "isatty", lambda: False)())
        self._min_interval_s = min_interval_s
        self._last = -math.inf

    def update(self, text: str) -> None:
        """Show ``text`` as the current status."""
        now = time.monotonic()
        if self._tty:
            self._stream.write("\r\x1b[2K" + text)
            self._stream.flush()
        elif now - self._last >= self._min_interval_s:
            self._stream.write(text + "\n")
            self._stream.flush()
            self._last = now

    def close(self) -> None:
        """End the status line (moves to a new line on a terminal)."""
        if self._tty:
            self._stream.write("\n")
            self._stream.flush()
