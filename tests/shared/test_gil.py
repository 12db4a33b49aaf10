"""shared.gil.switch_interval: set inside the block, restored after, validated."""

from __future__ import annotations

import math
import sys

import pytest

from shared.gil import switch_interval


@pytest.fixture(autouse=True)
def _keep_interval():
    before = sys.getswitchinterval()
    yield
    sys.setswitchinterval(before)


def test_sets_the_interval_inside_the_block_and_restores_it_after():
    sys.setswitchinterval(0.004)
    with switch_interval(0.0005) as inside:
        assert sys.getswitchinterval() == pytest.approx(0.0005)
        assert inside == pytest.approx(0.0005)
    assert sys.getswitchinterval() == pytest.approx(0.004)


def test_zero_leaves_the_interpreter_setting_alone():
    sys.setswitchinterval(0.003)
    with switch_interval(0.0) as inside:
        assert sys.getswitchinterval() == pytest.approx(0.003)
        assert inside == pytest.approx(0.003)
    assert sys.getswitchinterval() == pytest.approx(0.003)


def test_restored_when_the_block_raises():
    sys.setswitchinterval(0.004)
    with pytest.raises(RuntimeError), switch_interval(0.001):
        raise RuntimeError("station failed")
    assert sys.getswitchinterval() == pytest.approx(0.004)


@pytest.mark.parametrize("bad", [-0.001, math.nan, math.inf])
def test_refuses_a_negative_or_non_finite_interval(bad):
    sys.setswitchinterval(0.004)
    with pytest.raises(ValueError, match="switch interval"), switch_interval(bad):
        pass
    assert sys.getswitchinterval() == pytest.approx(0.004)
