"""Ball-press labels: ``labels.csv`` (``image,center_x,center_y,radius_px``) and checks.

``center_x`` is the column and ``center_y`` the row of the contact circle's centre, in
pixels of the stored image; ``radius_px`` its radius. :func:`labels_from_npz` converts the
gs_sdk-style ``<name>_label.npz`` files (keys ``center`` = [x, y], ``radius``).
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.errors import CalibrationError, InputDataError

__all__ = ["LABEL_COLUMNS", "BallLabel", "labels_from_npz", "read_labels_csv",
           "validate_label", "write_labels_csv"]

LABEL_COLUMNS = ("image", "center_x", "center_y", "radius_px")


@dataclass(frozen=True)
class BallLabel:
    """The contact circle of one ball press.

    Attributes:
        image: image file name (relative to the images directory).
        center_x: centre column, px.
        center_y: centre row, px.
        radius_px: contact radius, px.
    """

    image: str
    center_x: float
    center_y: float
    radius_px: float


def validate_label(label: BallLabel, shape_hw: tuple[int, int], trim_px: float = 0.0) -> None:
    """Check that a label describes a usable circle inside an image of ``shape_hw``.

    Raises:
        InputDataError: non-finite values, a radius too small after trimming, or a centre
            outside the image.
    """
    vals = (label.center_x, label.center_y, label.radius_px)
    if not all(math.isfinite(v) for v in vals):
        raise InputDataError(f"label for {label.image}: non-finite value in {vals}")
    h, w = shape_hw
    if label.radius_px - trim_px < 3:
        raise InputDataError(f"label for {label.image}: radius {label.radius_px} px is too small "
                             f"(after trimming {trim_px} px)")
    if not (0 <= label.center_x < w and 0 <= label.center_y < h):
        raise InputDataError(f"label for {label.image}: centre ({label.center_x}, "
                             f"{label.center_y}) lies outside the {w}x{h} image")
    if label.radius_px > max(h, w):
        raise InputDataError(f"label for {label.image}: radius {label.radius_px} px exceeds "
                             "the image")


def read_labels_csv(path: str | os.PathLike[str]) -> list[BallLabel]:
    """Read ``labels.csv``.

    Raises:
        CalibrationError: the file is missing, lacks a column, has an unparsable number or
            lists an image twice.
    """
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            missing = [c for c in LABEL_COLUMNS if c not in (reader.fieldnames or [])]
            if missing:
                raise CalibrationError(f"{path}: missing column(s) {missing}; expected "
                                       f"{','.join(LABEL_COLUMNS)}")
            labels = []
            for line, row in enumerate(reader, start=2):
                try:
                    labels.append(BallLabel(row["image"].strip(), float(row["center_x"]),
                                            float(row["center_y"]), float(row["radius_px"])))
                except (TypeError, ValueError) as err:
                    raise CalibrationError(f"{path}:{line}: bad number: {err}") from err
    except FileNotFoundError as err:
        raise CalibrationError(f"labels file not found: {path}") from err
    names = [lb.image for lb in labels]
    if len(set(names)) != len(names):
        raise CalibrationError(f"{path}: an image is labelled twice")
    if not labels:
        raise CalibrationError(f"{path}: no labels")
    return labels


def write_labels_csv(path: str | os.PathLike[str], labels: Iterable[BallLabel]) -> None:
    """Write labels as ``labels.csv``."""
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(LABEL_COLUMNS)
        for lb in labels:
            writer.writerow([lb.image, f"{lb.center_x:.3f}", f"{lb.center_y:.3f}",
                             f"{lb.radius_px:.3f}"])


def labels_from_npz(images_dir: str | os.PathLike[str], names: Sequence[str]) -> list[BallLabel]:
    """Convert gs_sdk-style ``<stem>_label.npz`` files next to ``<stem>.png`` into labels.

    Args:
        images_dir: directory holding ``<stem>.png`` and ``<stem>_label.npz``.
        names: image file names to convert (e.g. the train split).

    Raises:
        CalibrationError: a label file is missing or lacks ``center``/``radius``.
    """
    out = []
    for name in names:
        npz = Path(images_dir) / (Path(name).stem + "_label.npz")
        try:
            with np.load(npz) as data:
                centre = np.asarray(data["center"], np.float64).ravel()
                radius = float(np.asarray(data["radius"]).ravel()[0])
        except FileNotFoundError as err:
            raise CalibrationError(f"label file not found: {npz}") from err
        except KeyError as err:
            raise CalibrationError(f"{npz}: missing key {err}") from err
        out.append(BallLabel(name, float(centre[0]), float(centre[1]), radius))
    return out
