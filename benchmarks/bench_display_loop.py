"""Local-station drive loop: ArrayTac command rate and period jitter, platform read rate.

Three measurements from one run, all through the real byte protocols and the ``sim`` backends:

1. Platform: ``read_state()`` in a tight loop on ``open_platform("sim")`` (1 kHz simulated
   board on a pty, scripted raster operator). Reported: read rate, sample period p50/p99, and
   the position error against the motion source at each sample's board time (encoder
   quantisation + codec: must stay within one count).
2. Display command loop at a 1 kHz target on ``open_display("sim")`` (emulated firmware +
   plant on a virtual CAN FD channel) and on ``sim-serial`` (pty, COBS). The loop reads the
   platform, renders a hemisphere (radius 20 mm, 4 mm high, at (35, 35) mm) under the 4 x 4
   pins at the platform position, and sends it. Reported: loop rate, period p50/p99, jitter
   |period - 1 ms| p50/p99, send_command cost p50/p99 for sent vs skipped calls, the pin
   tracking error (feedback vs command: plant lag + quantisation) and the codec's
   quantisation error.
3. Skip saving: unchanged pins (presses, flat regions) are not re-sent: the fraction of
   frames skipped, the bus bytes saved, and the CPU time per call saved.

Run:   python benchmarks/bench_display_loop.py          (60 s CAN, 15 s serial, 10 s platform)
       python benchmarks/bench_display_loop.py --quick    (5 s, 2 s, 2 s)
Writes benchmarks/results/display_loop.md and benchmarks/results/display_loop.png.
"""

from __future__ import annotations

import argparse
import os
import platform as host_platform
import sys
import time
from pathlib import Path
from typing import Any, TypedDict

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from local_site.devices import open_display, open_platform  # noqa: E402
from local_site.platform.motion import RasterSweep  # noqa: E402
from shared.report import emit, format_table  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
PERIOD_S = 0.001
RADIUS_MM = 20.0


class _SweepOverrides(TypedDict):
    """Fields of :class:`RasterSweepParams` that :data:`SWEEP` overrides."""

    origin_mm: tuple[float, float]
    size_mm: tuple[float, float]
    line_spacing_mm: float


#: the scripted operator sweeps over the hemisphere from its first line on, with presses
SWEEP: _SweepOverrides = {"origin_mm": (20.0, 25.0), "size_mm": (30.0, 20.0),
                          "line_spacing_mm": 4.0}
PIN_OFFSETS_MM = np.stack(np.meshgrid((np.arange(4) - 1.5) * 1.7, (np.arange(4) - 1.5) * 1.7),
                          axis=-1).reshape(16, 2)  # (x, y) per pin, row-major


def _hemisphere_mm(xy_mm: tuple[float, float]) -> np.ndarray:
    pins = np.asarray(xy_mm) + PIN_OFFSETS_MM
    r2 = np.sum((pins - 35.0) ** 2, axis=1)
    return np.where(r2 < RADIUS_MM**2, 4.0 * np.sqrt(np.clip(1 - r2 / RADIUS_MM**2, 0, 1)), 0.0)


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if values.size else float("nan")


def measure_platform(duration_s: float) -> dict[str, Any]:
    """Tight read_state loop on the simulated platform."""
    motion = RasterSweep()
    with open_platform("sim", motion=motion) as plat:
        plat.read_state(0.5)
        samples = []
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < duration_s:
            samples.append(plat.read_state(0.5))
        elapsed = time.perf_counter() - t0
        stats = plat.stats()
    board_t = np.array([s.board_t_us for s in samples], dtype=float)
    pos = np.array([s.position_mm for s in samples])
    expected = motion.sample(board_t * 1e-6)
    err_um = np.max(np.abs(pos - expected), axis=1) * 1e3
    periods_ms = np.diff(board_t) / 1e3
    return {"reads": len(samples), "rate_hz": len(samples) / elapsed,
            "period_p50_ms": _pct(periods_ms, 50), "period_p99_ms": _pct(periods_ms, 99),
            "err_max_um": float(err_um.max()), "err_p99_um": _pct(err_um, 99),
            "crc_errors": stats.crc_errors, "garbage_bytes": stats.garbage_bytes,
            "samples_missed": stats.samples_missed, "periods_ms": periods_ms}


