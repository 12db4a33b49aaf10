"""Does each labelled calibration press show its contact where the label puts it?

A calibration trains the colour-to-slope model on the sphere's slopes inside each labelled
circle and on zero slope far from it, so one label on the wrong image (or copied from the
previous press) teaches the model that flat gel is steep and that a real contact is flat.
Labels are made by hand (the GelSight Mini set in the team kit was fitted by eye, and its
``press_50`` carries ``press_49``'s centre), so every press is checked against its own
colour change before it is used:

* the *strong* change is the relative colour change (:func:`.features.relative_change`)
  above ``median + max(8 sigma, 1 %)`` of the frame, sigma the robust (MAD) noise of the
  frame, which is mostly flat gel;
* a press is consistent when at least ``MIN_SHARE_NEAR`` of the strong change (weighted by
  how far it exceeds the threshold) lies within ``NEAR_FACTOR`` labelled radii of the
  labelled centre, and the frame shows a contact at all (at least ``MIN_STRONG_PX`` strong
  pixels).

On the kit's 51 presses the share is 0.99-1.00 for 50 and 0.04 for ``press_50``; the
thresholds leave a wide margin either side. This checks that the label sits on the press,
not that it is exact: a circle a few pixels off passes (the calibration's ``trim_px`` and
the least-squares fit absorb that).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from remote_site.reconstruction.features import relative_change
from remote_site.reconstruction.frames import validate_frame
from remote_site.reconstruction.labels import BallLabel

__all__ = ["MIN_SHARE_NEAR", "MIN_STRONG_PX", "NEAR_FACTOR", "LabelProblem", "label_problem",
           "screen_presses"]

#: strong change must lie within this many labelled radii of the labelled centre ...
NEAR_FACTOR = 1.5
#: ... for at least this share of it
MIN_SHARE_NEAR = 0.5
#: a frame with fewer strong pixels shows no contact
MIN_STRONG_PX = 50
#: threshold of the strong change: median + max(SIGMAS * robust sigma, FLOOR_PCT)
SIGMAS, FLOOR_PCT = 8.0, 1.0


class LabelProblem(NamedTuple):
    """A labelled press whose image disagrees with its label."""

    image: str
    reason: str


def label_problem(change_pct: np.ndarray, label: BallLabel) -> str | None:
    """Why the label does not fit the press's colour change, or None if it does.

    Args:
        change_pct: (H, W, 3) relative colour change of the press, percent.
        label: its labelled contact circle (pixels).
    """
    magnitude = np.linalg.norm(change_pct, axis=2)
    median = float(np.median(magnitude))
    sigma = 1.4826 * float(np.median(np.abs(magnitude - median)))
    excess = magnitude - (median + max(SIGMAS * sigma, FLOOR_PCT))
    strong = excess > 0
    n_strong = int(strong.sum())
    if n_strong < MIN_STRONG_PX:
        return (f"shows no contact ({n_strong} pixels change by more than the flat gel's "
                "noise): a no-contact frame, or the wrong background")
    rows, cols = np.nonzero(strong)
    weights = excess[rows, cols]
    near = np.hypot(cols - label.center_x, rows - label.center_y) < NEAR_FACTOR * label.radius_px
    share = float(weights[near].sum() / weights.sum())
    if share >= MIN_SHARE_NEAR:
        return None
    cx = float(np.average(cols, weights=weights))
    cy = float(np.average(rows, weights=weights))
    return (f"only {share:.0%} of its colour change lies within {NEAR_FACTOR:g} radii of the "
            f"labelled circle (centre {label.center_x:g}, {label.center_y:g}, radius "
            f"{label.radius_px:g} px); the change is centred near ({cx:.0f}, {cy:.0f}): "
            "the label belongs to another image or is misplaced")


def screen_presses(background_rgb: np.ndarray,
                   presses: Sequence[tuple[np.ndarray, BallLabel]], blur_sigma_px: float = 1.0
                   ) -> tuple[list[tuple[np.ndarray, BallLabel]], list[LabelProblem]]:
    """Split labelled presses into the consistent ones and the problems (see the module doc).

    Raises:
        InputDataError: a frame that is not an image of the background's size.
    """
    background = validate_frame(background_rgb, name="background")
    kept: list[tuple[np.ndarray, BallLabel]] = []
    problems: list[LabelProblem] = []
    for frame, label in presses:
        image = validate_frame(frame, background.shape[:2], name=label.image)
        reason = label_problem(relative_change(image, background, blur_sigma_px), label)
        if reason is None:
            kept.append((frame, label))
        else:
            problems.append(LabelProblem(label.image, reason))
    return kept, problems
