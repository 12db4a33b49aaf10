"""Shore 00 <-> k calibration table: monotone, clamped, invertible, validated."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from shared.errors import ConfigError, InputDataError
from shared.hardness import HardnessTable


@given(st.floats(-1e6, 1e6, allow_nan=False))
def test_k_always_in_display_range(shore: float) -> None:
    k = float(HardnessTable().shore00_to_k(shore))
    assert 0.5 <= k <= 1.0


@given(st.floats(10, 90))
def test_inverse_inside_table(shore: float) -> None:
    t = HardnessTable()
    assert math.isclose(float(t.k_to_shore00(t.shore00_to_k(shore))), shore, abs_tol=1e-9)


def test_linear_default_matches_two_point_formula() -> None:
    s = np.linspace(10, 90, 17)
    np.testing.assert_allclose(HardnessTable().shore00_to_k(s), 0.5 + 0.5 * (s - 10) / 80)


def test_custom_points_piecewise() -> None:
    t = HardnessTable.from_points([(0, 0.5), (50, 0.9), (100, 1.0)])
    np.testing.assert_allclose(t.shore00_to_k([25, 75]), [0.7, 0.95])


@pytest.mark.parametrize("points", [[(10, 0.5)], [(10, 0.5), (5, 0.6)], [(10, 0.6), (20, 0.55)],
                                    [(10, 0.4), (20, 0.6)], [(10, 0.5), (120, 1.0)],
                                    [(10, 0.5), (math.nan, 1.0)]])
def test_bad_tables(points) -> None:
    with pytest.raises(ConfigError):
        HardnessTable.from_points(points)


def test_nan_input_rejected() -> None:
    with pytest.raises(InputDataError):
        HardnessTable().shore00_to_k([10, math.nan])
    with pytest.raises(InputDataError):
        HardnessTable().k_to_shore00(math.inf)
