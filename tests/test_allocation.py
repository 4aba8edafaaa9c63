"""The allocation stage: a carrier's differential command onto its available wheels within
each wheel's current limit (rig_runtime/allocation.py)."""

import math
from types import SimpleNamespace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rig_runtime.allocation import allocate, authority, split, wheel_currents

U = st.floats(-20.0, 20.0)


@given(u=U)
def test_both_wheels_share_the_command(u):
    left, right = allocate(u, True, True, 10.0)
    assert (left, right) == (0.5 * u, -0.5 * u) == split(u)
    assert left - right == pytest.approx(u)


@given(u=U, i_max=st.floats(0.5, 5.0))
def test_one_wheel_alone_makes_the_difference_within_its_limit(u, i_max):
    left, right = allocate(u, True, False, i_max)
    assert right == 0.0 and abs(left) <= i_max
    assert left - right == (u if abs(u) <= i_max else math.copysign(i_max, u))
    left, right = allocate(u, False, True, i_max)
    assert left == 0.0 and abs(right) <= i_max
    assert left - right == (u if abs(u) <= i_max else math.copysign(i_max, u))
    assert allocate(u, False, False, i_max) == (0.0, 0.0)


def test_each_wheel_within_its_limit_when_both_are_fit():
    assert allocate(10.0, True, True, 2.0) == (2.0, -2.0)
    assert authority(True, True, 2.0) == 4.0 and authority(False, True, 2.0) == 2.0
    assert authority(False, False, 2.0) == 0.0


def test_wheel_currents_give_a_lost_wheel_zero_and_the_other_the_command():
    lanes = [SimpleNamespace(wheels=("fl", "fr"), u=1.5), SimpleNamespace(wheels=("rl", "rr"), u=-1.0)]
    out = {}
    assert wheel_currents(lanes, out) == {"fl": 0.75, "fr": -0.75, "rl": -0.5, "rr": 0.5}
    assert wheel_currents(lanes, out, lost={"fl"}, i_max=4.0) == {"fl": 0.0, "fr": -1.5, "rl": -0.5, "rr": 0.5}
    assert wheel_currents(lanes, out, lost={"rl", "rr"}) == {"fl": 0.75, "fr": -0.75, "rl": 0.0, "rr": 0.0}
    assert wheel_currents(lanes[1:], out) == {"fl": 0.0, "fr": 0.0, "rl": -0.5, "rr": 0.5}
