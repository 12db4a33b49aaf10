"""Remote pipeline benchmark: sensor frame -> tactile frame latency, resolution error, skips.

Run from the repository root::

    python benchmarks/bench_remote_pipeline.py            # the committed results
    python benchmarks/bench_remote_pipeline.py --quick    # a short CI-like run

Three parts, one run:

1. **Latency at 60 and 120 fps.** The real :class:`RemoteStation` (sim arm with its 1 kHz
   loop, sim sensor rendering the breast phantom, reconstruction, stiffness, assembly) runs
   against an in-memory link fed by a scripted operator (press a tumor, press the
   background, slide over the tumor) at 250 Hz. Per tactile frame: pipeline latency
   (render + reconstruct + stiffness/assembly, p50/p99), and ``arm_command -> tactile_ready``
   from the hops, which includes the wait for the next frame; achieved frame rate and CPU.
2. **Reconstruction resolution.** Contact frames reconstructed at pooling factors 1..16:
   time per frame against the height error (RMSE vs the true depth map and vs the full
   resolution reconstruction, both area-averaged to the output grid).
3. **Skips.** No-contact frames with and without the integration skip; stiffness fitted
   only on loading segments vs a naive fit of the last 200 samples on every frame.

Writes ``benchmarks/results/remote_pipeline.md`` and ``remote_pipeline.png``.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from remote_site.agent.config import RemoteAgentConfig
from remote_site.agent.devices import open_world_arm, open_world_sensor
from remote_site.agent.pipeline import FramePipeline
from remote_site.agent.station import RemoteStation, percentiles_ms
from remote_site.agent.stiffness_stage import StiffnessStage
from remote_site.agent.world import SimWorld
from remote_site.arm.base import Arm
from remote_site.arm.safety import SafeArm
from remote_site.phantom.reference_presses import sim_stiffness_calibration
from remote_site.phantom.scenes import make_scene
from remote_site.reconstruction.reconstructor import ReconstructionSettings, Reconstructor
from remote_site.sensor.base import TactileSensor
from remote_site.sensor.sim_calibration import simulated_calibration
from remote_site.sensor.simulator import SimulatedSensor
from remote_site.stiffness.estimator import StiffnessConfig, estimate_press
from remote_site.tactile import TactileAssembler
from shared.client import LinkCounters
from shared.freshness import ClockView
from shared.protocol import Message, PlatformState, TactileCompact, TactileFrame
from shared.report import emit, format_table
from shared.timebase import now_us
from shared.workspace import WorkspaceMap

RESULTS = Path(__file__).resolve().parent / "results"
SCENE, SEED = "breast", 1


class MemoryLink:
    """In-memory stand-in for the station's relay link (always up, zero clock offsets)."""

    def __init__(self) -> None:
        self.counters = LinkCounters(connects=1)
        self.sent: list[Message] = []
        self.inbox: asyncio.Queue[Message] = asyncio.Queue()
        self.is_connected = True
        self.clock_offsets_us: dict[str, int | None] = {"local": 0, "remote": 0}

    @property
    def clock_view(self) -> ClockView:
        """One process, one clock: exact offsets (zero error bound), reported just now (a
        view received at time 0 had aged by the drift bound into hours of uncertainty, and
        the station refused every command)."""
        return ClockView(self.clock_offsets_us, {"local": 0, "remote": 0}, now_us())

    def link_down_for_s(self, now_s: float | None = None) -> float:
        return 0.0

    async def send(self, msg: Message) -> None:
        self.sent.append(msg)

    async def recv(self, timeout_s: float | None = None) -> Message:
        return await self.inbox.get()


