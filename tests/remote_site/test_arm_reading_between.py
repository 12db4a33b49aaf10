"""Where the arm was between two polls: reading_between and polled_reading_at.

Checked against numpy.interp (the blend), against the simulated arm's own 1 kHz trajectory
polled at 250 Hz (the analytic bound of linear interpolation: a curve whose second
derivative stays within A is off its chord over a span h by at most A h^2 / 8), and against
the nearest poll it replaces.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.arm.base import ArmReading, polled_reading_at, reading_between
from remote_site.arm.sim import SimArm, SimArmConfig
from remote_site.phantom import make_scene
from shared.errors import InputDataError

coords = st.floats(-1e4, 1e4, allow_nan=False)
vec3 = st.tuples(coords, coords, coords)
readings = st.builds(ArmReading, vec3, vec3, st.floats(-100.0, 100.0),
                     st.sampled_from(["ok", "moving", "halted"]), st.none() | vec3,
                     st.floats(0.0, 1e6))


@settings(max_examples=200, deadline=None)
@given(a=readings, b=readings, w=st.floats(0.0, 1.0))
def test_the_blend_is_numpy_interp_and_the_rest_is_the_nearer(a: ArmReading, b: ArmReading,
                                                              w: float) -> None:
    r = reading_between(a, b, w)
    for got, lo, hi in ((r.position_mm, a.position_mm, b.position_mm),
                        (r.velocity_mm_s, a.velocity_mm_s, b.velocity_mm_s),
                        ((r.force_n, r.t_s), (a.force_n, a.t_s), (b.force_n, b.t_s))):
        want = [np.interp(w, [0.0, 1.0], [x, y]) for x, y in zip(lo, hi, strict=True)]
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)
        for v, x, y in zip(got, lo, hi, strict=True):
            assert min(x, y) - 1e-9 <= v <= max(x, y) + 1e-9
    near = a if w <= 0.5 else b
    assert (r.status, r.target_mm) == (near.status, near.target_mm)
    if w in (0.0, 1.0):
        assert r is (a if w == 0.0 else b)


@pytest.mark.parametrize("w", [-0.01, 1.01, math.nan, math.inf])
def test_a_weight_outside_the_span_is_refused(w: float) -> None:
    a = ArmReading((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, "ok", None, 0.0)
    with pytest.raises(InputDataError, match="weight"):
        reading_between(a, a, w)


def _reading(x: float) -> ArmReading:
    return ArmReading((x, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, "ok", None, x)


@settings(max_examples=200, deadline=None)
@given(gaps=st.lists(st.integers(1, 50_000), min_size=1, max_size=20),
       t_us=st.integers(-10_000, 1_200_000))
def test_polled_reading_at_follows_the_polls_piecewise_linear(gaps: list[int],
                                                              t_us: int) -> None:
    times = np.cumsum(gaps)
    polled = [(int(t), _reading(float(t) * 1e-3)) for t in times]  # x = t in ms
    got = polled_reading_at(polled, t_us)
    assert got is not None
    # x runs with t inside the polls, and stops at the first and the last outside them
    assert got.position_mm[0] == pytest.approx(np.interp(t_us, times, times) * 1e-3,
                                               rel=1e-12, abs=1e-9)
    if t_us <= times[0]:
        assert got is polled[0][1]
    elif t_us >= times[-1]:
        assert got is polled[-1][1]
    assert polled_reading_at([], t_us) is None


@settings(max_examples=10, deadline=None)
@given(targets=st.lists(st.tuples(st.floats(-40, 40), st.floats(-40, 40), st.floats(-5, 30)),
                        min_size=1, max_size=3),
       offset_steps=st.integers(0, 3))
def test_between_polls_the_arm_is_within_the_interpolation_bound(
        targets: list[tuple[float, float, float]], offset_steps: int) -> None:
    """The sim arm stepped at 1 kHz, polled every 4th step (250 Hz): at every step between
    two polls, the interpolated position is within A h^2 / 8 of the true one per axis (A the
    acceleration limit, h the poll spacing), and never further off than the nearest poll."""
    cfg = SimArmConfig(realtime=False)
    arm = SimArm(make_scene("breast", 1), cfg)
    arm.connect()
    try:
        truth: list[tuple[int, tuple[float, float, float]]] = []
        polled: list[tuple[int, ArmReading]] = []
        dt = 1.0 / cfg.loop_hz
        step_us = round(dt * 1e6)
        for k in range(600):
            if k % 200 == 0:
                arm.move_to(targets[(k // 200) % len(targets)])
            arm.advance(dt)
            t = k * step_us
            truth.append((t, arm.true_position_mm()))
            if k % 4 == offset_steps:
                polled.append((t, arm.state()))
        h_s = 4 * dt
        bound = cfg.max_acceleration_mm_s2 * h_s ** 2 / 8 + 1e-9
        worst_interp = worst_nearest = 0.0
        for t, true_pos in truth:
            if not polled[0][0] <= t <= polled[-1][0]:
                continue
            got = polled_reading_at(polled, t)
            assert got is not None
            err = max(abs(g - w) for g, w in zip(got.position_mm, true_pos, strict=True))
            assert err <= bound
            nearest = min(polled, key=lambda p: abs(p[0] - t))[1]
            worst_interp = max(worst_interp, err)
            worst_nearest = max(worst_nearest, max(
                abs(g - w) for g, w in zip(nearest.position_mm, true_pos, strict=True)))
        assert worst_interp <= worst_nearest + 1e-12
    finally:
        arm.disconnect()
