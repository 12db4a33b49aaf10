"""Calibrate a GelSight-style sensor from ball presses, and reconstruct height maps.

  teletouch sensor calibrate --background BG.png --images DIR --labels labels.csv \\
      --ball-diameter-mm D --mm-per-px P --out calib.npz
  teletouch sensor reconstruct --calibration calib.npz --background BG.png FRAME.png ... \\
      --out heights.npz
  teletouch sensor calibrate-stiffness --presses presses.csv --out stiffness_calib.json

labels.csv has columns image,center_x,center_y,radius_px (center_x = column, center_y =
row, pixels; image relative to --images). heights.npz holds one float32 array per frame,
keyed by the frame's file name, in mm, positive where the object presses into the gel, the
same shape as the frame (unless --out-pitch-mm asks for a coarser grid). Height 0 is the
undeformed gel (a plane fitted outside the contact region), or the detected contact rim for
a calibration made with ``--relief rim`` (the object's relief without the gel's drape).

presses.csv (for calibrate-stiffness) has columns sample,shore00,force_n,indentation_mm:
presses of the pad on reference blocks of known Shore 00 (``rigid`` for a rigid block); see
:mod:`remote_site.stiffness.calibrate`. The result is a stiffness calibration (JSON, see
:mod:`shared.stiffness_calibration`) for ``teletouch remote --stiffness-calibration``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["configure_parser", "run"]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the ``calibrate``, ``reconstruct`` and ``calibrate-stiffness`` subcommands."""
    sub = parser.add_subparsers(dest="sensor_command", metavar="SUBCOMMAND", required=True)
    cal = sub.add_parser("calibrate", help="fit a colour-to-slope calibration from ball presses")
    cal.add_argument("--background", required=True, help="no-contact frame (PNG)")
    cal.add_argument("--images", required=True, help="directory holding the press images")
    cal.add_argument("--labels", required=True,
                     help="labels.csv: image,center_x,center_y,radius_px")
    cal.add_argument("--ball-diameter-mm", type=float, required=True)
    cal.add_argument("--mm-per-px", type=float, required=True)
    cal.add_argument("--out", required=True, help="calibration file to write (.npz)")
    cal.add_argument("--model", choices=["poly", "lut"], default="poly",
                     help="poly: position-aware polynomial (default); lut: lookup table")
    cal.add_argument("--degree", type=int, default=5, help="polynomial degree (default 5)")
    cal.add_argument("--trim-px", type=float, default=4.0,
                     help="pixels trimmed off each labelled radius (default 4, as gs_sdk)")
    # the choices are relief.RELIEF_MODES, spelled out: importing the package here would load
    # the whole reconstruction for every teletouch command
    cal.add_argument("--relief", choices=["plane", "rim"], default="plane",
                     help="height reference saved for this sensor: plane = above the free gel "
                          "(default; palpation, pad flat on tissue), rim = the object's relief "
                          "above its contact rim, without the gel's drape (objects smaller "
                          "than the pad; fits one parameter on these presses, "
                          "see docs/reconstruction.md)")
    # the choices are calibration.CENTRES, spelled out for the same reason
    cal.add_argument("--centres", choices=["edge", "label"], default="edge",
                     help="edge = move each label's centre onto the contact edge its image "
                          "shows, where that edge is clean (default: hand labels are a few "
                          "pixels off); label = train on the centres as labelled")
    cal.add_argument("--drop-bad-labels", action="store_true",
                     help="calibrate without the presses whose label does not sit on their "
                          "contact (named in a warning) instead of refusing them")
    cal.add_argument("--json", action="store_true", help="print a JSON summary")

    rec = sub.add_parser("reconstruct", help="turn frames into height maps (mm)")
    rec.add_argument("--calibration", required=True, help="calibration file (.npz)")
    rec.add_argument("--background", default=None,
                     help="fresh no-contact frame (default: the calibration's background)")
    rec.add_argument("frames", nargs="+", help="frames (PNG) to reconstruct")
    rec.add_argument("--out", required=True, help="output .npz, one array per frame")
    rec.add_argument("--solver", choices=["dct", "dst", "fft"], default="dst")
    rec.add_argument("--out-pitch-mm", type=float, default=None,
                     help="coarser output grid pitch (default: full resolution)")
    rec.add_argument("--json", action="store_true", help="print a JSON summary")

    stiff = sub.add_parser("calibrate-stiffness",
                           help="fit the gel stiffness and the N/mm -> Shore 00 curve from "
                                "presses on reference blocks")
    stiff.add_argument("--presses", required=True,
                       help="presses.csv: sample,shore00,force_n,indentation_mm")
    stiff.add_argument("--out", required=True, help="stiffness calibration to write (.json)")
    stiff.add_argument("--source", default="", help="free text stored in the file")
    out_mode = stiff.add_mutually_exclusive_group()
    out_mode.add_argument("--json", action="store_true", help="print a JSON summary")
    out_mode.add_argument("--quiet", action="store_true", help="print nothing")


