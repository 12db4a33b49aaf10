"""Does another version of a library (OpenCV, NumPy, numba) change the reconstruction?

Run under each interpreter (a virtual environment per version set), then compare::

    A/bin/python benchmarks/reconstruction_versions.py dump --out /tmp/a.npz
    B/bin/python benchmarks/reconstruction_versions.py dump --out /tmp/b.npz \\
        --calibration /tmp/a.npz.calib.npz
    python benchmarks/reconstruction_versions.py compare /tmp/a.npz /tmp/b.npz

``dump`` fits the default calibration on the real GelSight Mini train presses (as
``bench_reconstruction_fullres.py`` does), keeps it beside ``--out`` (``.calib.npz``), and
writes the height maps of the test presses reconstructed with its own calibration and, with
``--calibration``, with another's (the first interpreter's). ``compare`` prints the largest
difference of the calibrations' arrays and of the height maps: calibration fits against
each other, and the reconstruction alone (both sides with the first calibration).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.bench_reconstruction_fullres import BALL_RADIUS_MM, MM_PER_PX  # noqa: E402
from benchmarks.gelsight_labels import DEFAULT_DATA, split_labels, train_labels  # noqa: E402
from remote_site.reconstruction.calibration import fit_calibration  # noqa: E402
from remote_site.reconstruction.frames import load_rgb  # noqa: E402
from remote_site.reconstruction.reconstructor import Reconstructor  # noqa: E402


def _heights(rec: Reconstructor, data: Path) -> dict[str, np.ndarray]:
    return {lb.image: np.asarray(rec.height_map(load_rgb(data / lb.image)).height_mm)
            for lb in split_labels(data, "test")}


def dump(args: argparse.Namespace) -> int:
    """Fit, reconstruct and write (see the module docstring)."""
    data = Path(args.data) if args.data else DEFAULT_DATA
    background = load_rgb(data / "background.png")
    calib = fit_calibration(background,
                            [(load_rgb(data / lb.image), lb) for lb in train_labels(data)],
                            2 * BALL_RADIUS_MM, MM_PER_PX)
    calib_path = Path(f"{args.out}.calib.npz")
    calib.save(calib_path)
    # Any: numpy's stubs type savez's keywords with its allow_pickle flag
    out: dict[str, Any] = {f"own/{k}": v
                           for k, v in _heights(Reconstructor(calib), data).items()}
    if args.calibration:
        other = Reconstructor.from_file(args.calibration)
        out.update({f"given/{k}": v for k, v in _heights(other, data).items()})
    out["versions"] = np.array([cv2.__version__, np.__version__])
    np.savez(args.out, **out)
    print(f"OpenCV {cv2.__version__}, NumPy {np.__version__}: wrote {args.out}, {calib_path}")
    return 0


def _largest(a: np.ndarray, b: np.ndarray) -> float:
    """The largest difference; infinite where the NaNs lie in different places."""
    if not a.size:
        return 0.0
    if not np.array_equal(np.isnan(a), np.isnan(b)):
        return float("inf")
    diff = np.abs(a.astype(np.float64) - b.astype(np.float64))
    return float(np.nanmax(diff)) if np.isfinite(diff).any() else 0.0


def _identical(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def compare(args: argparse.Namespace) -> int:
    """Print the largest differences between two dumps."""
    a, b = np.load(args.first), np.load(args.second)
    print(f"first: OpenCV {a['versions'][0]}, NumPy {a['versions'][1]}; "
          f"second: OpenCV {b['versions'][0]}, NumPy {b['versions'][1]}")
    ca, cb = np.load(f"{args.first}.calib.npz"), np.load(f"{args.second}.calib.npz")
    for key in sorted(set(ca.files) ^ set(cb.files)):
        print(f"calibration {key}: only in the {'first' if key in ca.files else 'second'}")
    for key in sorted(set(ca.files) & set(cb.files)):
        x, y = ca[key], cb[key]
        if x.shape != y.shape:
            print(f"calibration {key}: shapes differ, {x.shape} against {y.shape}")
        elif x.dtype.kind in "fiub" and (d := _largest(x, y)) > 0:
            print(f"calibration {key}: largest difference {d:.3g}")
    pairs = {"each its own calibration": [(a[k], b[k]) for k in a.files if k.startswith("own/")]}
    given = [k for k in b.files if k.startswith("given/")]
    if given:
        pairs["both with the first calibration"] = [(a["own/" + k.split("/", 1)[1]], b[k])
                                                    for k in given]
    for what, maps in pairs.items():
        same = sum(_identical(x, y) for x, y in maps)
        print(f"heights, {what}: largest difference "
              f"{max(_largest(x, y) for x, y in maps) * 1e3:.3g} um; "
              f"{same} of {len(maps)} maps bit-identical")
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("dump", help="fit, reconstruct, write")
    d.add_argument("--out", required=True, help="height maps .npz (calibration beside it)")
    d.add_argument("--calibration", default=None,
                   help="another interpreter's calibration to reconstruct with as well")
    d.add_argument("--data", default=None, help="gsmini_ball_9.47mm directory (default: kit)")
    c = sub.add_parser("compare", help="largest differences between two dumps")
    c.add_argument("first")
    c.add_argument("second")
    parsed = parser.parse_args()
    sys.exit(dump(parsed) if parsed.cmd == "dump" else compare(parsed))
