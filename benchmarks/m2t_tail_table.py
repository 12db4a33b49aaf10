"""Where the motion-to-touch tail goes: a table of ``bench cpu`` runs' tail attribution.

Reads every ``cpu-*.json`` in a results directory (``teletouch bench cpu`` runs, which carry
the local station's ``motion_to_touch_tail_ms``: for the slowest 5 % of the complete frames,
each stage's mean against its median over all of them, see
:meth:`shared.motion_to_touch.MotionToTouchLedger.tail_ms`) and writes ``tail.md`` beside
them: per side and link profile (the run's label without its round number, e.g. ``s250-lan``
for ``s250-lan-2``: the sides of a paired run are never pooled) and stage, the median over
the runs of the stage's median, its mean in the tail, its excess and its share of the tail's
excess (with the range over the runs), and the end-to-end median, tail mean and p99.

It also gives each group's **floor**, as ``bench_motion_to_touch.py`` defines it: the link
profile's nominal round trip plus the p50 of the stages that work and of the waits the
design's rates fix and of the sensor's own delivery (``WORK_STAGES``, ``DESIGN_WAITS``,
``SENSOR_STAGES`` there), medians over the runs, and how
far each run's p99 lies above it.

Run: ``python benchmarks/m2t_tail_table.py benchmarks/results/m2t_tail``.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.bench_motion_to_touch import (  # noqa: E402
    DESIGN_WAITS,
    SENSOR_STAGES,
    WORK_STAGES,
)
from benchmarks.bench_motion_to_touch import floor_ms as motion_to_touch_floor  # noqa: E402
from lab.linkemu import get_profile  # noqa: E402


def _runs(directory: Path) -> dict[str, list[dict[str, Any]]]:
    by_group: dict[str, list[dict[str, Any]]] = {}
    for path in sorted(directory.glob("cpu-*.json")):
        run = json.loads(path.read_text())
        if run.get("latency_tail_ms"):
            link = run["settings"]["link"] or "none"
            label = re.sub(r"-\d+$", "", str(run.get("label") or ""))
            by_group.setdefault(label if link in label else f"{label} {link}".strip(),
                                []).append(run)
    return by_group


def _cell(values: list[float], fmt: str = "{:.2f}") -> str:
    med = statistics.median(values)
    if len(values) == 1:
        return fmt.format(med)
    return f"{fmt.format(med)} ({fmt.format(min(values))}-{fmt.format(max(values))})"


def floor_ms(runs: list[dict[str, Any]]) -> float | None:
    """The floor of a group of runs of one link profile (``bench_motion_to_touch.floor_ms``);
    None without a link emulator, or when no run reports one of the floor's stages."""
    link = runs[0]["settings"]["link"]
    if not link:
        return None
    return motion_to_touch_floor(float(get_profile(link).round_trip_ms),
                                 [r.get("latency_ms") for r in runs])


def table(directory: Path) -> str:
    """The Markdown table of the runs in ``directory``."""
    lines = []
    for link, runs in _runs(directory).items():
        tails = [r["latency_tail_ms"] for r in runs]
        e2e = [r["latency_ms"]["end_to_end"] for r in runs]
        loads = [r["load_start"][0] for r in runs]
        lines += [f"### `{link}`: {len(runs)} runs, load {min(loads):.1f}-{max(loads):.1f}", "",
                  f"End to end (ms): median {_cell([t['end_to_end']['p50'] for t in tails])}, "
                  f"tail mean {_cell([t['end_to_end']['tail_mean'] for t in tails])}, "
                  f"p99 {_cell([e['p99'] for e in e2e])}; tail = the slowest "
                  f"{100 * (1 - tails[0]['quantile']):.0f} % of "
                  f"{_cell([float(t['of']) for t in tails], '{:.0f}')} complete frames.", ""]
        floor = floor_ms(runs)
        if floor is not None:
            counted = WORK_STAGES + DESIGN_WAITS + tuple(
                s for s in SENSOR_STAGES if any(s in r["latency_ms"] for r in runs))
            lines += [f"Floor {floor:.1f} ms (nominal round trip "
                      f"{get_profile(runs[0]['settings']['link']).round_trip_ms:.1f} ms + the "
                      f"p50 of {', '.join(counted)}); p99 above it by "
                      f"{_cell([e['p99'] - floor for e in e2e], '{:.1f}')} ms.", ""]
        lines += ["| stage | median (ms) | tail mean (ms) | excess (ms) | share of the excess |",
                  "|---|---|---|---|---|"]
        # every stage any run reports (files from before 2026-12-06 lack sensor_delivery),
        # each over the runs that report it
        stages = list(dict.fromkeys(s for t in tails for s in t["stages"]))
        stages.sort(key=lambda s: -statistics.median(
            t["stages"][s]["excess"] for t in tails if s in t["stages"]))
        for stage in stages:
            rows = [t["stages"][stage] for t in tails if stage in t["stages"]]
            shares = [r["share"] for r in rows if r["share"] is not None]
            lines.append(
                f"| {stage} | {_cell([r['p50'] for r in rows])} | "
                f"{_cell([r['tail_mean'] for r in rows])} | {_cell([r['excess'] for r in rows])} "
                f"| {_cell([100 * s for s in shares], '{:.0f} %') if shares else '-'} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("directory", nargs="?", type=Path, default=Path("benchmarks/results/m2t_tail"),
                    help="a directory of `bench cpu` runs (cpu-*.json); tail.md is written there")
    directory = ap.parse_args(argv).directory
    if not directory.is_dir():
        ap.error(f"{directory} is not a directory")
    text = table(directory)
    (directory / "tail.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
