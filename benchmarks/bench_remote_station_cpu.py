"""The remote station alone: CPU per second and per frame, before/after, paired, in-process.

The whole demo (``teletouch bench cpu``, ``bench_remote_cpu.py``) is the honest setting, but
on a machine shared with other jobs its per-run figures swing with the load. This benchmark
runs the remote station by itself - the real :class:`RemoteStation` with the demo's default
simulated world (breast phantom, realistic noise, registration error, LED drift), the sim arm
and sensor, reconstruction, stiffness, compact tactile codec, 120 Hz frame clock with capture
on pose - against an in-memory link fed by a scripted operator (platform states at 250 Hz:
a press on a tumor, a press beside it, a slide across it, and hovering), for a fixed time.

Measured (exact, kernel accounting): the process' CPU seconds per wall second, and each
thread's (``/proc/self/task/<native_id>/stat``, named by ``threading``); the simulated
hardware's share is the thread CPU spent inside the simulator's entry points (the sensor's
``_latest``: phantom contact + rendering; the arm: its 1 kHz thread before, the steps run on
reads after), the rest is product code (and the operator script, the same on both sides).

Paired: each checkout is run as a child process with that checkout first on ``PYTHONPATH``
(``git archive BASE | tar -x -C DIR`` gives a base tree), ABBA over the rounds.

Run: ``python benchmarks/bench_remote_station_cpu.py --before /tmp/base --after . --rounds 3``
(writes ``benchmarks/results/remote_station_cpu.{md,json}`` unless ``--no-write``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from lab.bench.results import median_known, write_results

RESULTS = Path(__file__).resolve().parent / "results"
SIDES = ("before", "after")
_CLK = os.sysconf("SC_CLK_TCK")


def _task_cpu_s(tid: int) -> float:
    with open(f"/proc/self/task/{tid}/stat") as f:
        stat = f.read()
    fields = stat[stat.rfind(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / _CLK


def _child(duration_s: float, seed: int) -> dict[str, Any]:
    """Run the station once in this process (the checkout under test is on sys.path)."""
    from remote_site.agent.config import RemoteAgentConfig
    from remote_site.agent.devices import open_world_arm, open_world_sensor
    from remote_site.agent.pipeline import FramePipeline
    from remote_site.agent.station import RemoteStation
    from remote_site.agent.stiffness_stage import StiffnessStage
    from remote_site.agent.world import build_world
    from remote_site.arm.safety import SafeArm
    from remote_site.arm.sim import SimArm
    from remote_site.phantom.reference_presses import sim_stiffness_calibration
    from remote_site.reconstruction.reconstructor import Reconstructor
    from remote_site.sensor.sim_calibration import simulated_calibration
    from remote_site.sensor.simulator import SimulatedSensor
    from remote_site.stiffness.estimator import StiffnessConfig
    from remote_site.tactile import TactileAssembler
    from shared.client import LinkCounters
    from shared.freshness import ClockView
    from shared.protocol import Message, PlatformState
    from shared.timebase import now_us
    from shared.workspace import WorkspaceMap

    sim_cpu = {"sensor": 0.0, "arm": 0.0}

    def timed(kind: str, fn: Any) -> Any:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            t0 = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                sim_cpu[kind] += time.thread_time() - t0
        return wrapper

    setattr(SimulatedSensor, "_latest", timed("sensor", SimulatedSensor._latest))  # noqa: B010
    arm_in_thread = hasattr(SimArm, "_loop")
    if not arm_in_thread:  # the steps run inside the reads
        setattr(SimArm, "_catch_up", timed("arm", getattr(SimArm, "_catch_up")))  # noqa: B010,B009

    class MemoryLink:
        def __init__(self) -> None:
            self.counters = LinkCounters(connects=1)
            self.sent = 0
            self.inbox: asyncio.Queue[Message] = asyncio.Queue()
            self.is_connected = True

        @property
        def clock_view(self) -> ClockView:  # exact offsets, reported just now (not aged)
            return ClockView({"local": 0, "remote": 0}, {"local": 0, "remote": 0}, now_us())

        def link_down_for_s(self, now_s: float | None = None) -> float:
            return 0.0

        async def send(self, msg: Message) -> None:
            self.sent += 1

        async def recv(self, timeout_s: float | None = None) -> Message:
            return await self.inbox.get()

    world = build_world("breast", seed)
    ws = WorkspaceMap()
    arm = open_world_arm("sim", world)
    sensor = open_world_sensor("sim", world, arm)
    arm.connect()
    sensor.connect()
    world.prepare_sensor(sensor)
    safe = SafeArm(arm, bounds_mm=ws.phantom_bounds_mm)
    calib = sim_stiffness_calibration()
    stiffness = StiffnessStage(StiffnessConfig().with_calibration(calib))
    pipeline = FramePipeline(sensor, Reconstructor(simulated_calibration()),
                             TactileAssembler(ws, stiffness_to_k=calib.stiffness_to_k()),
                             stiffness, arm.state)
    pipeline.warm_up()
    link = MemoryLink()
    station = RemoteStation(link, safe, pipeline, stiffness, ws.forward,
                            RemoteAgentConfig(frame_rate_hz=120.0, status_interval_s=60.0))
    tumor = world.phantom.tumors[0].center_mm

    def operator_xyz(t: float) -> tuple[float, float, float]:
        u = (t % 8.0) / 8.0  # 8 s cycle: press tumor, press beside, slide, hover
        x, y = float(tumor[0]), float(tumor[1])
        if u < 0.25:
            v = u / 0.25
            return x, y, 2.0 - 5.0 * min(v / 0.6, 1.0)
        if u < 0.5:
            v = (u - 0.25) / 0.25
            return x, y + 15.0, 2.0 - 5.0 * min(v / 0.6, 1.0)
        if u < 0.75:
            v = (u - 0.5) / 0.25
            return x - 10.0 + 20.0 * v, y, -1.5
        return x + 10.0 - 20.0 * (u - 0.75) / 0.25, y, 5.0

    stop = asyncio.Event()

    async def operator() -> None:
        t0 = time.monotonic()
        seq = 0
        while (t := time.monotonic() - t0) < duration_s:
            p = ws.inverse(list(operator_xyz(t)))
            seq += 1
            ts = now_us()
            link.inbox.put_nowait(PlatformState(seq=seq, ts_us=ts, position_mm=(
                float(p[0]), float(p[1]), float(p[2]))).with_hop("remote", "station_rx", ts))
            await asyncio.sleep(0.004)
        stop.set()

    async def main() -> dict[str, Any]:
        start: dict[int, float] = {}
        names: dict[int, str] = {}
        result: dict[str, Any] = {}

        async def sample_start() -> None:
            await asyncio.sleep(1.0)  # threads started, first frames done
            for th in threading.enumerate():
                if th.native_id is not None:
                    start[th.native_id] = _task_cpu_s(th.native_id)
                    names[th.native_id] = th.name
            result["sim0"] = dict(sim_cpu)
            result["t0"] = time.monotonic()
            result["frames0"] = station.pipeline.processed

        async def sample_end() -> None:
            await asyncio.sleep(duration_s - 0.5)
            end = {}
            for th in threading.enumerate():
                if th.native_id is not None and th.native_id in start:
                    end[th.native_id] = _task_cpu_s(th.native_id)
            result["end"] = end
            result["sim1"] = dict(sim_cpu)
            result["t1"] = time.monotonic()
            result["frames1"] = station.pipeline.processed

        op = asyncio.create_task(operator())
        s0 = asyncio.create_task(sample_start())
        s1 = asyncio.create_task(sample_end())
        await station.run(stop, duration_s=duration_s + 5.0)
        await asyncio.gather(op, s0, s1)
        wall = result["t1"] - result["t0"]
        threads = {f"{names[tid]}": (result["end"][tid] - start[tid]) / wall
                   for tid in result["end"]}
        total = sum(threads.values())
        sim_sensor = (result["sim1"]["sensor"] - result["sim0"]["sensor"]) / wall
        sim_arm = ((result["sim1"]["arm"] - result["sim0"]["arm"]) / wall if not arm_in_thread
                   else threads.get("sim-arm-1khz", 0.0))
        frames = result["frames1"] - result["frames0"]
        summary = station.summary()
        return {"wall_s": wall, "cores": total, "threads": threads,
                "sim_sensor": sim_sensor, "sim_arm": sim_arm,
                "product": total - sim_sensor - sim_arm,
                "frames_per_s": frames / wall,
                "ms_per_frame": total / (frames / wall) * 1e3 if frames else None,
                "captures": summary["frames"]["captures"],
                "watchdog_halts": summary["arm"]["watchdog_halts"],
                "presses": summary["stiffness"].get("presses"),
                "sent": link.sent, "platform_states": summary["platform_states"]}

    out = asyncio.run(main())
    safe.close()
    sensor.disconnect()
    arm.disconnect()
    return out


def _run_side(root: Path, duration_s: float, seed: int) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(root)}
    load = os.getloadavg()[0]
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child",
                           "--duration-s", f"{duration_s:g}", "--seed", str(seed)],
                          cwd=root, env=env, capture_output=True, text=True, timeout=600,
                          check=False)
    if proc.returncode != 0:
        return {"error": proc.stderr[-2000:], "load_1min": load}
    run = json.loads(proc.stdout.strip().splitlines()[-1])
    run["load_1min"] = load
    return run


def _f(v: float | None, digits: int = 3) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


METRICS = (("remote station (cores)", "cores"), ("product code (cores)", "product"),
           ("sim sensor + phantom (cores)", "sim_sensor"), ("sim arm (cores)", "sim_arm"),
           ("CPU per tactile frame (ms)", "ms_per_frame"), ("tactile frames / s", "frames_per_s"))


def _report(runs: dict[str, list[dict[str, Any]]], args: argparse.Namespace) -> str:
    ok = {s: [r for r in runs[s] if "error" not in r] for s in SIDES}
    tag = f" ({args.tag})" if args.tag else ""
    lines = [f"# Remote station alone: CPU, paired before/after{tag}",
             "", f"`python benchmarks/bench_remote_station_cpu.py --before {args.before} --after "
             f"{args.after} --rounds {args.rounds} --duration-s {args.duration_s:g}"
             f"{' --tag ' + args.tag if args.tag else ''}`", "",
             f"Machine: nproc {os.cpu_count()}, Python {platform.python_version()}. Other jobs "
             "may share the machine (1-minute load average per run below): compare medians "
             "and ratios of the same minutes. Method: see the module docstring.", "",
             f"Before: {args.before_note}. After: {args.after_note}.", "",
             "| metric | before (median) | after (median) | after / before |", "|---|---|---|---|"]
    for name, key in METRICS:
        b = median_known([r.get(key) for r in ok["before"]])
        a = median_known([r.get(key) for r in ok["after"]])
        ratio = a / b if a is not None and b else None
        lines.append(f"| {name} | {_f(b)} | {_f(a)} | {_f(ratio, 2)} |")
    lines += ["", "## Runs", "", "| run | load 1 min | cores | product | sim sensor | sim arm | "
              "ms / frame | frames/s | captures (on_pose/moving/idle) | watchdog halts | "
              "threads (cores) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted((r for s in SIDES for r in runs[s]), key=lambda r: r["order"]):
        if "error" in r:
            lines.append(f"| {r['label']} | {r['load_1min']:.1f} | failed: "
                         f"{r['error'][-200:]!r} |||||||||")
            continue
        c = r["captures"]
        th = ", ".join(f"{k} {v:.3f}" for k, v in
                       sorted(r["threads"].items(), key=lambda kv: -kv[1]) if v >= 0.002)
        lines.append(f"| {r['label']} | {r['load_1min']:.1f} | {_f(r['cores'])} | "
                     f"{_f(r['product'])} | {_f(r['sim_sensor'])} | {_f(r['sim_arm'])} | "
                     f"{_f(r['ms_per_frame'], 2)} | {r['frames_per_s']:.0f} | "
                     f"{c['on_pose']}/{c['moving']}/{c['idle']} | {r['watchdog_halts']} | {th} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--before", type=Path)
    ap.add_argument("--after", type=Path)
    ap.add_argument("--before-note", default="base commit")
    ap.add_argument("--after-note", default="this branch")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--duration-s", type=float, default=16.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--tag", default="")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_child(args.duration_s, args.seed)))
        return 0
    if args.before is None or args.after is None:
        ap.error("--before and --after are required")
    roots = {"before": args.before.resolve(), "after": args.after.resolve()}
    runs: dict[str, list[dict[str, Any]]] = {s: [] for s in SIDES}
    n = 0
    for i in range(args.rounds):
        for side in (SIDES if i % 2 == 0 else SIDES[::-1]):
            run = _run_side(roots[side], args.duration_s, args.seed)
            run["label"], run["order"] = f"{side}-{i + 1}", n
            n += 1
            runs[side].append(run)
            print(f"{run['label']}: load {run['load_1min']:.1f} "
                  + (f"FAILED {run['error'][-300:]}" if "error" in run else
                     f"{run['cores']:.3f} cores, {_f(run['ms_per_frame'], 2)} ms/frame, "
                     f"{run['frames_per_s']:.0f} fps"), flush=True)
    text = _report(runs, args)
    if not args.no_write:
        write_results(RESULTS, f"remote_station_cpu{'_' + args.tag if args.tag else ''}", text,
                      data=runs)
    print(text)  # after writing: a closed pipe must not lose the results
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
