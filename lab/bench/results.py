"""Where a benchmark's results go: printed, and with ``--write-results DIR`` written to files.

Every benchmark writes ``<stem>.md`` (the human table, the file committed under
``benchmarks/results/``), ``<stem>.json`` (the same figures, strict JSON) when it has structured
results, and ``<stem>.png`` when it draws a plot. :func:`median_known` is the median their
tables of paired runs share (a run that does not report a figure is left out).
"""

from __future__ import annotations

import json
import os
import statistics
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from shared.report import emit, emit_json, to_jsonable

__all__ = ["median_known", "publish", "write_results"]


def median_known(values: Iterable[float | None]) -> float | None:
    """The median of the values that are known (not None); None when none is."""
    known = [v for v in values if v is not None]
    return statistics.median(known) if known else None


def write_results(out_dir: str | os.PathLike[str], stem: str, markdown: str, *,
                  data: Any = None, plot: Callable[[Path], None] | None = None) -> Path:
    """Write ``stem.md`` (and ``stem.json`` if ``data``, ``stem.png`` via ``plot``) in ``out_dir``.

    Returns the directory, created if missing.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.md").write_text(markdown.rstrip("\n") + "\n")
    if data is not None:
        (out / f"{stem}.json").write_text(
            json.dumps(to_jsonable(data), indent=1, default=str, allow_nan=False) + "\n")
    if plot is not None:
        plot(out / f"{stem}.png")
    return out


def publish(results: dict[str, Any], markdown: str, *, as_json: bool,
            out_dir: str | os.PathLike[str] | None, stem: str,
            plot: Callable[[Path], None] | None = None) -> None:
    """Print ``results`` as one JSON object (``as_json``) or ``markdown``; with ``out_dir``
    also write them (:func:`write_results`)."""
    if as_json:
        emit_json(results)
    else:
        emit(markdown)
    if out_dir is not None:
        write_results(out_dir, stem, markdown, data=results, plot=plot)
