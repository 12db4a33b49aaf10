"""The view's patch encoding: quantisation error bound, NaN marking, the pins' window.

Property tests (hypothesis) against independent references: the decoded heights against
the originals, and the window against pin positions interpolated on the patch's own
coordinate axes (built as the TactileFrame docstring defines them).
"""

from __future__ import annotations

import base64
import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from local_site.render.pin_command import pin_offsets_mm
from shared.protocol import TactileFrame
from shared.timebase import now_us
from shared.view.encode import encode_patch, num, nums

heights = arrays(np.float32, st.tuples(st.integers(1, 12), st.integers(1, 12)),
                 elements=st.floats(-2.0, 6.0, width=32))


def _frame(height: np.ndarray, center: tuple[float, float] = (30.0, 30.0),
           pitch: float = 0.5) -> TactileFrame:
    return TactileFrame(seq=1, ts_us=0, center_mm=center, pitch_mm=pitch,
                        layers={"height_mm": height})


@settings(max_examples=60, deadline=None)
@given(heights)
def test_decoded_heights_are_within_half_a_step(height: np.ndarray) -> None:
    doc = encode_patch(_frame(height), now_us(), None, None)
    assert doc is not None and (doc["w"], doc["h"]) == (height.shape[1], height.shape[0])
    q = np.frombuffer(base64.b64decode(doc["data"]), np.uint8).reshape(height.shape)
    assert (q >= 1).all()  # every cell finite here
    lo, hi = doc["lo_mm"], doc["hi_mm"]
    assert lo == round(float(height.min()), 4) and hi == round(float(height.max()), 4)
    decoded = lo + (q.astype(np.float64) - 1) / 254.0 * (hi - lo)
    step = (hi - lo) / 254.0
    assert np.all(np.abs(decoded - height) <= step / 2 + 2e-4)  # + the 4-digit rounding


def test_non_finite_cells_are_marked_missing_and_never_reach_json() -> None:
    h = np.array([[0.0, np.nan], [np.inf, 1.0]], np.float32)
    frame = TactileFrame.__new__(TactileFrame)  # a frame the wire would have refused
    object.__setattr__(frame, "layers", {"height_mm": h})
    for name, value in (("seq", 1), ("center_mm", (0.0, 0.0)), ("pitch_mm", 1.0),
                        ("contact", False), ("force_n", math.nan), ("indentation_mm", 0.0)):
        object.__setattr__(frame, name, value)
    doc = encode_patch(frame, now_us(), None, None)
    assert doc is not None
    q = np.frombuffer(base64.b64decode(doc["data"]), np.uint8).reshape(2, 2)
    assert q[0, 1] == 0 and q[1, 0] == 0 and q[0, 0] == 1 and q[1, 1] == 255
    assert doc["force_n"] is None
    assert num(math.inf) is None and nums([1.0, math.nan]) == [1.0, None]


@settings(max_examples=80, deadline=None)
@given(st.integers(5, 40), st.integers(5, 40), st.floats(0.2, 2.0),
       st.floats(-20.0, 20.0), st.floats(-20.0, 20.0), st.floats(0.5, 3.0))
def test_the_window_encloses_the_pins_where_they_sample(w: int, h: int, pitch: float,
                                                        dx: float, dy: float,
                                                        pin_pitch: float) -> None:
    center = (30.0, 30.0)
    position = (center[0] + dx, center[1] + dy)
    doc = encode_patch(_frame(np.zeros((h, w), np.float32), center, pitch), now_us(),
                       position, pin_pitch)
    assert doc is not None
    c0, r0, c1, r1 = doc["window"]
    # independent reference: the patch's own axes, then the pins' outer edges on them
    xs = center[0] + (np.arange(w) - (w - 1) / 2.0) * pitch
    ys = center[1] + (np.arange(h) - (h - 1) / 2.0) * pitch
    pins = pin_offsets_mm(pin_pitch).reshape(-1, 2) + np.asarray(position)
    edge_x = (pins[:, 0].min() - pin_pitch / 2, pins[:, 0].max() + pin_pitch / 2)
    edge_y = (pins[:, 1].min() - pin_pitch / 2, pins[:, 1].max() + pin_pitch / 2)

    def index(axis: np.ndarray, value: float) -> float:  # linear, also beyond the ends
        return float((value - axis[0]) / (axis[1] - axis[0]) if axis.size > 1 else 0.0)

    assert math.isclose(c0, index(xs, edge_x[0]), abs_tol=2e-3)
    assert math.isclose(c1, index(xs, edge_x[1]), abs_tol=2e-3)
    assert math.isclose(r0, index(ys, edge_y[0]), abs_tol=2e-3)
    assert math.isclose(r1, index(ys, edge_y[1]), abs_tol=2e-3)
