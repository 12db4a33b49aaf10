"""Fiducial registration on many random phantom placements, in simulated time.

Each placement: a scene (breast, localization, severity in turn) with its own seed, placed
with a random shift (normal, ``--shift-sd`` mm per axis) and turn (uniform within
``--max-yaw`` deg) unknown to the station; ``remote_site.registration.calibrate_with_fiducials``
runs on the simulated arm and sensor of the realistic world. Outcomes:

- **right**: all four corners of a 60 mm square (+-30 mm) mapped within 1 mm of the truth;
- **silently wrong**: an estimate returned, some corner further off (the dangerous case:
  findings placed wrong at a claimed precision);
- **refused**: a ``CalibrationError`` (the station does not start; the lab re-places the
  phantom).

``--tree DIR`` runs another checkout's procedure (e.g. ``git archive <rev> | tar -x -C DIR``)
in a child process for a before/after on the same placements.

Run: ``python benchmarks/bench_registration.py`` (about a minute); writes
``benchmarks/results/registration.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SETTINGS = ((6.0, 3.0, 90, 2), (20.0, 3.0, 90, 1), (35.0, 6.0, 150, 3))


def placements(seed: int, n: int, max_yaw: float, shift_sd: float
               ) -> list[tuple[str, int, float, float, float]]:
    import numpy as np

    rng = np.random.default_rng(seed)
    out = []
    for t in range(n):
        scene = ("breast", "localization", "severity")[t % 3]
        out.append((scene, int(rng.integers(0, 10000)), float(rng.normal(0, shift_sd)),
                    float(rng.normal(0, shift_sd)), float(rng.uniform(-max_yaw, max_yaw))))
    return out


def run(rows: list[tuple[str, int, float, float, float]]) -> dict[str, object]:
    """Register every placement with this tree's code (imported from ``sys.path``)."""
    import numpy as np

    from remote_site.agent.world import REALISTIC, Registration, world_for
    from remote_site.arm.base import ArmLimits
    from remote_site.arm.sim import SimArm, SimArmConfig
    from remote_site.phantom import make_scene
    from remote_site.reconstruction.reconstructor import Reconstructor
    from remote_site.registration import calibrate_with_fiducials, guarded
    from remote_site.sensor.sim_calibration import simulated_calibration
    from remote_site.sensor.simulator import SimulatedSensor
    from shared.errors import CalibrationError

    rec = Reconstructor(simulated_calibration())
    counts = {"right": 0, "wrong": 0, "refused": 0}
    wrong_mm: list[float] = []
    corners = ([30.0, 30.0], [-30.0, 30.0], [30.0, -30.0], [-30.0, -30.0])
    for scene, seed, dx, dy, yaw in rows:
        reg = Registration(dx, dy, 0.2, yaw)
        world = world_for(make_scene(scene, seed), REALISTIC, seed, reg)
        arm = SimArm(config=SimArmConfig(realtime=False, loop_hz=250.0), limits=ArmLimits(),
                     **world.arm_options())
        holder: list[SimulatedSensor] = []
        sensor = SimulatedSensor(**world.sensor_options(
            arm, lambda holder=holder: holder[0]))  # type: ignore[misc]
        holder.append(sensor)
        arm.connect()
        sensor.connect()
        try:
            est = calibrate_with_fiducials(guarded(arm), sensor, rec,
                                           [f.center_mm for f in world.phantom.fiducials],
                                           wait=arm.advance)
            err = max(float(np.linalg.norm(est.arm_to_phantom(c)
                                           - np.array(reg.to_phantom((*c, 0))[:2])))
                      for c in corners)
            if err < 1.0:
                counts["right"] += 1
            else:
                counts["wrong"] += 1
                wrong_mm.append(err)
        except CalibrationError:
            counts["refused"] += 1
        finally:
            sensor.disconnect()
            arm.disconnect()
    return {**counts, "wrong_mm": wrong_mm}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", type=Path, default=None,
                        help="another checkout to compare (its code, same placements)")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:  # run the placements given as JSON with the code on sys.path
        print(json.dumps(run([(str(r[0]), int(r[1]), float(r[2]), float(r[3]), float(r[4]))
                              for r in json.loads(args.child)])))
        return 0
    # the parent only: a child must import the tree it was given, not this checkout
    sys.path.insert(0, str(ROOT))
    from benchmarks.tree_child import run_in_tree

    load = os.getloadavg()[0]
    t0 = time.monotonic()
    trees = [("this tree", ROOT)] + ([("--tree", args.tree.resolve())] if args.tree else [])
    lines = ["| turn (uniform) | shift sd | placements | code | right | silently wrong "
             "(corner error) | refused |", "|---|---|---|---|---|---|---|"]
    for max_yaw, shift_sd, n, seed in SETTINGS:
        rows = placements(seed, n, max_yaw, shift_sd)
        for name, tree in trees:
            r = run_in_tree(__file__, tree, rows)
            wrong = (f"{r['wrong']} ({min(r['wrong_mm']):.1f}-{max(r['wrong_mm']):.1f} mm)"
                     if r["wrong"] else "0")
            lines.append(f"| +-{max_yaw:g} deg | {shift_sd:g} mm | {n} | {name} | "
                         f"{r['right']} | {wrong} | {r['refused']} |")
            print(lines[-1], flush=True)
    md = ["# Fiducial registration on random phantom placements", "",
          f"Reproduce: `python benchmarks/bench_registration.py"
          f"{' --tree DIR' if args.tree else ''}` ({time.monotonic() - t0:.0f} s, load "
          f"average {load:.2f} at the start). Simulated arm and sensor of the realistic world, "
          "in simulated time; scenes breast, localization, severity in turn, each placement "
          "its own seed. Right = the four corners of a 60 mm square within 1 mm of the truth; "
          "silently wrong = an estimate further off; refused = a CalibrationError "
          "(`docs/registration.md`).", "", *lines, ""]
    from lab.bench.results import write_results

    write_results(ROOT / "benchmarks" / "results", "registration", "\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
