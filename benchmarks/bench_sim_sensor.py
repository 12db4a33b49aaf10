"""The simulated sensor's frame, per stage, on several checkouts in the same minutes.

The demo's remote station renders every tactile frame with the simulated GelSight-style
sensor: the phantom's contact depth at the arm's pose (``contact``, with the session's
registration yaw applied: ``rotate``), then the photometric model (``render``: the drape
blur and checks, the camera noise, the shading kernel). This times each stage by the
thread's CPU time over the same poses (a raster over the breast scene at pressing depths
from 0.5 to 3 mm, and some out of contact) for each *tree*, a checkout with its own
``.venv``, in a fresh child process per tree and round, the trees' order reversed every
round. The table pools each stage's times over the rounds, and gives the ratios to the first
tree round by round.

Two pacings per child: ``warm``, frames back to back; ``paced``, a sleep of one frame
period of the demo (12.5 ms, 80 frames/s) before each frame, so that the caches are as cold
as the demo leaves them between frames.

Error: each child also writes its noise-free frames of the same poses (LED gain 1.01, 0.99,
1.0); the report gives every tree's largest difference from the first tree's frames, in
digital numbers, and the share of values that differ. The kernel's agreement with an
independent numpy evaluation of the model is a test (``tests/remote_site/
test_sensor_shading.py``), not this benchmark's.

Run: ``python benchmarks/bench_sim_sensor.py --tree base=../base --tree new=. --rounds 4
--out benchmarks/results/sim_sensor``. Writes ``runs.json`` and ``README.md`` (table).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

#: the demo's default frame rate: the pause before each frame of the ``paced`` pacing
PACED_GAP_S = 1.0 / 80.0
#: the LED gain of the noise-free frames compared across trees
GAIN = (1.01, 0.99, 1.0)
STAGES = ("contact", "rotate", "render", "frame")


def poses() -> list[tuple[float, float, float]]:
    """A raster over the breast scene (tumors near (6, -10) and (-20, -21) mm), pressing 0.5
    to 3 mm deep, and one pose in eight lifted out of contact."""
    out = []
    k = 0
    for y in np.linspace(-30.0, 5.0, 8):
        for x in np.linspace(-30.0, 15.0, 10):
            k += 1
            z = 2.0 if k % 8 == 0 else -(0.5 + 2.5 * ((k * 7) % 11) / 10.0)
            out.append((float(x), float(y), z))
    return out


def child(frames_path: Path, repeats: int) -> dict[str, Any]:
    """Time the stages in this interpreter's tree (see the module docstring)."""
    from remote_site.agent.world import _rotate, build_world
    from remote_site.phantom.phantom import PixelGrid
    from remote_site.sensor.photometric import PhotometricModel

    world = build_world("breast", 0)
    model = PhotometricModel(world.sensor_settings(), seed=0)
    s = model.settings
    grid = PixelGrid(width_px=s.shape_hw[1], height_px=s.shape_hw[0], mm_per_px=s.mm_per_px)
    world.phantom.modulus_table(s.mm_per_px)
    yaw = world.registration.yaw_deg
    gain = np.asarray(GAIN)
    where = poses()

    def one(pose: tuple[float, float, float], noise: bool) -> tuple[list[int], np.ndarray]:
        t0 = time.thread_time_ns()
        contact = world.phantom.contact(world.true_pose(pose), grid)
        t1 = time.thread_time_ns()
        depth = _rotate(contact.depth_map_mm, yaw) if contact.in_contact else \
            contact.depth_map_mm
        t2 = time.thread_time_ns()
        rgb = model.render(depth, noise=noise, gain=gain)
        t3 = time.thread_time_ns()
        return [t1 - t0, t2 - t1, t3 - t2, t3 - t0], rgb

    for pose in where[:8]:  # compile and build caches; the eighth pose is out of contact
        one(pose, True)
    times: dict[str, dict[str, list[float]]] = {}
    for pacing in ("warm", "paced"):
        rows: list[list[int]] = []
        for _ in range(repeats):
            for pose in where:
                if pacing == "paced":
                    time.sleep(PACED_GAP_S)
                rows.append(one(pose, True)[0])
        times[pacing] = {st: [r[i] / 1e3 for r in rows] for i, st in enumerate(STAGES)}
    np.save(frames_path, np.stack([one(p, False)[1] for p in where]))
    return {"times_us": times, "in_contact": sum(p[2] < 0 for p in where), "poses": len(where),
            "python": sys.version.split()[0], "numpy": np.__version__}


def _run_tree(name: str, root: Path, work: Path, rnd: int, repeats: int) -> dict[str, Any]:
    frames = work / f"{name}-{rnd}.npy"
    proc = subprocess.run([str(root / ".venv" / "bin" / "python"), str(Path(__file__).resolve()),
                           "--child", str(frames), "--repeats", str(repeats)],
                          cwd=root, env={**os.environ, "PYTHONPATH": str(root)},
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"tree {name} ({root}) failed:\n{proc.stderr}")
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    result.update(tree=name, root=str(root), round=rnd, frames=str(frames))
    return result


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q))


