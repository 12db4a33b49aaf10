"""The calibration's label check on synthetic colour changes (the kit case is in
test_reconstruction_real_gelsight.py)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.reconstruction.label_check import NEAR_FACTOR, label_problem
from remote_site.reconstruction.labels import BallLabel

H, W = 120, 160


def ring_change(cx: float, cy: float, radius: float, noise: float = 0.5,
                seed: int = 0) -> np.ndarray:
    """A press-like colour change (strongest towards the rim, as a sphere's slope) plus noise."""
    rows, cols = np.mgrid[0:H, 0:W]
    r = np.hypot(cols - cx, rows - cy)
    amp = np.where(r < radius, 30.0 * r / radius, 30.0 * np.exp(-(r - radius) / 3.0))
    rng = np.random.default_rng(seed)
    change = amp[..., None] * np.array([0.6, 0.5, 0.4]) + rng.normal(0, noise, (H, W, 3))
    return change.astype(np.float32)


@settings(max_examples=40, deadline=None)
@given(cx=st.floats(25, W - 25), cy=st.floats(25, H - 25), radius=st.floats(10, 20),
       off=st.floats(0, 4), angle=st.floats(0, 2 * np.pi))
def test_a_label_a_few_pixels_off_passes(cx: float, cy: float, radius: float, off: float,
                                         angle: float) -> None:
    label = BallLabel("p.png", cx + off * np.cos(angle), cy + off * np.sin(angle), radius)
    assert label_problem(ring_change(cx, cy, radius), label) is None


@settings(max_examples=40, deadline=None)
@given(cx=st.floats(20, 60), cy=st.floats(20, H - 20), radius=st.floats(8, 15),
       shift=st.floats(0, 1))
def test_a_label_on_flat_gel_is_named_with_where_the_press_is(cx: float, cy: float,
                                                               radius: float,
                                                               shift: float) -> None:
    # the label sits well beyond NEAR_FACTOR radii plus the press's own extent
    lx = cx + (NEAR_FACTOR + 2.5) * radius + 10 + shift * 20
    reason = label_problem(ring_change(cx, cy, radius), BallLabel("p.png", lx, cy, radius))
    assert reason is not None and "belongs to another image or is misplaced" in reason
    near = reason.split("centred near (")[1].split(")")[0].split(", ")
    assert abs(float(near[0]) - cx) < 3 and abs(float(near[1]) - cy) < 3


def test_a_frame_without_contact_is_named() -> None:
    flat = np.random.default_rng(1).normal(0, 0.5, (H, W, 3)).astype(np.float32)
    reason = label_problem(flat, BallLabel("p.png", 80, 60, 15))
    assert reason is not None and "shows no contact" in reason