def operator_xyz(t_s: float, tumor_xy: tuple[float, float], duration_s: float
                 ) -> tuple[float, float, float]:
    """Scripted palpation in phantom mm: press the tumor, press the background, slide."""
    u = t_s / duration_s
    bg = (tumor_xy[0], tumor_xy[1] - 20.0 if tumor_xy[1] > 0 else tumor_xy[1] + 20.0)

    def press(v: float) -> float:  # v in [0, 1): hover, descend to -3 mm, hold, lift
        if v < 0.15:
            return 2.0
        if v < 0.6:
            return 2.0 - 5.0 * (v - 0.15) / 0.45
        return -3.0 if v < 0.8 else 2.0

    if u < 0.35:
        return (*tumor_xy, press(u / 0.35))
    if u < 0.7:
        return (*bg, press((u - 0.35) / 0.35))
    v = (u - 0.7) / 0.3  # slide across the tumor at 1.5 mm depth
    return (tumor_xy[0] - 8.0 + 16.0 * v, tumor_xy[1], -1.5 if 0.1 < v < 0.9 else 1.0)


def build_station(frame_rate_hz: float, *,
                  sensor_for: Callable[[TactileSensor, Arm], TactileSensor] | None = None,
                  tactile_codec: str = "compact"
                  ) -> tuple[RemoteStation, MemoryLink, SimWorld]:
    """The station on the simulated world and an in-memory link (``sensor_for``: wraps the
    simulated sensor, e.g. as a streaming camera)."""
    world = SimWorld(make_scene(SCENE, SEED))
    ws = WorkspaceMap()
    arm = open_world_arm("sim", world)
    sensor = open_world_sensor("sim", world, arm)
    if sensor_for is not None:
        sensor = sensor_for(sensor, arm)
    arm.connect()
    sensor.connect()
    safe = SafeArm(arm, bounds_mm=ws.phantom_bounds_mm)
    calib = sim_stiffness_calibration()
    stiffness = StiffnessStage(StiffnessConfig().with_calibration(calib))
    pipeline = FramePipeline(sensor, Reconstructor(simulated_calibration()),
                             TactileAssembler(ws, stiffness_to_k=calib.stiffness_to_k()),
                             stiffness, arm.state)
    link = MemoryLink()
    cfg = RemoteAgentConfig(frame_rate_hz=frame_rate_hz, status_interval_s=60.0,
                            tactile_codec=tactile_codec)
    return RemoteStation(link, safe, pipeline, stiffness, ws.forward, cfg), link, world


async def feed_states(link: MemoryLink, phantom_xyz: Callable[[float], Sequence[float]],
                      duration_s: float, stop: asyncio.Event) -> None:
    """Platform states at 250 Hz along ``phantom_xyz(t_s)`` (phantom mm, mapped to the
    platform as the stations do) for ``duration_s``, then ``stop`` set."""
    ws = WorkspaceMap()
    t0 = time.monotonic()
    seq = 0
    while (t := time.monotonic() - t0) < duration_s:
        p = ws.inverse(list(phantom_xyz(t)))
        seq += 1
        ts = now_us()
        link.inbox.put_nowait(PlatformState(seq=seq, ts_us=ts, position_mm=(
            float(p[0]), float(p[1]), float(p[2]))).with_hop("remote", "station_rx", ts))
        await asyncio.sleep(0.004)
    stop.set()


