"""Sensor geometry of Sec. 2: hand-computed values and a property-based round trip."""

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rig_runtime.config import Geometry
from rig_runtime.geometry import Pose, ideal_readings, measure, pose_from_carriers

GEO = Geometry(b0=0.1, l_L=1.0, l0=0.5, d0=0.2)
NAMES = ("b_f", "b_r", "s_fl", "s_fr", "s_rl", "s_rr", "fl", "fr", "rl", "rr")


def named(*values):
    """The readings by name, as ``devices.poll`` hands them to the geometry."""
    return dict(zip(NAMES, values))


def test_a_reading_is_taken_by_name_not_by_position():
    v = named(0.11, 0.10, 0.05, 0.03, 0.03, 0.05, 10.0, 9.0, 8.0, 8.5)
    shuffled = dict(reversed(list(v.items())))
    assert measure(shuffled, GEO) == measure(v, GEO)
    m = measure(v, GEO)
    assert m.carrier("front") == (m.y_f, m.psi_af, m.dw_f) and m.carrier("rear") == (m.y_r, m.psi_ar, m.dw_r)
    with pytest.raises(KeyError):
        measure({k: x for k, x in v.items() if k != "s_rr"}, GEO)


def test_hand_computed_values():
    m = measure(named(0.11, 0.10, 0.05, 0.03, 0.03, 0.05, 10.0, 9.0, 8.0, 8.5), GEO)
    # y_m = (0.11 + 0.10)/2 − 0.1 = 0.005
    assert m.y_m == pytest.approx(0.005, abs=1e-15)
    # ψ_m = atan(0.01/1.0) = 0.00999966668666…
    assert m.psi_m == pytest.approx(0.0099996666866652, rel=1e-12)
    # l0 sin ψ_m = 0.5 · 0.01/sqrt(1.0001) = 0.00499975001875
    assert m.y_f == pytest.approx(0.005 + 0.00499975001875, rel=1e-10)
    assert m.y_r == pytest.approx(0.005 - 0.00499975001875, abs=1e-12)
    # ψ_af = atan(0.02/0.2) = atan(0.1) = 0.0996686524911620
    assert m.psi_af == pytest.approx(0.0996686524911620, rel=1e-12)
    assert m.psi_ar == pytest.approx(-0.0996686524911620, rel=1e-12)
    assert m.psi_f == pytest.approx(m.psi_af + m.psi_m)
    assert m.psi_r == pytest.approx(m.psi_ar + m.psi_m)
    assert m.dw_f == 1.0 and m.dw_r == -0.5


def test_signs():
    """Nose left (ψ > 0) and displacement left (y > 0) as in docs/conventions.md."""
    r = ideal_readings(Pose(y_m=0.002, psi_m=0.01, psi_af=0.02, psi_ar=-0.03), GEO)
    assert r.b_f > r.b_r and r.s_fl > r.s_fr and r.s_rl < r.s_rr
    m = measure(named(r.b_f, r.b_r, r.s_fl, r.s_fr, r.s_rl, r.s_rr, 0, 0, 0, 0), GEO)
    assert m.y_m > 0 and m.psi_m > 0 and m.psi_af > 0 and m.psi_ar < 0 and m.y_f > m.y_r


angle = st.floats(min_value=-0.06, max_value=0.06, allow_nan=False)
lateral = st.floats(min_value=-0.01, max_value=0.01, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(y_f=lateral, y_r=lateral, psi_af=angle, psi_ar=angle,
       geo=st.builds(Geometry, b0=st.floats(0.02, 0.2), l_L=st.floats(0.3, 2.0),
                     l0=st.floats(0.1, 1.0), d0=st.floats(0.1, 0.5)))
def test_round_trip_pose_readings_geometry(y_f, y_r, psi_af, psi_ar, geo):
    """physical pose → ideal readings → geometry → the same pose, over the working range."""
    pose = pose_from_carriers(y_f, y_r, psi_af, psi_ar, geo)
    r = ideal_readings(pose, geo)
    m = measure(named(r.b_f, r.b_r, r.s_fl, r.s_fr, r.s_rl, r.s_rr, 0, 0, 0, 0), geo)
    assert m.y_f == pytest.approx(y_f, abs=1e-12)
    assert m.y_r == pytest.approx(y_r, abs=1e-12)
    assert m.psi_af == pytest.approx(psi_af, abs=1e-12)
    assert m.psi_ar == pytest.approx(psi_ar, abs=1e-12)
    assert m.psi_m == pytest.approx(pose.psi_m, abs=1e-12)
    assert m.y_m == pytest.approx(pose.y_m, abs=1e-12)


def test_paper_small_angle_form_differs_only_at_third_order():
    """The paper's ψ ≈ ratio (written tan/sin) agrees with atan to x³/3 at the 0.05 rad limit."""
    x = math.tan(0.05)
    m = measure(named(0.1 + x / 2, 0.1 - x / 2, 0.0, 0.0, 0.0, 0.0, 0, 0, 0, 0), GEO)
    assert m.psi_m == pytest.approx(0.05, abs=1e-15)
    assert abs(x - 0.05) == pytest.approx(0.05 ** 3 / 3, rel=0.02)


def test_unreachable_pose_is_refused():
    with pytest.raises(ValueError):
        pose_from_carriers(1.0, -1.0, 0, 0, GEO)
