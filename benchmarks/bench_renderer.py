"""Renderer benchmark: render rate and latency per scene kind, interpolation order against
error, and the measured savings of the renderer's skips.

Run from the repository root::

    python benchmarks/bench_renderer.py            # the committed results
    python benchmarks/bench_renderer.py --quick    # a short CI-like run

Writes ``benchmarks/results/renderer.md`` and ``renderer.png`` (``--out-dir`` to change).
All figures come from this one run on this machine; nothing is hard-coded.
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from local_site.render import Renderer, RendererConfig
from local_site.scenes import (
    LayerFileData,
    LayerFileScene,
    SceneSample,
    SceneSource,
    TactileFrameScene,
    make_shape_scene,
)
from shared.protocol import TactileFrame
from shared.report import emit, format_table

log = logging.getLogger(__name__)

RESULTS = Path(__file__).resolve().parent / "results"


class GaussianBump(SceneSource):
    """A smooth reference surface: ``h = 4 exp(-r^2 / (2 sigma^2))``."""

    kind = "analytic"

    def __init__(self, sigma_mm: float = 2.5) -> None:
        super().__init__()
        self.sigma_mm = sigma_mm

    def extent_mm(self) -> tuple[float, float, float, float]:
        return (-12.0, 12.0, -12.0, 12.0)

    def _sample(self, p: NDArray[np.float64]) -> SceneSample:
        n = p.shape[0]
        r2 = p[:, 0] ** 2 + p[:, 1] ** 2
        return SceneSample(4.0 * np.exp(-r2 / (2 * self.sigma_mm ** 2)), np.ones(n),
                           np.zeros(n), np.ones(n, dtype=bool))


def grid_copy(scene: SceneSource, pitch_mm: float, order: int) -> LayerFileScene:
    """Rasterise an analytic scene at ``pitch_mm`` into a layer-file scene."""
    ext = scene.extent_mm()
    if ext is None:
        raise ValueError("scene has no extent")
    layers = scene.rasterize(ext, pitch_mm)
    return LayerFileScene(LayerFileData(layers["height_mm"], layers["stiffness_k"],
                                        layers["friction"], ext), order=order)


def sweep_positions(n: int, speed_mm_s: float = 20.0, rate_hz: float = 1000.0,
                    half_width_mm: float = 6.0) -> NDArray[np.float64]:
    """A raster sweep sampled at ``rate_hz``: x back and forth, y advancing slowly."""
    t = np.arange(n) / rate_hz
    period = 4 * half_width_mm / speed_mm_s
    phase = (t % period) / period
    x = half_width_mm * (4 * np.abs(phase - 0.5) - 1)
    y = -half_width_mm + (t * 0.5) % (2 * half_width_mm)
    return np.column_stack([x, y])


def time_renders(renderer: Renderer, scene: SceneSource,
                 positions: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per-call latency in microseconds."""
    out = np.empty(len(positions))
    for i, pos in enumerate(positions):
        t0 = time.perf_counter_ns()
        renderer.render(scene, pos)
        out[i] = (time.perf_counter_ns() - t0) / 1e3
    return out