def measure_display(spec: str, duration_s: float) -> dict[str, Any]:
    """1 kHz command loop: platform -> hemisphere -> 16 pins -> sim backend."""
    with open_platform("sim", motion=RasterSweep(**SWEEP)) as plat, \
            open_display(spec, keepalive_interval_s=0.02, watchdog_ms=100) as disp:
        starts: list[float] = []
        costs_sent: list[float] = []
        costs_skipped: list[float] = []
        track_err: list[float] = []
        quant_err: list[float] = []
        next_t = time.perf_counter()
        t_end = next_t + duration_s
        while True:
            now = time.perf_counter()
            if now >= t_end:
                break
            starts.append(now)
            sample = plat.latest()
            xy = sample.position_mm[:2] if sample is not None else (0.0, 0.0)
            height = _hemisphere_mm(xy)
            c0 = time.perf_counter()
            applied = disp.send_command(height, 1.0, 0.0)
            cost = time.perf_counter() - c0
            (costs_sent if applied.sent else costs_skipped).append(cost)
            quant_err.append(float(np.max(np.abs(applied.height_mm - height))))
            fb = disp.latest_feedback()
            if fb is not None:
                track_err.append(float(np.sqrt(np.mean((fb.position_mm - applied.height_mm)
                                                       ** 2))))
            next_t += PERIOD_S
            if next_t < time.perf_counter() - PERIOD_S:  # late by a period: re-anchor, no burst
                next_t = time.perf_counter()
            remaining = next_t - time.perf_counter()
            if remaining > 0:  # absolute schedule: sleep overshoot does not accumulate
                time.sleep(remaining)  # never spin: a spinning thread starves the GIL
        stats = disp.stats()
        last_fb = disp.latest_feedback()
        emulator = getattr(disp, "emulator", None)
        overruns = emulator.firmware.overruns if emulator is not None else 0
    periods_ms = np.diff(starts) * 1e3
    jitter_ms = np.abs(periods_ms - PERIOD_S * 1e3)
    elapsed = starts[-1] - starts[0]
    sent_ms, skip_ms = np.array(costs_sent) * 1e3, np.array(costs_skipped) * 1e3
    frame_bytes = 64
    return {"backend": spec, "iterations": len(starts), "rate_hz": (len(starts) - 1) / elapsed,
            "period_p50_ms": _pct(periods_ms, 50), "period_p99_ms": _pct(periods_ms, 99),
            "jitter_p50_ms": _pct(jitter_ms, 50), "jitter_p99_ms": _pct(jitter_ms, 99),
            "frames_sent": stats.frames_sent, "skipped": stats.skipped_unchanged,
            "keepalives": stats.keepalives,
            "skipped_pct": 100.0 * stats.skipped_unchanged / max(1, stats.commands),
            "bytes_saved_per_s": stats.skipped_unchanged * frame_bytes / elapsed,
            "cost_sent_p50_ms": _pct(sent_ms, 50), "cost_sent_p99_ms": _pct(sent_ms, 99),
            "cost_skip_p50_ms": _pct(skip_ms, 50), "cost_skip_p99_ms": _pct(skip_ms, 99),
            "track_rms_p50_um": _pct(np.array(track_err) * 1e3, 50),
            "track_rms_p99_um": _pct(np.array(track_err) * 1e3, 99),
            "quant_err_max_um": max(quant_err) * 1e3, "feedback_frames": stats.feedback_frames,
            "emulator_overruns": overruns,
            "watchdog_trips": last_fb.watchdog_trips if last_fb is not None else -1,
            "periods_ms": periods_ms}