def report(runs: list[dict[str, Any]], trees: list[str], work: Path) -> str:
    """The README table: per tree and pacing, each stage's p50 / p99 CPU us over all rounds;
    the render's and the whole frame's p50 against the first tree's in the same round (the
    range over rounds: a disturbed round shows instead of moving a pooled figure); and the
    frames' difference from the first tree's."""
    first = np.load(work / f"{trees[0]}-1.npy").astype(int)
    lines = ["| tree | pacing | contact p50 / p99 us | rotate | render | frame | render p50 "
             f"vs {trees[0]}, per round | frame p50 vs {trees[0]}, per round | frames/s of "
             "one core (p50) | largest difference DN | values that differ |",
             "|" + "---|" * 11]
    pooled: dict[tuple[str, str], dict[str, list[float]]] = {}
    per_round: dict[tuple[str, str, int], dict[str, float]] = {}
    for run in runs:
        for pacing, stages in run["times_us"].items():
            into = pooled.setdefault((run["tree"], pacing), {st: [] for st in STAGES})
            for st in STAGES:
                into[st] += stages[st]
            per_round[(run["tree"], pacing, run["round"])] = {
                st: _pct(stages[st], 50) for st in STAGES}
    rounds = sorted({run["round"] for run in runs})

    def ratios(tree: str, pacing: str, stage: str) -> str:
        r = [per_round[(tree, pacing, n)][stage] / per_round[(trees[0], pacing, n)][stage]
             for n in rounds]
        return f"x{min(r):.2f}-{max(r):.2f}"

    for pacing in ("warm", "paced"):
        for tree in trees:
            t = pooled[(tree, pacing)]
            frames = np.load(work / f"{tree}-1.npy").astype(int)
            diff = np.abs(frames - first)
            cells = [f"{_pct(t[st], 50):.0f} / {_pct(t[st], 99):.0f}" for st in STAGES]
            lines.append(f"| {tree} | {pacing} | " + " | ".join(cells)
                         + f" | {ratios(tree, pacing, 'render')} | "
                         f"{ratios(tree, pacing, 'frame')} | {1e6 / _pct(t['frame'], 50):.0f} | "
                         f"{int(diff.max())} | {np.count_nonzero(diff) / diff.size:.2e} |")
    return "\n".join(lines)



def main(argv: list[str] | None = None) -> int:
    count: Callable[[str], int] = int  # a child: its parent checked the values
    if "--child" not in (sys.argv[1:] if argv is None else argv):
        # here, not at the top: a child runs with another tree's packages first on its path
        repo = str(Path(__file__).resolve().parents[1])
        if repo not in sys.path:
            sys.path.insert(0, repo)
        from benchmarks.cli_args import count

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", action="append", default=[], metavar="NAME=ROOT",
                    help="a checkout with its own .venv (repeat; the first is the reference)")
    ap.add_argument("--rounds", type=count, default=4)
    ap.add_argument("--repeats", type=count, default=3, help="passes over the poses per pacing")
    ap.add_argument("--out", type=Path, help="results directory (runs.json, README.md)")
    ap.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        print(json.dumps(child(args.child, args.repeats)))
        return 0
    if not args.tree or args.out is None:
        ap.error("--tree NAME=ROOT (at least one) and --out are required")
    trees = []
    for spec in args.tree:
        name, sep, root = spec.partition("=")
        if not sep or not (Path(root) / ".venv" / "bin" / "python").exists():
            ap.error(f"--tree {spec!r}: NAME=ROOT, with ROOT/.venv/bin/python")
        trees.append((name, Path(root).resolve()))
    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for rnd in range(1, args.rounds + 1):
            order = trees if rnd % 2 else trees[::-1]
            for name, root in order:
                runs.append(_run_tree(name, root, work, rnd, args.repeats))
                print(f"round {rnd} {name}: frame p50 "
                      f"{_pct(runs[-1]['times_us']['paced']['frame'], 50):.0f} us (paced)",
                      flush=True)
        table = report(runs, [n for n, _ in trees], work)
    load = os.getloadavg()[0]
    (args.out / "runs.json").write_text(json.dumps(runs, indent=1))
    (args.out / "README.md").write_text(
        "# The simulated sensor's frame per stage (`benchmarks/bench_sim_sensor.py`)\n\n"
        f"CPU us per frame (thread time), {args.rounds} rounds x {args.repeats} passes over "
        f"{runs[0]['poses']} poses ({runs[0]['in_contact']} in contact) per tree and pacing; "
        f"trees: {', '.join(f'`{n}` = {r}' for n, r in trees)}; 1-minute load at the end "
        f"{load:.2f}. Differences: noise-free frames of the same poses against the first "
        "tree's.\n\n" + table + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
