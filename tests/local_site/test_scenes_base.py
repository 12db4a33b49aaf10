"""SceneSource.rasterize and OutsidePolicy on input beyond their bounds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from local_site.scenes import make_shape_scene
from local_site.scenes.base import OutsidePolicy
from shared.errors import ConfigError, InputDataError

_MAX = 4096  # samples per side (scenes.base._MAX_RASTER_DIM)


@pytest.mark.parametrize("extent, pitch", [
    ((-1e308, 1e308, 0.0, 1.0), 1.0),  # the span overflows to inf (OverflowError before)
    ((0.0, 1.0, -1e308, 1e308), 1.0),
    ((0.0, 1e300, 0.0, 1.0), 1.0),
    ((0.0, 1.0, 0.0, 1.0), 5e-324),  # 1 / pitch is inf
    ((0.0, 1.0, 0.0, 1.0), 1e-300)])
def test_a_raster_too_large_for_floats_is_an_input_error(
        extent: tuple[float, float, float, float], pitch: float) -> None:
    with pytest.raises(InputDataError, match="too large"):
        make_shape_scene("hemisphere").rasterize(extent, pitch)


@settings(max_examples=40, deadline=None)
@given(x0=st.floats(-1e308, 1e308), span=st.floats(1e-300, 1e308),
       pitch=st.floats(1e-300, 1e300))
def test_rasterize_returns_a_bounded_grid_or_an_input_error(x0: float, span: float,
                                                            pitch: float) -> None:
    x1 = x0 + span
    steps = (x1 - x0) / pitch
    try:
        # (a hemisphere sampled near 1e308 mm squares its coordinates to inf: a warning, the
        # right answer (outside its disc); the subject here is the raster's size)
        with np.errstate(over="ignore"):
            out = make_shape_scene("hemisphere").rasterize((x0, x1, 0.0, pitch), pitch)
    except InputDataError:
        assert not (x1 > x0 and steps < _MAX - 1)  # refused: degenerate or too large
        return
    ny, nx = out["height_mm"].shape
    assert nx == round(steps) + 1 <= _MAX and ny == 2


@pytest.mark.parametrize("field, bad", [("height_mm", "1"), ("stiffness_k", None),
                                        ("friction", [0.1]), ("height_mm", True)])
def test_outside_policy_values_must_be_numbers(field: str, bad: object) -> None:
    with pytest.raises(ConfigError, match=field):
        OutsidePolicy(**{field: bad})  # type: ignore[arg-type]
    assert OutsidePolicy(height_mm=np.float64(0.5)).height_mm == 0.5