def _plot(path: Path, plat: dict[str, Any], loops: list[dict[str, Any]]) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    bins = np.linspace(0.0, 3.0, 121)
    for loop in loops:
        axes[0].hist(np.clip(loop["periods_ms"], 0, 3), bins=bins, histtype="step",
                     label=f"display loop, {loop['backend']}")
    axes[0].hist(np.clip(plat["periods_ms"], 0, 3), bins=bins, histtype="step",
                 label="platform samples read")
    axes[0].axvline(2.0, color="grey", ls=":", label="500 Hz (paper's refresh)")
    axes[0].set_yscale("log")
    axes[0].set_xlabel("period (ms)")
    axes[0].set_ylabel("count")
    axes[0].legend(fontsize=8)
    axes[0].set_title("loop and read periods (1 ms target)")
    names = [str(loop["backend"]) for loop in loops]
    x = np.arange(len(names))
    axes[1].bar(x - 0.2, [loop["cost_sent_p50_ms"] * 1e3 for loop in loops], 0.4,
                label="sent (p50)")
    axes[1].bar(x + 0.2, [loop["cost_skip_p50_ms"] * 1e3 for loop in loops], 0.4,
                label="skipped, unchanged (p50)")
    axes[1].set_xticks(x, names)
    axes[1].set_ylabel("send_command cost (us)")
    axes[1].set_title("skipping unchanged pins")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and write the results."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="5 s CI-like run")
    parser.add_argument("--duration", type=float, default=None,
                        help="seconds of the CAN display loop (default 60, quick 5)")
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args(argv)
    can_s = args.duration or (5.0 if args.quick else 60.0)
    serial_s = 2.0 if args.quick else can_s / 4
    plat_s = 2.0 if args.quick else 10.0

    plat = measure_platform(plat_s)
    loops = [measure_display("sim", can_s), measure_display("sim-serial", serial_s)]

    plat_row = {k: v for k, v in plat.items() if k != "periods_ms"}
    loop_cols = ["backend", "iterations", "rate_hz", "period_p50_ms", "period_p99_ms",
                 "jitter_p50_ms", "jitter_p99_ms", "emulator_overruns", "watchdog_trips"]
    skip_cols = ["backend", "frames_sent", "skipped", "keepalives", "skipped_pct",
                 "bytes_saved_per_s", "cost_sent_p50_ms", "cost_sent_p99_ms",
                 "cost_skip_p50_ms", "cost_skip_p99_ms"]
    err_cols = ["backend", "track_rms_p50_um", "track_rms_p99_um", "quant_err_max_um",
                "feedback_frames"]
    rows = [{k: v for k, v in loop.items() if k != "periods_ms"} for loop in loops]
    command = "python benchmarks/bench_display_loop.py" + (" --quick" if args.quick else "") \
        + (f" --duration {args.duration:g}" if args.duration else "")
    sent_vs_skip = [loop["cost_sent_p50_ms"] / loop["cost_skip_p50_ms"] for loop in loops]
    text = "\n".join([
        "# Local-station drive loop: ArrayTac command rate and jitter, platform read rate",
        "",
        f"Machine: {host_platform.machine()}, {os.cpu_count()} cores shared with other jobs, "
        f"no GPU; Python {host_platform.python_version()}; load average at the end "
        f"{os.getloadavg()[0]:.1f} (other developers' jobs share the cores). "
        f"Command: `{command}`.",
        f"Durations: display loop {can_s:g} s on `sim` (virtual CAN FD), {serial_s:g} s on "
        f"`sim-serial` (pty, COBS); platform {plat_s:g} s. Target period 1 ms (1 kHz); the paper "
        "needs > 500 Hz array refresh.",
        "",
        "## Platform read (sim encoder board, 1 kHz, pty)",
        "",
        format_table([plat_row], ["reads", "rate_hz", "period_p50_ms", "period_p99_ms",
                                  "err_max_um", "err_p99_um", "crc_errors", "garbage_bytes",
                                  "samples_missed"]),
        "",
        "err: |position read - motion source at the sample's board time|, max over axes "
        "(one encoder count is 9.2 um on X/Y, 9.8 um on Z; half a count is the ideal).",
        "",
        "## Display command loop (rate and period jitter)",
        "",
        format_table(rows, loop_cols),
        "",
        "jitter = |period - 1 ms|. emulator_overruns: emulator ticks where the plant could "
        "not keep real time (it then falls behind instead of bursting); watchdog_trips: "
        "link-loss safe states the emulated board entered (0 = keepalives always in time). "
        "The loop re-anchors its schedule when it is a full period late, so it never bursts.",
        "",
        "## Skipping unchanged pins (same run)",
        "",
        format_table(rows, skip_cols),
        "",
        "A sent call costs " + ", ".join(f"{r:.1f}x" for r in sent_vs_skip)
        + " a skipped one (p50, per backend above); each skipped frame also saves 64 "
        "payload bytes on the bus (68 on serial).",
        "",
        "## Error (same run)",
        "",
        format_table(rows, err_cols),
        "",
        "track_rms: RMS over the 16 pins of (latest feedback position - applied command), "
        "sampled every loop iteration; it is dominated by the plant's dynamic lag while the "
        "scene changes (rise time 13 ms), not by the link. quant_err_max: largest "
        "|applied - requested| height, the codec's 1.25 um quantisation (<= 0.625 um).",
        "",
    ])
    emit(text)
    if not args.no_write:
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / "display_loop.md").write_text(text)
        _plot(RESULTS / "display_loop.png", plat, loops)
    return 0


if __name__ == "__main__":
    sys.exit(main())
