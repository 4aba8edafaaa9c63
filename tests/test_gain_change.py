"""Live gain changes in the controllers (set_gain), checked by hand on round numbers:
h = 0.01 s, K_P_y = 2, K_I_y = 4, K_P_psi = 10, K_D_psi = 1, T_f_psi = 0.05."""

import copy

import pytest

from rig_runtime.config import Controller, PIPDGains
from rig_runtime.control import PController, PIPDController

CFG = Controller(h=0.01, pipd=PIPDGains(K_P_y=2.0, K_I_y=4.0, K_P_psi=10.0, K_D_psi=1.0, T_f_psi=0.05))


def started():
    c = PIPDController(CFG, u_max=100.0)
    c.start(0.001, 0.0, 0.0)       # e_y = 1 mm: x_I = (0 - 2 * 0.001) / 4 = -0.0005, psi_ref = 0
    c.step(0.001, 0.0, 0.0)        # dI = 0.005 * 0.002 = 1e-5: x_I = -0.00049, psi_ref = 0.002 - 0.00196 = 4e-5
    assert c.st.x_I == pytest.approx(-0.00049, abs=1e-15)
    assert c.st.psi_ref == pytest.approx(4e-5, abs=1e-15)
    return c


def test_K_P_y_shifts_the_integrator_so_psi_ref_does_not_jump():
    c = started()
    c.set_gain("K_P_y", 3.0)
    # x_I' = (4e-5 - 3 * 0.001) / 4 = -0.00074: 3 * 0.001 + 4 * x_I' is still 4e-5
    assert c.st.x_I == pytest.approx(-0.00074, abs=1e-15)
    assert c.gains()["K_P_y"] == 3.0
    c.step(0.001, 0.0, 0.0)
    # x_I = -0.00073, psi_ref = 0.003 - 0.00292 = 8e-5: as with the old gain (e_y unchanged);
    # without the shift it would have jumped to 0.003 - 0.00192 = 1.08e-3
    assert c.st.psi_ref == pytest.approx(8e-5, abs=1e-15)


def test_K_I_y_rescales_the_integrator():
    c = started()
    c.set_gain("K_I_y", 8.0)
    assert c.st.x_I == pytest.approx((4e-5 - 0.002) / 8.0, abs=1e-15)      # -0.000245
    c.step(0.001, 0.0, 0.0)
    # x_I = -0.000235, psi_ref = 0.002 - 8 * 0.000235 = 1.2e-4: the integral now grows twice as fast
    assert c.st.psi_ref == pytest.approx(1.2e-4, abs=1e-15)


def test_inner_PD_keeps_the_filter_state_and_steps_u_by_the_gain_difference():
    c = started()
    ref = copy.deepcopy(c)
    c.set_gain("K_P_psi", 15.0)
    assert c.st.de_psi == ref.st.de_psi and c._e_psi_prev == ref._e_psi_prev
    u_new, u_old = c.step(0.001, 0.0, 0.0), ref.step(0.001, 0.0, 0.0)
    assert c.st.de_psi == ref.st.de_psi          # filter untouched
    assert u_new - u_old == pytest.approx(5.0 * c.st.e_psi, abs=1e-15)   # (15 - 10) e_psi, e_psi = 8e-5
    c.set_gain("K_D_psi", 3.0)
    ref.set_gain("K_P_psi", 15.0)
    u_new, u_old = c.step(0.001, 0.0, 0.0), ref.step(0.001, 0.0, 0.0)
    assert u_new - u_old == pytest.approx(2.0 * c.st.de_psi, abs=1e-15)


def test_T_f_psi_changes_the_filter_coefficients_not_its_state():
    c = started()
    de0, e_prev = c.st.de_psi, c._e_psi_prev
    c.set_gain("T_f_psi", 0.1)
    assert c.st.de_psi == de0
    c.step(0.001, 0.0, 0.0)
    # Tustin of s/(0.1 s + 1) at h = 0.01: a = 0.19 / 0.21, b = 2 / 0.21
    assert c.st.de_psi == pytest.approx(0.19 / 0.21 * de0 + 2 / 0.21 * (c.st.e_psi - e_prev), rel=1e-12)


def test_before_start_only_the_gain_changes():
    c = PIPDController(CFG, u_max=100.0)
    c.set_gain("K_I_y", 8.0)
    c.set_gain("K_P_y", 3.0)
    assert c.st.x_I == 0.0 and c.gains()["K_I_y"] == 8.0
    c.start(0.001, 0.0, 0.0)
    assert c.st.x_I == pytest.approx(-3.0 * 0.001 / 8.0)


@pytest.mark.parametrize("name, value, text", [
    ("u_max", 5.0, "'u_max' is not a gain of the PI-PD law"),
    ("K_P", 5.0, "'K_P' is not a gain of the PI-PD law"),
    ("K_P_y", float("nan"), "not a finite positive number"),
    ("K_I_y", 0.0, "not a finite positive number"),
])
def test_not_a_gain_or_not_a_value_changes_nothing(name, value, text):
    c = started()
    before = (c.gains(), c.st.x_I, c.u_max)
    with pytest.raises(ValueError, match=text):
        c.set_gain(name, value)
    assert (c.gains(), c.st.x_I, c.u_max) == before


def test_P_law():
    c = PController(CFG, u_max=4.0)
    assert c.step(0.001, 0.0, 0.0) == pytest.approx(0.5)       # 500 A/m * 1 mm
    c.set_gain("K_P", 1000.0)
    assert c.gains() == {"K_P": 1000.0}
    assert c.step(0.001, 0.0, 0.0) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="not a gain of the P law"):
        c.set_gain("K_P_y", 1.0)
