"""Garbage-collector pauses of every Python process of a run (docs/speed.md section 16).

Loaded at interpreter start through a ``.pth`` file in the venv's site-packages, it times
each collection with :data:`gc.callbacks` and, at exit, writes ``$GC_PROBE_DIR/<pid>.json``
(default: ``teletouch-gcstats`` in the temporary directory): per generation the count, total,
max and p99 pause (ms) and how many took over 5 ms, the process's object count, and every
pause over 1 ms with its time since start (``big``: seconds, generation, ms, collected).

Use (remove the two files afterwards; every process of that venv loads the probe meanwhile)::

    SP=$(.venv/bin/python -c "import site; print(site.getsitepackages()[0])")
    cp benchmarks/gc_probe.py $SP/zz_gc_probe.py && echo "import zz_gc_probe" > $SP/zz_gc_probe.pth
    teletouch demo --headless --no-view --link lan
    rm $SP/zz_gc_probe.py $SP/zz_gc_probe.pth

A process that ends without running its ``atexit`` handlers (killed) writes nothing.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import json
import os
import sys
import tempfile
import time
from typing import Any

_T0 = time.perf_counter()
_start: list[float] = [0.0]
_pauses: dict[int, list[float]] = {0: [], 1: [], 2: []}
_big: list[tuple[float, int, float, Any]] = []


def _callback(phase: str, info: dict[str, Any]) -> None:
    now = time.perf_counter()
    if phase == "start":
        _start[0] = now
        return
    ms = (now - _start[0]) * 1e3
    _pauses[info["generation"]].append(ms)
    if ms > 1.0:
        _big.append((round(now - _T0, 2), info["generation"], round(ms, 1), info.get("collected")))


def _dump() -> None:
    out: dict[str, Any] = {}
    for generation, pauses in _pauses.items():
        ordered = sorted(pauses)
        out[str(generation)] = {
            "n": len(ordered), "total_ms": sum(ordered), "max_ms": ordered[-1] if ordered else 0,
            "p99_ms": ordered[int(0.99 * (len(ordered) - 1))] if ordered else 0,
            "over_5ms": sum(1 for p in ordered if p > 5)}
    out.update(argv=" ".join(sys.argv[:8]), big=_big, objects=len(gc.get_objects()))
    directory = os.environ.get("GC_PROBE_DIR") or os.path.join(tempfile.gettempdir(),
                                                              "teletouch-gcstats")
    with contextlib.suppress(OSError):
        os.makedirs(directory, exist_ok=True)
        with open(os.path.join(directory, f"{os.getpid()}.json"), "w", encoding="utf-8") as f:
            json.dump(out, f)


gc.callbacks.append(_callback)
atexit.register(_dump)