def bench_rate(n: int) -> list[dict]:
    """Renders/s and latency p50/p99 for each scene kind (skips off: full cost)."""
    positions = sweep_positions(n)
    frame_scene = TactileFrameScene()  # the default order (DEFAULT_ORDER)
    g = np.linspace(-1, 1, 32)
    gx, gy = np.meshgrid(g, g)
    frame = TactileFrame(center_mm=(0.0, 0.0), pitch_mm=0.4,
                         layers={"height_mm": 3.0 - 2.0 * (gx ** 2 + gy ** 2),
                                 "stiffness_k": np.full((32, 32), 0.8)})
    update_us = []
    for _ in range(max(50, n // 100)):
        t0_ns = time.perf_counter_ns()
        frame_scene.update(frame)
        update_us.append((time.perf_counter_ns() - t0_ns) / 1e3)
    hemi = make_shape_scene("hemisphere", radius_mm=4.5, shore00=40.0)
    scenes: list[tuple[str, SceneSource]] = [
        ("virtual hemisphere", hemi),
        ("layer file 0.1 mm, order 0", grid_copy(hemi, 0.1, 0)),
        ("layer file 0.1 mm, order 1", grid_copy(hemi, 0.1, 1)),
        ("layer file 0.1 mm, order 3", grid_copy(hemi, 0.1, 3)),
        (f"remote stream 32x32, order {frame_scene.order}", frame_scene),
    ]
    rows = []
    for name, scene in scenes:
        renderer = Renderer(RendererConfig(skip_unchanged=False))
        time_renders(renderer, scene, positions[: min(200, n)])  # warm-up
        t0 = time.perf_counter()
        lat = time_renders(renderer, scene, positions)
        total = time.perf_counter() - t0
        rows.append({"scene": name, "renders_per_s": n / total,
                     "p50_us": float(np.percentile(lat, 50)),
                     "p99_us": float(np.percentile(lat, 99)),
                     "max_us": float(lat.max())})
    rows.append({"scene": "remote stream: update(frame) 32x32", "renders_per_s": float("nan"),
                 "p50_us": float(np.percentile(update_us, 50)),
                 "p99_us": float(np.percentile(update_us, 99)),
                 "max_us": float(np.max(update_us))})
    return rows


def bench_order(n_positions: int, pitches: list[float]) -> list[dict]:
    """Pin-height error of grid scenes (orders 0, 1, 3) against the analytic scene."""
    rng = np.random.default_rng(1)
    references: list[tuple[str, SceneSource]] = [
        ("gaussian bump (smooth)", GaussianBump()),
        ("hemisphere", make_shape_scene("hemisphere", radius_mm=4.5)),
        ("cone", make_shape_scene("cone")),
    ]
    rows = []
    for ref_name, ref in references:
        positions = rng.uniform(-7.0, 7.0, size=(n_positions, 2))
        exact = Renderer()
        truth = np.stack([exact.render(ref, p).height_mm for p in positions])
        for pitch in pitches:
            for order in (0, 1, 3):
                scene = grid_copy(ref, pitch, order)
                renderer = Renderer(RendererConfig(skip_unchanged=False))
                t0 = time.perf_counter()
                got = np.stack([renderer.render(scene, p).height_mm for p in positions])
                us = (time.perf_counter() - t0) / n_positions * 1e6
                err = got - truth
                rows.append({"reference": ref_name, "grid_pitch_mm": pitch, "order": order,
                             "rms_error_mm": float(np.sqrt(np.mean(err ** 2))),
                             "max_error_mm": float(np.abs(err).max()),
                             "us_per_render": us})
    return rows


def dwell_trajectory(n: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """1 kHz samples of an exploring hand: 0.3-1 s moves at 5-30 mm/s, 0.2-1 s dwells."""
    pos = np.zeros((n, 2))
    p = np.zeros(2)
    i = 0
    while i < n:
        move = int(rng.uniform(300, 1000))
        v = rng.uniform(5, 30) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a)])
        for _ in range(min(move, n - i)):
            p = np.clip(p + v / 1000.0, -10.0, 10.0)
            pos[i] = np.round(p / 0.0185) * 0.0185  # encoder counts (~18.5 um, assumed)
            i += 1
        dwell = int(rng.uniform(200, 1000))
        pos[i:i + dwell] = pos[i - 1]
        i += dwell
    return pos[:n]


