"""Write ``labels.csv`` for a split of the GelSight Mini ball-press set (team kit data).

The kit stores each press's hand-labelled contact circle as ``press_XX_label.npz`` (gs_sdk
format: ``center`` = [x (column), y (row)] px, ``radius`` px) and the author's 40/11 split
in ``train_test_split.json`` (entries ``9.470mm/<i>`` -> ``press_<ii>.png``). This helper
converts one split to the CLI's ``labels.csv`` (image,center_x,center_y,radius_px), so the
calibration is run exactly as a user would::

    python benchmarks/gelsight_labels.py --split train --out /tmp/labels_train.csv
    teletouch sensor calibrate --background $D/background.png --images $D \\
        --labels /tmp/labels_train.csv --ball-diameter-mm 9.47 --mm-per-px 0.0634 \\
        --drop-bad-labels --out /tmp/calib.npz

with ``D=../shared/data/gelsight/gsmini_ball_9.47mm`` (the team kit beside the repository).
Radii are written as labelled (untrimmed); the calibration trims ``--trim-px`` itself.
``--drop-bad-labels``: the kit's ``press_50`` label is ``press_49``'s circle, which the
calibration refuses (:mod:`remote_site.reconstruction.label_check`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from remote_site.reconstruction.labels import (  # noqa: E402
    BallLabel,
    labels_from_npz,
    write_labels_csv,
)

DEFAULT_DATA = (ROOT / ".." / "shared" / "data" / "gelsight" / "gsmini_ball_9.47mm").resolve()
#: the kit's ball (9.47 mm) and the Mini's pixel pitch at 320 x 240
BALL_RADIUS_MM = 4.735
MM_PER_PX = 0.0634
FRAME_W_PX, FRAME_H_PX = 320, 240


def border_distance_px(label: BallLabel) -> float:
    """How far a label's centre lies from the nearest frame edge (px)."""
    return min(label.center_x, FRAME_W_PX - label.center_x, label.center_y,
               FRAME_H_PX - label.center_y)


def cap_shift_px(reconstructor: Any, rgb: Any, label: BallLabel) -> Any:
    """The reconstructed cap's centre minus the labelled one, (dx, dy) px: the cap fitted
    to ``reconstructor``'s height map of ``rgb`` with the ball radius fixed."""
    import numpy as np

    from lab.reconstruction_metrics import evaluate_press

    return np.array(evaluate_press(reconstructor.height_map(rgb).height_mm, MM_PER_PX, label,
                                   MM_PER_PX, BALL_RADIUS_MM).centre_shift_xy_px)


def split_names(data_dir: Path, split: str) -> list[str]:
    """Image file names of ``split`` ("train" or "test"), in the split file's order."""
    entries = json.loads((data_dir / "train_test_split.json").read_text())[split]
    return [f"press_{int(entry.rsplit('/', 1)[1]):02d}.png" for entry in entries]


def split_labels(data_dir: Path, split: str) -> list[BallLabel]:
    """Labels of one split, read from the ``_label.npz`` files."""
    return labels_from_npz(data_dir, split_names(data_dir, split))


def train_labels(data_dir: Path) -> list[BallLabel]:
    """The train split's labels that pass the calibration's label check.

    The kit's ``press_50`` carries ``press_49``'s circle (on flat gel); the calibration
    refuses it (:mod:`remote_site.reconstruction.label_check`), so the benchmarks calibrate
    without it, as ``teletouch sensor calibrate --drop-bad-labels`` does. Dropped presses
    are named on stderr.
    """
    from remote_site.reconstruction.frames import load_rgb
    from remote_site.reconstruction.label_check import screen_presses

    labels = split_labels(data_dir, "train")
    kept, problems = screen_presses(load_rgb(data_dir / "background.png"),
                                    [(load_rgb(data_dir / lb.image), lb) for lb in labels])
    for problem in problems:
        print(f"train split: without {problem.image}: {problem.reason}", file=sys.stderr)
    return [lb for _, lb in kept]


def main(argv: list[str] | None = None) -> int:
    """Command-line entry: write labels.csv for one split."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--split", choices=["train", "test"], default="train")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    write_labels_csv(args.out, split_labels(args.data, args.split))
    return 0


if __name__ == "__main__":
    sys.exit(main())