async def run_latency(frame_rate_hz: float, duration_s: float) -> dict[str, Any]:
    """Part 1: the station at one frame rate under the scripted operator."""
    station, link, world = build_station(frame_rate_hz)
    tumor = world.phantom.tumors[1].center_mm  # the malignant one
    tumor_xy = (float(tumor[0]), float(tumor[1]))
    stop = asyncio.Event()
    cpu0, wall0 = time.process_time(), time.monotonic()
    op = asyncio.create_task(feed_states(
        link, lambda t: operator_xyz(t, tumor_xy, duration_s), duration_s, stop))
    await station.run(stop, duration_s=duration_s + 5.0)
    await op
    cpu_s, wall_s = time.process_time() - cpu0, time.monotonic() - wall0
    # either encoding (the station sends compact frames by default): the stamps are the same
    frames = [m for m in link.sent if isinstance(m, TactileFrame | TactileCompact)]
    cmd_to_ready = []
    for f in frames:
        stamps = {h.stage: h.t_us for h in f.hops}
        if "arm_command" in stamps:
            cmd_to_ready.append((stamps["tactile_ready"] - stamps["arm_command"]) / 1e6)
    pipeline_s = [c + r + a for c, r, a in zip(station.capture_s, station.reconstruct_s,
                                               station.assemble_s, strict=True)]
    periods = np.asarray(station.frame_period_s, dtype=float)
    # a motion at a uniformly random time waits E[T^2] / (2 E[T]) for the next frame start
    wait_s = float((periods**2).sum() / (2 * periods.sum())) if periods.size else float("nan")
    summary = station.summary()
    station.safe_arm.close()
    station.pipeline.sensor.disconnect()
    station.safe_arm.arm.disconnect()
    return {"fps_target": frame_rate_hz, "summary": summary,
            "pipeline": percentiles_ms(pipeline_s),
            "render": percentiles_ms(station.capture_s),
            "reconstruct": percentiles_ms(station.reconstruct_s),
            "assemble": percentiles_ms(station.assemble_s),
            "cmd_to_ready": percentiles_ms(cmd_to_ready),
            "cpu_fraction": cpu_s / wall_s, "frame_wait_mean_ms": wait_s * 1e3,
            "motion_to_tactile_mean_ms": wait_s * 1e3 + float(np.mean(pipeline_s)) * 1e3
            if pipeline_s else float("nan"), "pipeline_samples_s": pipeline_s,
            "cmd_samples_s": cmd_to_ready}