def bench_skips(n: int) -> tuple[list[dict], list[dict]]:
    """Savings of the unchanged-window skip and the zero-friction flag."""
    rng = np.random.default_rng(2)
    scene = make_shape_scene("semi_ellipsoid", shore00=40.0, friction=0.3)
    rows = []
    for label, positions in (("stationary hand", np.zeros((n, 2))),
                             ("explore with dwells (1 kHz)", dwell_trajectory(n, rng)),
                             ("continuous sweep 20 mm/s", sweep_positions(n))):
        timings = {}
        skipped = 0
        for skip in (False, True):
            renderer = Renderer(RendererConfig(skip_unchanged=skip))
            time_renders(renderer, scene, positions[:100])
            renderer.invalidate()
            renderer.stats.skipped = 0
            t0 = time.perf_counter()
            for p in positions:
                renderer.render(scene, p)
            timings[skip] = (time.perf_counter() - t0) / n * 1e6
            if skip:
                skipped = renderer.stats.skipped
        rows.append({"trajectory": label, "skipped_pct": 100.0 * skipped / n,
                     "us_per_call_no_skip": timings[False], "us_per_call_skip": timings[True],
                     "speedup": timings[False] / timings[True]})
    friction_rows = []
    plant_cls: type[ArrayTacPlant] | None
    try:
        from local_site.arraytac_sim.plant import ArrayTacPlant
    except ImportError as err:  # the simulator is another developer's module
        log.warning("ArrayTac simulator not importable (%s): zero-friction saving not timed", err)
        plant_cls = None
    else:
        plant_cls = ArrayTacPlant
    g = np.linspace(-10.0, 10.0, 25)
    grid_positions = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    for label, friction in (("cone, friction 0", 0.0), ("cone, friction 0.3 on the shape", 0.3)):
        sc = make_shape_scene("cone", shore00=40.0, friction=friction)
        renderer = Renderer()
        cmds = [renderer.render(sc, p) for p in grid_positions]
        inactive = sum(not c.friction_active for c in cmds) / len(cmds)
        friction_rows.append({"case": f"{label}: window positions on a 25x25 grid over "
                                      "+-10 mm", "no_vibration_pct": 100.0 * inactive,
                              "sim_ms_per_1ms_period": float("nan")})
    if plant_cls is not None:
        periods = max(100, n // 20)
        for label, friction in (("simulator, flat 2.5 mm, all f = 0", 0.0),
                                ("simulator, flat 2.5 mm, all f = 0.3", 0.3)):
            plant = plant_cls()
            plant.set_targets(np.full(16, 2.5), np.full(16, 0.8), np.full(16, friction))
            plant.advance(0.05)  # settle
            t0 = time.perf_counter()
            for _ in range(periods):
                plant.advance(0.001)
            friction_rows.append({"case": label, "no_vibration_pct": float("nan"),
                                  "sim_ms_per_1ms_period":
                                  (time.perf_counter() - t0) / periods * 1e3})
    return rows, friction_rows


def plot(order_rows: list[dict], rate_rows: list[dict], path: Path) -> None:
    """Error against grid pitch per order, and latency per scene kind."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    ax = axes[0]
    styles = {0: ":", 1: "-", 3: "--"}
    colours: dict[str, str] = {}
    for row in order_rows:
        colours.setdefault(row["reference"], f"C{len(colours)}")
    for ref, colour in colours.items():
        for order, ls in styles.items():
            sel = [r for r in order_rows if r["reference"] == ref and r["order"] == order]
            ax.loglog([r["grid_pitch_mm"] for r in sel], [r["rms_error_mm"] for r in sel],
                      ls, color=colour, marker="o", ms=3, label=f"{ref}, order {order}")
    ax.set_xlabel("layer grid pitch (mm)")
    ax.set_ylabel("RMS pin-height error (mm)")
    ax.set_title("interpolation order against error")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    ax = axes[1]
    sel = [r for r in rate_rows if np.isfinite(r["renders_per_s"])]
    y = np.arange(len(sel))
    ax.barh(y - 0.2, [r["p50_us"] for r in sel], height=0.4, label="p50")
    ax.barh(y + 0.2, [r["p99_us"] for r in sel], height=0.4, label="p99")
    ax.set_yticks(y, [r["scene"] for r in sel], fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("render latency (us, log scale)")
    ax.set_title("per-render latency (skips off)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and write the results."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="short run (CI)")
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    n = 2000 if args.quick else 20000
    n_pos = 100 if args.quick else 600
    pitches = [0.25, 1.0] if args.quick else [0.1, 0.25, 0.5, 1.0, 1.7]
    t_start = time.perf_counter()
    rate_rows = bench_rate(n)
    order_rows = bench_order(n_pos, pitches)
    skip_rows, friction_rows = bench_skips(n)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    cmd = "python benchmarks/bench_renderer.py" + (" --quick" if args.quick else "")
    md = [
        "# Renderer benchmark",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores shared with other jobs, no GPU; "
        f"Python {platform.python_version()}, numpy {np.__version__}. "
        f"Run time {time.perf_counter() - t_start:.1f} s; load average at the end "
        f"{os.getloadavg()[0]:.2f} (other jobs share the cores: p99/max latencies include "
        "scheduler preemption, p50 is the renderer's own cost).",
        f"Reproduce: `{cmd}`",
        "",
        f"## Render rate and latency per scene kind ({n} renders on a 20 mm/s raster sweep, "
        "skips off so every call renders)",
        "",
        format_table(rate_rows, ["scene", "renders_per_s", "p50_us", "p99_us", "max_us"]),
        "",
        "The remote-stream row with no rate is the cost of `update(frame)` (validation and "
        "grid build) per incoming frame.",
        "",
        f"## Interpolation order against error ({n_pos} random window positions; reference: "
        "the same surface evaluated analytically at each pin)",
        "",
        format_table(order_rows, ["reference", "grid_pitch_mm", "order", "rms_error_mm",
                                  "max_error_mm", "us_per_render"]),
        "",
        "## Skip: unchanged window (same scene and version, moved <= 0.01 mm)",
        "",
        format_table(skip_rows, ["trajectory", "skipped_pct", "us_per_call_no_skip",
                                 "us_per_call_skip", "speedup"]),
        "",
        "Encoder quantisation in the dwell trajectory is an assumed 18.5 um per count.",
        "",
        "## Skip: zero friction (no vibration synthesised)",
        "",
        format_table(friction_rows, ["case", "no_vibration_pct", "sim_ms_per_1ms_period"]),
        "",
        "`no_vibration_pct`: rendered commands with `friction_active == False` (every pin "
        "f = 0, so the display synthesises no vibration). `sim_ms_per_1ms_period`: wall time "
        "of the ArrayTac simulator (`local_site.arraytac_sim.plant.ArrayTacPlant`, 10 kHz "
        "firmware, another module) to advance one 1 ms display period holding a flat command "
        "with all f = 0 against all f = 0.3; n/a when the simulator is absent.",
        "",
        "![renderer](renderer.png)",
        "",
    ]
    (args.out_dir / "renderer.md").write_text("\n".join(md))
    plot(order_rows, rate_rows, args.out_dir / "renderer.png")
    emit("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
