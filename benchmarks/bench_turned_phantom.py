"""A turned phantom through the live station's path: registration, then palpation and analysis.

The OOD benchmark records through the designed map and applies the registration in the
analysis; the live remote station instead puts the registration into its workspace map and
the local station analyses with the designed map. This script runs the live order in
simulated time: for each yaw, the OOD ``type`` phantom (seeds 15000 + i, a benign and a
malignant inclusion), the registration measured by the fiducial procedure, the session
recorded through ``estimate.workspace_to_arm(WorkspaceMap())`` (as the station does), the
analysis in the designed map (as the local station does), scored in phantom coordinates.

``--tree DIR`` runs another checkout's code on the same cases (before/after).

Run: ``python benchmarks/bench_turned_phantom.py [--tree DIR]`` (about two minutes per tree);
writes ``benchmarks/results/turned_phantom.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

YAWS_DEG = (3.0, -3.0, 8.0, -8.0, 10.0, -10.0, 12.0, -12.0, 14.0, -14.0, 16.0, -16.0, 18.0,
            -18.0, 20.0, -20.0)


def run(yaws: list[float]) -> list[dict[str, object]]:
    """Each yaw's session with the code on ``sys.path``."""
    from lab.bench.palpation_ood import make_case
    from lab.bench.palpation_session import simulate_registration, simulate_session
    from lab.scoring import score_findings
    from local_site.palpation import analyse_recording
    from remote_site.agent.world import Registration, world_for
    from remote_site.phantom.phantom_file import phantom_from_dict
    from shared.workspace import WorkspaceMap

    out: list[dict[str, object]] = []
    for i, yaw in enumerate(yaws):
        case = make_case("type", i, len(yaws), 15000 + i)
        phantom = phantom_from_dict(case.phantom, case.seed, source=case.key)
        world = world_for(phantom, case.realism, case.seed, Registration(1.0, -1.5, 0.1, yaw))
        est = simulate_registration(world)
        rec = simulate_session(world, case.operator,
                               workspace=est.workspace_to_arm(WorkspaceMap()),
                               frame_rate_hz=case.frame_rate_hz)
        truth = world.phantom.ground_truth()
        score = score_findings(analyse_recording(rec, WorkspaceMap()), truth)
        kinds = {t["id"]: t["kind"] for t in truth["tumors"]}
        out.append({"yaw_deg": yaw, "false_positives": score["false_positives"],
                    "matches": [{"kind": kinds[m["id"]], "found_kind": m["found_kind"],
                                 "error_mm": m["error_mm"]} for m in score["matches"]],
                    "tumors": len(truth["tumors"])})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", type=Path, default=None,
                        help="another checkout to compare (its code, same cases)")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(run([float(y) for y in json.loads(args.child)])))
        return 0
    # the parent only: a child must import the tree it was given, not this checkout
    sys.path.insert(0, str(ROOT))
    from benchmarks.tree_child import run_in_tree

    load = os.getloadavg()[0]
    t0 = time.monotonic()
    trees = [("this tree", ROOT)] + ([("--tree", args.tree.resolve())] if args.tree else [])
    results = {}
    for name, tree in trees:
        results[name] = run_in_tree(__file__, tree, list(YAWS_DEG))
    lines = ["| yaw deg | " + " | ".join(f"{n}: benign typed, malignant typed, "
                                         "localization mm, FP" for n in results) + " |",
             "|---|" + "---|" * len(results)]
    summary = []
    for k, yaw in enumerate(YAWS_DEG):
        cells = []
        for rows in results.values():
            r = rows[k]
            by = {m["kind"]: m for m in r["matches"]}
            cells.append(f"{by['benign']['found_kind'] if 'benign' in by else 'missed'}, "
                         f"{by['malignant']['found_kind'] if 'malignant' in by else 'missed'}, "
                         + "/".join(f"{m['error_mm']:.2f}" for m in r["matches"])
                         + f", {r['false_positives']}")
        lines.append(f"| {yaw:+g} | " + " | ".join(cells) + " |")
    for name, rows in results.items():
        matches = [m for r in rows for m in r["matches"]]
        right = sum(m["found_kind"] == m["kind"] for m in matches)
        errors = [m["error_mm"] for m in matches]
        summary.append(f"- {name}: typed right {right} of {sum(r['tumors'] for r in rows)}"
                       f" inclusions, found {len(matches)}, localization mean "
                       f"{sum(errors) / len(errors):.3f} mm, max {max(errors):.3f} mm, false "
                       f"positives {sum(r['false_positives'] for r in rows)}")
    md = ["# A turned phantom through the live station's path", "",
          f"Reproduce: `python benchmarks/bench_turned_phantom.py"
          f"{' --tree DIR' if args.tree else ''}` ({time.monotonic() - t0:.0f} s, load "
          f"average {load:.2f} at the start). OOD `type` phantoms (seeds 15000 + i), shifted "
          "(1.0, -1.5) mm and turned by the yaw; fiducial registration, the session recorded "
          "through the registered map, the analysis in the designed map (the live order), "
          "scored in phantom coordinates.", "", *summary, "", *lines, ""]
    from lab.bench.results import write_results

    write_results(ROOT / "benchmarks" / "results", "turned_phantom", "\n".join(md))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