def _calibrate(args: argparse.Namespace) -> int:
    from remote_site.reconstruction.calibration import fit_calibration
    from remote_site.reconstruction.frames import load_rgb
    from remote_site.reconstruction.labels import read_labels_csv
    from shared.errors import CalibrationError
    from shared.report import emit, emit_json

    images_dir = Path(args.images)
    if not images_dir.is_dir():
        raise CalibrationError(f"--images {images_dir} is not a directory")
    labels = read_labels_csv(args.labels)
    background = load_rgb(args.background)
    presses = [(load_rgb(images_dir / label.image), label) for label in labels]
    dropped: list[str] = []
    if args.drop_bad_labels:
        from remote_site.reconstruction.label_check import screen_presses

        presses, problems = screen_presses(background, presses)
        for problem in problems:
            emit(f"warning: calibrating without {problem.image}: {problem.reason}",
                 stream=sys.stderr)
        dropped = [p.image for p in problems]
    calib = fit_calibration(background, presses, args.ball_diameter_mm, args.mm_per_px,
                            model=args.model, degree=args.degree, trim_px=args.trim_px,
                            centres=args.centres)
    if args.relief == "rim":
        from remote_site.reconstruction.relief_fit import fit_rim_relief

        calib = fit_rim_relief(calib, presses)
    calib.save(args.out)
    summary = {"out": str(args.out), "model": args.model, "presses": len(presses),
               "shape_hw": list(calib.shape_hw), "noise_pct": calib.noise_pct,
               "relief": calib.relief, "dropped_presses": dropped,
               "rim_extension_mm": {str(k): v for k, v in calib.rim_extension_mm.items()},
               **calib.stats}
    if args.json:
        emit_json(summary)
    else:
        emit(f"calibrated {args.model} model on {len(presses)} presses "
             + (f"(dropped {', '.join(dropped)}: label not on the contact) " if dropped else "")
             + f"({calib.shape_hw[1]}x{calib.shape_hw[0]}): training slope RMSE "
             f"{calib.stats['train_slope_rmse']:.4f}, flat-gel noise {calib.noise_pct:.2f} %, "
             f"relief {calib.relief}"
             + (f", {calib.stats['centres_moved_to_edge']:.0f} centres moved to the contact "
                f"edge (mean {calib.stats['centre_moved_mean_px']:.1f} px, max "
                f"{calib.stats['centre_moved_max_px']:.1f} px)" if args.centres == "edge" else "")
             + f" -> {args.out}")
    return 0


def _reconstruct(args: argparse.Namespace) -> int:
    import numpy as np

    from remote_site.reconstruction.frames import load_rgb
    from remote_site.reconstruction.reconstructor import ReconstructionSettings, Reconstructor
    from shared.errors import InputDataError
    from shared.report import emit, emit_json, format_table

    rec = Reconstructor.from_file(args.calibration, ReconstructionSettings(solver=args.solver))
    background = load_rgb(args.background) if args.background else None
    heights: dict[str, np.ndarray] = {}
    rows = []
    for path in args.frames:
        key = Path(path).name
        if key in heights:
            raise InputDataError(f"two frames share the file name {key!r}")
        hm = rec.height_map(load_rgb(path), background=background,
                            out_pitch_mm=args.out_pitch_mm)
        heights[key] = hm.height_mm.astype(np.float32)
        rows.append({"frame": key, "contact": hm.contact, "skipped": hm.skipped,
                     "max_height_mm": hm.max_height_mm,
                     "contact_area_mm2": float(hm.mask.sum()) * hm.mm_per_px**2})
    np.savez_compressed(args.out, **heights)  # type: ignore[arg-type]
    if args.json:
        emit_json({"out": str(args.out), "frames": rows})
    else:
        emit(format_table(rows))
        emit(f"wrote {len(heights)} height map(s) to {args.out}")
    return 0


def _calibrate_stiffness(args: argparse.Namespace) -> int:
    from remote_site.stiffness.calibrate import fit_stiffness_calibration, read_presses_csv
    from shared.report import emit, emit_json

    records = read_presses_csv(args.presses)
    calib = fit_stiffness_calibration(records, source=args.source or str(args.presses))
    calib.save(args.out)
    curve = calib.shore_curve.points
    summary = {"out": str(args.out), "presses": len(records),
               "reference_samples": len(calib.reference_samples),
               "gel_stiffness_n_per_mm": calib.gel_stiffness_n_per_mm,
               "shore00_range": [curve[0][1], curve[-1][1]],
               "n_per_mm_range": [curve[0][0], curve[-1][0]]}
    if args.json:
        emit_json(summary)
    elif not args.quiet:
        emit(f"stiffness calibration from {len(records)} presses on "
             f"{len(calib.reference_samples)} blocks: gel {calib.gel_stiffness_n_per_mm:.4g} "
             f"N/mm, Shore 00 {curve[0][1]:g}..{curve[-1][1]:g} over "
             f"{curve[0][0]:.4g}..{curve[-1][0]:.4g} N/mm -> {args.out}")
    return 0


def run(args: argparse.Namespace) -> int:
    """Dispatch ``teletouch sensor calibrate|reconstruct|calibrate-stiffness``."""
    if args.sensor_command == "calibrate":
        return _calibrate(args)
    if args.sensor_command == "calibrate-stiffness":
        return _calibrate_stiffness(args)
    return _reconstruct(args)
