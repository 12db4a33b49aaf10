"""One fresh process: per-stage CPU times of ``Reconstructor.height_map`` of a given tree.

Run by ``bench_reconstruction_fullres.py --baseline-tree DIR`` to compare this tree's
pipeline with an earlier one (e.g. main, unpacked with ``git archive``) stage by stage: the
parent starts this script alternately with ``--tree DIR`` and ``--tree`` this checkout, so
machine load hits both alike. The tree given comes first on ``sys.path``: every
``remote_site`` import below is that tree's code. The stages are called through functions
both trees have (``validate_frame``, ``relative_change``, ``evidence_kernel``, the grid
predictor's ``predict_into``, the solver's ``integrate``, ``_zero_level_and_mask``), on the
same inputs, each many times in a row (warm caches), then the whole ``height_map`` in a
row (a process that only reconstructs). Prints one JSON line: median CPU ms per stage.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path


def startup(args: argparse.Namespace, t_start: float) -> int:
    """Wall seconds of the start-up steps of the tree's reconstruction: one JSON line."""
    from benchmarks.gelsight_labels import split_labels
    from remote_site.reconstruction.frames import load_rgb
    from remote_site.reconstruction.reconstructor import Reconstructor

    t_import = time.perf_counter()
    rec = Reconstructor.from_file(args.calibration)
    t_built = time.perf_counter()
    frame = load_rgb(Path(args.data) / split_labels(Path(args.data), "test")[0].image)
    t0 = time.perf_counter()
    rec.height_map(frame)
    t1 = time.perf_counter()
    rec.height_map(frame)
    t2 = time.perf_counter()
    print(json.dumps({"import_s": t_import - t_start, "construct_s": t_built - t_import,
                      "first_frame_s": t1 - t0, "second_frame_s": t2 - t1}))
    return 0


def main() -> int:
    """Measure and print the JSON line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", required=True, help="repository root whose code to time")
    parser.add_argument("--calibration", required=True, help="calibration .npz")
    parser.add_argument("--data", required=True, help="gsmini_ball_9.47mm directory")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--startup", action="store_true",
                        help="print the start-up times instead (imports, constructing the "
                             "reconstructor, first and second frame: kernel loading or "
                             "compiling, the baked table); run it twice for a warm numba cache")
    args = parser.parse_args()
    t_start = time.perf_counter()
    sys.path.insert(0, str(Path(args.tree).resolve()))
    if args.startup:
        return startup(args, t_start)

    import numpy as np

    from benchmarks.gelsight_labels import split_labels
    from remote_site.reconstruction.features import relative_change
    from remote_site.reconstruction.frames import load_rgb, validate_frame
    from remote_site.reconstruction.kernels import evidence_kernel
    from remote_site.reconstruction.reconstructor import Reconstructor

    data = Path(args.data)
    rec = Reconstructor.from_file(args.calibration)
    frames = [load_rgb(data / lb.image) for lb in split_labels(data, "test")]
    calib = rec.calibration
    bg, inv_bg = rec._background_for(None)
    valid = [validate_frame(f, rec.shape_hw) for f in frames]
    noise = max(calib.noise_pct, 1e-3)
    ev = np.float32(rec.settings.contact_evidence_sigmas * noise)
    dz = np.float32(rec.settings.dead_zone_sigmas * noise)
    change = [relative_change(v, bg, calib.blur_sigma_px, inv_background_pct=inv_bg)
              for v in valid]
    active = [evidence_kernel(c, ev, dz)[1] for c in change]
    slopes = [rec.slopes(f)[:2] for f in frames]
    predictor = rec._grid_predictor(1, rec.shape_hw)
    gx = np.zeros(rec.shape_hw, np.float32)
    gy = np.zeros(rec.shape_hw, np.float32)
    pitch = calib.mm_per_px
    raw = [rec._solver.integrate(sx, sy, pitch) for sx, sy in slopes]
    frame_buf = np.empty_like(valid[0])
    stages: dict[str, Callable[[int], object]] = {
        "validate frame": lambda i: validate_frame(frames[i], rec.shape_hw, out=frame_buf),
        "colour change: gain + change + blur": lambda i: relative_change(
            valid[i], bg, calib.blur_sigma_px, inv_background_pct=inv_bg),
        "evidence count + active mask": lambda i: evidence_kernel(change[i], ev, dz),
        "model on active pixels": lambda i: predictor.predict_into(change[i], active[i], gx,
                                                                   gy),
        "Poisson (DST)": lambda i: rec._solver.integrate(*slopes[i], pitch),
        "zero level + mask + finite check": lambda i: rec._zero_level_and_mask(raw[i], pitch),
        "whole height_map": lambda i: rec.height_map(frames[i]),
    }
    out: dict[str, float] = {}
    for name, fn in stages.items():
        for i in range(len(frames)):  # compile / load kernels, warm caches
            fn(i)
        times = []
        for _ in range(args.repeats):
            for i in range(len(frames)):
                c0 = time.process_time()
                fn(i)
                times.append(time.process_time() - c0)
        out[name] = float(np.median(times)) * 1e3
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
