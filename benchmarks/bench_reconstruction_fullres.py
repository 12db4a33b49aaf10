"""Full-resolution reconstruction (320 x 240, no pooling): before/after per stage, with error.

A/B in one process: the frozen pre-change pipeline (``lab/reconstruction_reference.py``,
"before") and the product's ``Reconstructor.height_map`` ("after") are called alternately on
the same frame, per stage and end to end, so machine load hits both alike. Data: the real
GelSight Mini ball presses (default poly5 calibration fitted on the 39 train presses
(the label check drops press_50, which carries press_49's circle),
measured on the 11 test presses, DST solver). Times: wall clock and the CPU time
(``time.process_time``: what the process spends on all its threads, i.e. on one core when
everything is single-threaded; on a loaded machine wall time also counts the waits for a
core). Error: the same metrics as ``bench_reconstruction.py`` for both
pipelines, and the largest height difference between them. Writes
benchmarks/results/reconstruction_fullres.md.

Run (single-threaded BLAS, as the one-core target demands):

    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 python benchmarks/bench_reconstruction_fullres.py
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

import lab.reconstruction_reference as ref  # noqa: E402
from benchmarks.gelsight_labels import DEFAULT_DATA, split_labels, train_labels  # noqa: E402
from lab.reconstruction_metrics import evaluate_press  # noqa: E402
from remote_site.reconstruction.calibration import fit_calibration  # noqa: E402
from remote_site.reconstruction.features import relative_change  # noqa: E402
from remote_site.reconstruction.frames import load_rgb, validate_frame  # noqa: E402
from remote_site.reconstruction.grid_predict import BakedPolyPredictor  # noqa: E402
from remote_site.reconstruction.kernels import evidence_kernel  # noqa: E402
from remote_site.reconstruction.reconstructor import Reconstructor  # noqa: E402
from shared.report import emit, format_table  # noqa: E402

BALL_RADIUS_MM = 4.735
MM_PER_PX = 0.0634
TARGET_FPS = 400.0
#: the margin aimed for so that the target holds on a loaded machine
AIM_FPS = 450.0

Fn = Callable[[int], object]


_KEYS = ("b_wall", "b_cpu", "b_faults", "a_wall", "a_cpu", "a_faults")


def _timed(fn: Fn, i: int, tag: str, out: dict[str, list[float]]) -> None:
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    c0, w0 = time.process_time(), time.perf_counter()
    fn(i)
    w1, c1 = time.perf_counter(), time.process_time()
    out[f"{tag}_faults"].append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
    out[f"{tag}_wall"].append((w1 - w0) * 1e3)
    out[f"{tag}_cpu"].append((c1 - c0) * 1e3)


def _paired(before: Fn, after: Fn, n_inputs: int, repeats: int) -> dict[str, np.ndarray]:
    """Wall and CPU ms (and minor page faults) of ``before(i)`` and ``after(i)``, called
    alternately (the order swapped every call)."""
    for i in range(min(2, n_inputs)):  # compile / warm caches
        before(i)
        after(i)
    out: dict[str, list[float]] = {k: [] for k in _KEYS}
    for rep in range(repeats):
        for i in range(n_inputs):
            order = ((before, "b"), (after, "a")) if (rep + i) % 2 == 0 else (
                (after, "a"), (before, "b"))
            for fn, tag in order:
                _timed(fn, i, tag, out)
    return {k: np.array(v) for k, v in out.items()}


def _blocks(before: Fn, after: Fn, n_inputs: int, rounds: int,
            block: int) -> dict[str, np.ndarray]:
    """As :func:`_paired`, but each pipeline runs ``block`` passes over the inputs in a row,
    the blocks alternating for ``rounds`` rounds (the memory allocator then settles on one
    pipeline's pattern, as in a station process that only reconstructs)."""
    out: dict[str, list[float]] = {k: [] for k in _KEYS}
    for _ in range(rounds):
        for fn, tag in ((before, "b"), (after, "a")):
            for k in range(block):
                for i in range(n_inputs):
                    if k == 0 and i == 0:
                        fn(i)  # settle after the switch; not counted
                        continue
                    _timed(fn, i, tag, out)
    return {k: np.array(v) for k, v in out.items()}


def _stage_row(name: str, t: dict[str, np.ndarray]) -> dict[str, Any]:
    b_cpu, a_cpu = float(np.median(t["b_cpu"])), float(np.median(t["a_cpu"]))
    return {"stage": name,
            "before_cpu_ms_p50": b_cpu, "after_cpu_ms_p50": a_cpu,
            "after/before": a_cpu / b_cpu if b_cpu > 0 else float("nan"),
            "before_wall_ms_p50": float(np.median(t["b_wall"])),
            "after_wall_ms_p50": float(np.median(t["a_wall"])),
            "after_cpu_ms_p90": float(np.percentile(t["a_cpu"], 90)),
            "before_faults": float(np.mean(t["b_faults"])),
            "after_faults": float(np.mean(t["a_faults"]))}


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def _commit() -> str:
    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _metrics(maps: list[np.ndarray], labels: list) -> dict[str, float]:
    ms = [evaluate_press(h, MM_PER_PX, lb, MM_PER_PX, BALL_RADIUS_MM) for h, lb in
          zip(maps, labels, strict=True)]
    radius = np.array([m.radius_error(BALL_RADIUS_MM) for m in ms])
    return {"shape_rmse_mm": float(np.mean([m.shape_rmse_mm for m in ms])),
            "flat_p99_mm": float(np.mean([m.flat_p99_mm for m in ms])),
            "radius_err_mean_abs": float(np.mean(np.abs(radius))),
            "abs_rmse_mm": float(np.mean([m.abs_rmse_mm for m in ms]))}


def lean_child(args: argparse.Namespace) -> int:
    """One pipeline alone in a fresh process (nothing else allocated): print JSON figures."""
    import json

    data = Path(args.data) if args.data else DEFAULT_DATA
    rec = Reconstructor.from_file(args.lean_calibration)
    frames = [load_rgb(data / lb.image) for lb in split_labels(data, "test")]
    if args.lean == "before":
        def fn(i: int) -> object:
            return ref.reference_height_map(rec, frames[i])
    else:
        def fn(i: int) -> object:
            return rec.height_map(frames[i])
    for i in range(len(frames)):
        fn(i)
    out: dict[str, list[float]] = {k: [] for k in _KEYS}
    for _ in range(args.repeats):
        for i in range(len(frames)):
            _timed(fn, i, "a", out)
    print(json.dumps({"cpu_ms_p50": float(np.median(out["a_cpu"])),
                      "wall_ms_p50": float(np.median(out["a_wall"])),
                      "faults": float(np.mean(out["a_faults"]))}))
    return 0


def _lean(calib_path: Path, args: argparse.Namespace, rounds: int = 3) -> list[dict[str, Any]]:
    """Each pipeline alone in fresh processes, alternating before/after ``rounds`` times."""
    import json

    results: dict[str, list[dict[str, float]]] = {"before": [], "after": []}
    for _ in range(rounds):
        for which in ("before", "after"):
            argv = [sys.executable, str(Path(__file__).resolve()), "--lean", which,
                    "--lean-calibration", str(calib_path), "--repeats",
                    str(max(5, args.repeats // 3))]
            argv += ["--data", args.data] if args.data else []
            done = subprocess.run(argv, capture_output=True, text=True, check=True)
            results[which].append(json.loads(done.stdout.strip().splitlines()[-1]))
    rows = []
    for which, runs in results.items():
        rows.append({"pipeline": which, "process": "alone, fresh",
                     "cpu_ms_p50 (median of runs)": float(np.median(
                         [r["cpu_ms_p50"] for r in runs])),
                     "runs cpu_ms_p50": ", ".join(f"{r['cpu_ms_p50']:.2f}" for r in runs),
                     "page_faults_per_frame": float(np.median([r["faults"] for r in runs]))})
    return rows


def _opencv_version(python: str) -> str:
    """The OpenCV version another interpreter imports."""
    done = subprocess.run([python, "-c", "import cv2; print(cv2.__version__)"],
                          capture_output=True, text=True, check=True)
    return done.stdout.strip()


def _python(args: argparse.Namespace, which: str) -> str:
    """The interpreter of one side: ``--baseline-python`` for the baseline (the same tree
    under other library versions, e.g. a virtual environment with OpenCV 4), else this one."""
    return str(args.baseline_python) if which == "previous" and args.baseline_python \
        else sys.executable


def _tree_stages(calib_path: Path, data: Path, args: argparse.Namespace,
                 rounds: int = 3) -> tuple[list[dict[str, Any]], dict[str, float]]:
    """Per-stage CPU ms of the baseline tree and of this tree, each in fresh processes
    (``reconstruction_stage_child.py``), alternating ``rounds`` times; medians of runs."""
    import json

    child = Path(__file__).resolve().parent / "reconstruction_stage_child.py"
    runs: dict[str, list[dict[str, float]]] = {"previous": [], "this": []}
    for _ in range(rounds):
        for which, tree in (("previous", Path(args.baseline_tree)), ("this", ROOT)):
            argv = [_python(args, which), str(child), "--tree", str(tree), "--calibration",
                    str(calib_path), "--data", str(data), "--repeats",
                    str(max(5, args.repeats // 3))]
            done = subprocess.run(argv, capture_output=True, text=True, check=True)
            runs[which].append(json.loads(done.stdout.strip().splitlines()[-1]))
    starts: dict[str, list[dict[str, float]]] = {"previous": [], "this": []}
    for _ in range(rounds):  # start-up, numba cache warm (the stage runs above filled it)
        for which, tree in (("previous", Path(args.baseline_tree)), ("this", ROOT)):
            argv = [_python(args, which), str(child), "--startup", "--tree", str(tree),
                    "--calibration", str(calib_path), "--data", str(data)]
            done = subprocess.run(argv, capture_output=True, text=True, check=True)
            starts[which].append(json.loads(done.stdout.strip().splitlines()[-1]))
    rows = []
    for table, unit in ((runs, "cpu ms p50"), (starts, "wall s")):
        for stage in table["this"][0]:
            prev = float(np.median([r[stage] for r in table["previous"]]))
            this = float(np.median([r[stage] for r in table["this"]]))
            rows.append({"stage": stage.replace("_s", "").replace("_", " "), "unit": unit,
                         "previous": prev, "this tree": this, "this/previous": this / prev,
                         "previous runs": ", ".join(f"{r[stage]:.3g}" for r in table["previous"]),
                         "this runs": ", ".join(f"{r[stage]:.3g}" for r in table["this"])})
    whole = "whole height_map"
    fps = {which: 1e3 / float(np.median([r[whole] for r in runs[which]]))
           for which in ("previous", "this")}
    return rows, fps


def _tree_section(args: argparse.Namespace, rows: list[dict[str, Any]],
                  fps: dict[str, float]) -> list[str]:
    verdict = "meets" if fps["this"] >= TARGET_FPS else "does NOT meet"
    return [
        f"## This change: previous tree ({args.baseline_label}) against this tree, per stage",
        "",
        "Each tree's own `Reconstructor` in fresh processes (`benchmarks/"
        "reconstruction_stage_child.py --tree`), the two alternating, 3 processes each; "
        "every stage many times in a row on the same inputs (warm caches), then whole "
        "`height_map` calls in a row; CPU ms p50 per process, the median of the processes "
        "(each process's figure in the last columns). The previous tree is an unpacked "
        "commit (`mkdir DIR && git archive <commit> | tar -x -C DIR`). Start-up "
        "(`--startup`, wall seconds, numba's cache already filled): imports, building the "
        "reconstructor, the first frame (kernels loaded from the cache, the per-pixel table "
        "baked) and the second.",
        "",
        format_table(rows),
        "",
        f"Whole frame, by CPU time on one core: {fps['previous']:.0f} frames/s for the previous "
        f"tree, **{fps['this']:.0f} frames/s for this tree** "
        f"({fps['this'] / fps['previous']:.2f}x), which {verdict} the {TARGET_FPS:.0f} "
        f"frames/s target (aim: {AIM_FPS:.0f}, to hold on a noisy machine).",
        "",
    ]


def main(args: argparse.Namespace) -> int:
    """Run the A/B benchmark and write the results file."""
    if args.lean:
        return lean_child(args)
    data = Path(args.data) if args.data else DEFAULT_DATA
    out_dir = Path(args.out_dir) if args.out_dir else ROOT / "benchmarks" / "results"
    out_dir.mkdir(parents=True, exist_ok=True)
    load_start, t_start = _load(), time.perf_counter()
    started = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    background = load_rgb(data / "background.png")
    train, test = train_labels(data), split_labels(data, "test")
    calib = fit_calibration(background, [(load_rgb(data / lb.image), lb) for lb in train],
                            2 * BALL_RADIUS_MM, MM_PER_PX)
    rec = Reconstructor(calib)
    frames = [load_rgb(data / lb.image) for lb in test]
    n = len(frames)
    import tempfile

    tree_rows: list[dict[str, Any]] = []
    tree_fps: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        calib.save(Path(tmp) / "calib.npz")
        lean_rows = _lean(Path(tmp) / "calib.npz", args)
        if args.baseline_tree:
            tree_rows, tree_fps = _tree_stages(Path(tmp) / "calib.npz", data, args)

    # --- error: both pipelines on the test presses, and how far apart they are
    after_maps = [rec.height_map(f) for f in frames]
    before_maps = [ref.reference_height_map(rec, f) for f in frames]
    max_diff = max(float(np.abs(a.height_mm - b.height_mm).max())
                   for a, b in zip(after_maps, before_maps, strict=True))
    mask_diff = sum(int(np.count_nonzero(a.mask != b.mask))
                    for a, b in zip(after_maps, before_maps, strict=True))
    err_before = _metrics([m.height_mm for m in before_maps], test)
    err_after = _metrics([m.height_mm for m in after_maps], test)

    # --- per-stage inputs (each stage gets the same input in both pipelines)
    bg, inv_bg = rec._background_for(None)
    valid = [validate_frame(f, rec.shape_hw) for f in frames]
    change = [relative_change(v, bg, calib.blur_sigma_px, inv_background_pct=inv_bg)
              for v in valid]
    noise = max(calib.noise_pct, 1e-3)
    ev_thr = np.float32(rec.settings.contact_evidence_sigmas * noise)
    dz_thr = np.float32(rec.settings.dead_zone_sigmas * noise)
    active = [evidence_kernel(c, ev_thr, dz_thr)[1] for c in change]
    slopes = [rec.slopes(f)[:2] for f in frames]
    raw = [ref.reference_integrate(gx, gy, MM_PER_PX) for gx, gy in slopes]
    predictor = rec._grid_predictor(1, rec.shape_hw)
    if not isinstance(predictor, BakedPolyPredictor):
        raise SystemExit("the default calibration should bake its polynomial per pixel")
    gx_buf = np.zeros(rec.shape_hw, np.float32)
    gy_buf = np.zeros(rec.shape_hw, np.float32)
    s = rec.settings

    def ref_evidence(i: int) -> object:
        m = ref.reference_abs_max(change[i])
        return int(np.count_nonzero(m > ev_thr)), m > dz_thr

    def ref_zero(i: int) -> object:
        h = ref.reference_zero_level(raw[i], MM_PER_PX, s.zero_level, s.contact_threshold_mm,
                                     s.zero_exclusion_mm)
        return h, h > s.contact_threshold_mm, np.isfinite(h).all()

    stages: list[tuple[str, Fn, Fn]] = [
        ("validate frame (the product's in both)",
         lambda i: validate_frame(frames[i], rec.shape_hw),
         lambda i: validate_frame(frames[i], rec.shape_hw)),
        ("colour change: gain + change + blur",
         lambda i: ref.reference_relative_change(valid[i], bg, calib.blur_sigma_px, inv_bg),
         lambda i: relative_change(valid[i], bg, calib.blur_sigma_px,
                                   inv_background_pct=inv_bg)),
        ("  of which: brightness gain", lambda i: ref.reference_brightness_gain(valid[i], bg),
         lambda i: __import__("remote_site.reconstruction.features", fromlist=["x"])
         .brightness_gain(valid[i], bg)),
        ("evidence count + active mask", ref_evidence,
         lambda i: evidence_kernel(change[i], ev_thr, dz_thr)),
        ("model on active pixels",
         lambda i: ref._predict_active(change[i], active[i], predictor.inv_scale,
                                       predictor.exponents, predictor.coeffs,
                                       predictor.max_slope, gx_buf, gy_buf),
         lambda i: predictor.predict_into(change[i], active[i], gx_buf, gy_buf)),
        ("Poisson (DST)", lambda i: ref.reference_integrate(*slopes[i], MM_PER_PX),
         lambda i: rec._solver.integrate(*slopes[i], MM_PER_PX)),
        ("zero level + mask + finite check", ref_zero,
         lambda i: rec._zero_level_and_mask(raw[i], MM_PER_PX)),
    ]
    rows = [_stage_row(name, _paired(b, a, n, args.repeats)) for name, b, a in stages]
    whole = _paired(lambda i: ref.reference_height_map(rec, frames[i]),
                    lambda i: rec.height_map(frames[i]), n, args.repeats)
    rows.append(_stage_row("whole height_map (alternating calls)", whole))
    blocks = _blocks(lambda i: ref.reference_height_map(rec, frames[i]),
                     lambda i: rec.height_map(frames[i]), n, 4, max(1, args.repeats // 4))
    rows.append(_stage_row("whole height_map (blocks)", blocks))
    load_end, elapsed = _load(), time.perf_counter() - t_start

    summary: list[dict[str, Any]] = []
    for runs, how in ((blocks, "blocks"), (whole, "alternating")):
        for tag, label, err in (("b", "before (reference)", err_before),
                                ("a", "after (this tree)", err_after)):
            cpu50 = float(np.median(runs[f"{tag}_cpu"]))
            summary.append({"pipeline": label, "timing": how, "cpu_ms_p50": cpu50,
                            "cpu_ms_p90": float(np.percentile(runs[f"{tag}_cpu"], 90)),
                            "frames_per_s_cpu": 1e3 / cpu50,
                            "wall_ms_p50": float(np.median(runs[f"{tag}_wall"])),
                            "page_faults_per_frame": float(np.mean(runs[f"{tag}_faults"])),
                            **err})
    speedup = float(np.median(blocks["b_cpu"]) / np.median(blocks["a_cpu"]))
    speedup_alt = float(np.median(whole["b_cpu"]) / np.median(whole["a_cpu"]))
    fps_after = float(summary[1]["frames_per_s_cpu"])
    verdict = ("meets" if fps_after >= TARGET_FPS else "does NOT meet")
    cmd = ("OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 python "
           "benchmarks/bench_reconstruction_fullres.py" +
           (f" --repeats {args.repeats}" if args.repeats != 60 else "") +
           (f" --baseline-tree DIR --baseline-label '{args.baseline_label}'"
            if args.baseline_tree else "") +
           (" --baseline-python PYTHON" if args.baseline_python else ""))
    md = [
        "# Reconstruction at full resolution (320 x 240): before / after, per stage, with error",
        "",
        f"Run {started}, commit {_commit()}, {platform.machine()}, nproc {os.cpu_count()}, "
        f"Python {platform.python_version()}, OpenCV {cv2.__version__}"
        + (f" (the baseline's interpreter: OpenCV {_opencv_version(args.baseline_python)})"
           if args.baseline_python else "")
        + f", NumPy {np.__version__}, "
        "OPENBLAS_NUM_THREADS="
        f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}. **Machine load average at start "
        f"{load_start}, at end {load_end}** (other jobs on the machine inflate every figure "
        "against a quiet machine, CPU time less than wall time; compare the ratio). "
        f"Run time {elapsed:.0f} s.",
        f"Reproduce: `{cmd}`.",
        "",
        "Before = the pre-change pipeline, frozen in `lab/reconstruction_reference.py`; after = "
        "`Reconstructor.height_map` of this tree. Per stage, both are called alternately on "
        f"the same frame (order swapped every call), {args.repeats} passes over the {n} real "
        "GelSight Mini test presses (default poly5 calibration fitted on the 39 train presses "
        "(press_50 dropped by the label check), DST "
        "solver, no `out_pitch_mm` pooling). `cpu` = the process's CPU time (all threads), "
        "`wall` = elapsed time; p50/p90 over all calls; page faults = minor faults per call "
        "(fresh memory touched). Timing `blocks`: each pipeline runs many frames in a row "
        "(blocks alternate; like a process that only reconstructs); `alternating`: the two "
        "alternate call by call, so each one's allocations may disturb the other's. Error "
        "metrics as in `reconstruction.md` (mean over the test presses).",
        "",
        "## Run time against error (whole frame)",
        "",
        format_table(summary),
        "",
        f"Speed-up (CPU p50): {speedup:.2f}x in blocks, {speedup_alt:.2f}x alternating call "
        f"by call. After, in blocks: {fps_after:.0f} frames/s on one core by CPU time under "
        f"this load, which {verdict} the {TARGET_FPS:.0f} frames/s target. "
        f"Largest height difference after - before over the test presses: {max_diff:.2e} mm; "
        f"contact-mask pixels that differ: {mask_diff}.",
        "",
        *(_tree_section(args, tree_rows, tree_fps) if tree_rows else []),
        "## Each pipeline alone in a fresh process",
        "",
        "A process that has allocated little else: fresh `python` processes running only one "
        "pipeline over the test presses, before/after alternating, 3 processes each (the "
        "page faults show whether per-frame temporaries come back as fresh pages).",
        "",
        format_table(lean_rows),
        "",
        "## Per stage (each stage on the same input in both pipelines)",
        "",
        format_table(rows),
        "",
    ]
    path = out_dir / "reconstruction_fullres.md"
    path.write_text("\n".join(md) + "\n")
    emit(format_table(summary))
    emit(format_table(rows))
    if tree_rows:
        emit(format_table(tree_rows))
    emit(f"wrote {path} ({elapsed:.0f} s)")
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=60,
                        help="passes over the test presses per stage (default 60)")
    parser.add_argument("--data", default=None,
                        help="gsmini_ball_9.47mm directory (default: the team kit's copy)")
    parser.add_argument("--out-dir", default=None,
                        help="where reconstruction_fullres.md goes (default benchmarks/results)")
    parser.add_argument("--baseline-tree", default=None,
                        help="an earlier checkout (e.g. `git archive main | tar -x -C DIR`) "
                             "to compare with this tree stage by stage in fresh processes")
    parser.add_argument("--baseline-python", default=None,
                        help="the interpreter that runs the baseline tree's processes "
                             "(default: this one); with --baseline-tree . it compares library "
                             "versions, e.g. a virtual environment with OpenCV 4")
    parser.add_argument("--baseline-label", default="baseline",
                        help="how the results name the baseline tree (e.g. its commit)")
    parser.add_argument("--lean", choices=("before", "after"), default=None,
                        help=argparse.SUPPRESS)  # internal: one pipeline in a fresh process
    parser.add_argument("--lean-calibration", default=None, help=argparse.SUPPRESS)
    sys.exit(main(parser.parse_args()))