def contact_frames(n: int, seed: int = 3) -> list[tuple[np.ndarray, np.ndarray]]:
    """(depth map, rendered frame) pairs of the phantom pressed at random poses."""
    phantom = make_scene(SCENE, SEED)
    sensor = SimulatedSensor(seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    centres = [t.center_mm for t in phantom.tumors]
    for i in range(n):
        cx, cy = centres[i % len(centres)] if i % 3 else (rng.uniform(-25, 25), -30.0)
        pose = (cx + rng.uniform(-4, 4), cy + rng.uniform(-4, 4), -rng.uniform(0.5, 4.0))
        depth = phantom.contact(pose).depth_map_mm.astype(np.float32)
        out.append((depth, sensor.render(depth)))
    return out


def _area_mean(image: np.ndarray, factor: int) -> np.ndarray:
    rows, cols = image.shape[0] // factor, image.shape[1] // factor
    return image[:rows * factor, :cols * factor].reshape(rows, factor, cols, factor).mean((1, 3))


def run_resolution(frames: list[tuple[np.ndarray, np.ndarray]], repeats: int
                   ) -> list[dict[str, Any]]:
    """Part 2: reconstruction time against height error per pooling factor."""
    rec = Reconstructor(simulated_calibration())
    full = [rec.height_map(rgb).height_mm for _, rgb in frames]
    rows: list[dict[str, Any]] = []
    for factor in (1, 2, 4, 8, 16):
        pitch = 0.0634 * factor
        times, err_truth, err_full = [], [], []
        for (depth, rgb), hf in zip(frames, full, strict=True):
            best = np.inf
            for _ in range(repeats):
                t0 = time.perf_counter()
                hm = rec.height_map(rgb, out_pitch_mm=pitch if factor > 1 else None)
                best = min(best, time.perf_counter() - t0)
            times.append(best)
            h = hm.height_mm.astype(np.float64)
            err_truth.append(np.sqrt(np.mean((h - _area_mean(depth, factor)) ** 2)))
            err_full.append(np.sqrt(np.mean((h - _area_mean(hf, factor)) ** 2)))
        grid = f"{320 // factor}x{240 // factor}"
        rows.append({"factor": factor, "pitch_mm": pitch, "grid": grid,
                     "time_ms_p50": float(np.median(times)) * 1e3,
                     "frames_per_s": 1.0 / float(np.median(times)),
                     "rmse_vs_truth_mm": float(np.mean(err_truth)),
                     "rmse_vs_full_res_mm": float(np.mean(err_full))})
    full_time = rows[0]["time_ms_p50"]
    for r in rows:
        r["speedup_vs_full"] = full_time / r["time_ms_p50"]
    return rows


def run_skips(n: int, latency: dict[str, Any]) -> list[dict[str, Any]]:
    """Part 3: what the no-contact skip and loading-only stiffness save."""
    sensor = SimulatedSensor(seed=9)
    free = [sensor.render(np.zeros((240, 320))) for _ in range(n)]
    skip = Reconstructor(simulated_calibration())
    force = Reconstructor(simulated_calibration(), ReconstructionSettings(
        contact_evidence_sigmas=0.0, min_contact_area_mm2=0.0))

    def med_ms(rec: Reconstructor) -> float:
        ts = []
        for rgb in free:
            t0 = time.perf_counter()
            rec.height_map(rgb, out_pitch_mm=0.5)
            ts.append(time.perf_counter() - t0)
        return float(np.median(ts)) * 1e3

    t_skip, t_force = med_ms(skip), med_ms(force)
    s = latency["summary"]
    frac_free = s["frames"]["skipped_integration_no_contact"] / max(1, s["frames"]["processed"])
    # stiffness: loading-only segments vs a naive fit of the last 200 samples every frame
    rng = np.random.default_rng(0)
    a = np.linspace(0.0, 3.0, 200)
    f = 1.3 * np.clip(a - 0.5, 0, None) + rng.normal(0, 0.02, a.size)
    t0 = time.perf_counter()
    for _ in range(50):
        estimate_press(a, f, StiffnessConfig().with_calibration(sim_stiffness_calibration()))
    fit_ms = (time.perf_counter() - t0) / 50 * 1e3
    st = s["stiffness"]
    naive_ms_per_s = fit_ms * s["frames"]["achieved_fps"]
    loading_ms_per_s = fit_ms * st["presses"] / max(s["elapsed_s"], 1e-9)
    return [
        {"skip": "no-contact frame: integration skipped", "with_skip_ms": t_skip,
         "without_skip_ms": t_force, "saving": 1.0 - t_skip / t_force,
         "share_of_scan": frac_free},
        {"skip": "stiffness: loading segments only (ms of fitting per s)",
         "with_skip_ms": loading_ms_per_s, "without_skip_ms": naive_ms_per_s,
         "saving": 1.0 - loading_ms_per_s / naive_ms_per_s if naive_ms_per_s else 0.0,
         "share_of_scan": st["samples_skipped_not_loading"] / max(1, st["samples_seen"])},
    ]


def plot(latencies: list[dict[str, Any]], resolution: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ax = axes[0]
    for lat in latencies:
        for key, style in (("pipeline_samples_s", "-"), ("cmd_samples_s", "--")):
            v = np.sort(np.asarray(lat[key]) * 1e3)
            if v.size:
                label = ("frame->tactile" if key.startswith("pipeline") else "arm cmd->tactile")
                ax.plot(v, np.linspace(0, 1, v.size), style,
                        label=f"{lat['fps_target']:.0f} fps: {label}")
    ax.set_xlabel("latency (ms)")
    ax.set_ylabel("CDF")
    ax.set_title("remote pipeline latency")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax = axes[1]
    t = [r["time_ms_p50"] for r in resolution]
    e = [r["rmse_vs_truth_mm"] * 1e3 for r in resolution]
    ax.loglog(t, e, "o-")
    for r, x, y in zip(resolution, t, e, strict=True):
        ax.annotate(f"{r['pitch_mm']:.2f} mm", (x, y), fontsize=8)
    ax.set_xlabel("reconstruction time per frame (ms, p50)")
    ax.set_ylabel("height RMSE vs true depth (um)")
    ax.set_title("output pitch: time vs error")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and write the results."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="short run (CI)")
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    duration = 3.0 if args.quick else 8.0
    n_frames, repeats = (6, 1) if args.quick else (24, 3)
    latencies = [asyncio.run(run_latency(fps, duration)) for fps in (60.0, 120.0)]
    resolution = run_resolution(contact_frames(n_frames), repeats)
    skips = run_skips(n_frames, latencies[0])

    lat_rows = []
    for lat in latencies:
        s = lat["summary"]
        row: dict[str, Any] = {"target_fps": lat["fps_target"],
                               "achieved_fps": s["frames"]["achieved_fps"],
                               "late_frames": s["frames"]["late"]}
        for key in ("pipeline", "render", "reconstruct", "assemble", "cmd_to_ready"):
            p = lat[key] or {"p50": float("nan"), "p99": float("nan")}
            row[f"{key}_p50_ms"], row[f"{key}_p99_ms"] = p["p50"], p["p99"]
        row["frame_wait_mean_ms"] = lat["frame_wait_mean_ms"]
        row["motion_to_tactile_mean_ms"] = lat["motion_to_tactile_mean_ms"]
        row["cpu_cores"] = lat["cpu_fraction"]
        lat_rows.append(row)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    cmd = "python benchmarks/bench_remote_pipeline.py" + (" --quick" if args.quick else "")
    cols_a = ["target_fps", "achieved_fps", "late_frames", "pipeline_p50_ms", "pipeline_p99_ms",
              "cmd_to_ready_p50_ms", "cmd_to_ready_p99_ms", "frame_wait_mean_ms",
              "motion_to_tactile_mean_ms", "cpu_cores"]
    cols_b = ["target_fps", "render_p50_ms", "render_p99_ms", "reconstruct_p50_ms",
              "reconstruct_p99_ms", "assemble_p50_ms", "assemble_p99_ms"]
    lines = [
        "# Remote pipeline: sensor frame -> tactile frame",
        "",
        f"Machine: {os.cpu_count()} cores shared with other jobs, no GPU, "
        f"Python {platform.python_version()}. Reproduce: `{cmd}`.",
        f"Scene: `{SCENE}` seed {SEED}; sim arm (1 kHz loop), sim sensor 320 x 240, shipped sim "
        f"calibration, tactile patch at 0.507 mm (pool factor 8); {duration:.0f} s per frame "
        "rate of a scripted operator (press the malignant tumor, press the background, slide).",
        "",
        "## 1. Latency per frame rate (the real RemoteStation, in-memory link)",
        "",
        "`pipeline` = render (sim sensor; a camera frame would be ready) + reconstruct + "
        "stiffness/assembly. `cmd_to_ready` = hops `remote.arm_command -> remote.tactile_ready`: "
        "the wait for the next frame + the pipeline, what the motion-to-touch budget pays at "
        "the remote station (platform states arrive at 250 Hz, so the latest command is always "
        "recent). `frame_wait_mean_ms` = mean wait of a motion at a random time for the next "
        "frame start (E[T^2]/2E[T] over the measured frame periods); `motion_to_tactile_mean_ms`"
        " = that wait + the mean pipeline. `cpu_cores` = process CPU time / wall time (arm "
        "loop included).",
        "",
        format_table(lat_rows, cols_a),
        "",
        format_table(lat_rows, cols_b),
        "",
        "## 2. Reconstruction resolution: time against error (contact frames)",
        "",
        "Errors are area-averaged to each output grid; `rmse_vs_full_res_mm` is what pooling "
        "costs against reconstructing at full resolution.",
        "",
        format_table(resolution, ["factor", "pitch_mm", "grid", "time_ms_p50", "frames_per_s",
                                  "speedup_vs_full", "rmse_vs_truth_mm",
                                  "rmse_vs_full_res_mm"]),
        "",
        "## 3. Skips",
        "",
        format_table(skips, ["skip", "with_skip_ms", "without_skip_ms", "saving",
                             "share_of_scan"]),
        "",
        "`share_of_scan`: fraction of the 60 fps run's frames without contact / of arm samples "
        "never fitted. The stiffness row compares fitting each closed loading segment once "
        "with a naive fit of the last 200 samples on every frame (ms of fitting per second).",
        "",
        "![remote pipeline](remote_pipeline.png)",
        "",
    ]
    (args.out_dir / "remote_pipeline.md").write_text("\n".join(lines))
    plot(latencies, resolution, args.out_dir / "remote_pipeline.png")
    emit("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
