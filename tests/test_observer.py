"""The observer: the filter step by hand, the Riccati design against its own equations, the
health statistic, the innovation rule, and the import boundary of the cycle's modules."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rig_runtime import config
from rig_runtime.app import observer_design as od
from rig_runtime.observer import Observer, ObserverDesign
from rig_runtime.safety import innovation


def _toy(window: int = 4) -> ObserverDesign:
    """A design with numbers easy to follow by hand."""
    return ObserverDesign(
        carrier="rear", A=(0.5, 1.0, 0.0, 0.0, 1.0, 0.1, 0.0, 0.0, 0.9), B=(0.0, 0.0, 2.0),
        E=(0.25, 0.0, 0.0), F=(0.0, 0.0, 0.0), c=(0.01, 0.0, 0.0), dw_row=(10.0, 2.0, 0.1),
        K_full=(0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.1), K_nolat=(0.0, 0.0, 0.5, 0.0, 0.0, 0.1),
        S_full=(4.0, 1.0, 0.25), S_nolat=(1.0, 0.25), window=window,
        lateral_lasers=("b_r", "b_f"), lateral_weights=(0.85, 0.15), yaw_lasers=("s_rl", "s_rr"),
        encoders=("rl", "rr"))


def test_first_step_starts_on_the_measurement():
    o = Observer(_toy())
    o.step(0.3, 0.2, 9.0, 1.0, 0.0, True)
    assert (o.y, o.psi, o.rate) == (0.3, 0.2, 0.0)


def test_step_by_hand():
    o = Observer(_toy())
    o.step(1.0, 0.5, 0.0, 0.0, 0.0, True)              # start: x = (1, 0.5, 0)
    o.step(2.0, 1.0, 20.0, 1.0, 0.4, True)
    # predict: y = 0.5·1 + 1·0.5 + 0.25·0.4 + 0.01 = 1.11; ψ = 0.5 + 0.1·0 = 0.5; ψ̇ = 0.9·0 + 2·1 = 2
    # innovations: lat 2 − 1.11 = 0.89; ψ 1 − 0.5 = 0.5; Δω 20 − (10·1.11 + 2·2 + 0.1·1) = 4.8
    assert o.nu_lat == pytest.approx(0.89)
    assert o.nu_psi == pytest.approx(0.5)
    assert o.nu_dw == pytest.approx(4.8)
    # correct: y = 1.11 + 0.5·0.89; ψ = 0.5 + 0.5·0.5; ψ̇ = 2 + 0.1·4.8
    assert o.y == pytest.approx(1.555)
    assert o.psi == pytest.approx(0.75)
    assert o.rate == pytest.approx(2.48)
    assert o.lat_used == 1.0


def test_a_lateral_laser_not_fit_is_not_used():
    o = Observer(_toy())
    o.step(1.0, 0.5, 0.0, 0.0, 0.0, True)
    o.step(1e6, 1.0, 20.0, 1.0, 0.4, False)           # a wild lateral value, not fit: ignored
    # K_nolat: y += 0·ν_ψ + 0·ν_Δω; ψ += 0.5·ν_ψ; ψ̇ += 0.1·ν_Δω
    assert o.y == pytest.approx(1.11)
    assert o.psi == pytest.approx(0.75)
    assert o.rate == pytest.approx(2.48)
    assert math.isnan(o.nu_lat) and o.lat_used == 0.0


def test_window_statistic_by_hand():
    o = Observer(_toy(window=4))
    o.step(0.0, 0.0, 0.0, 0.0, 0.0, True)
    for _ in range(3):
        o.step(0.0, 0.0, 0.0, 0.0, 0.0, True)
        assert o.T_lat == 0.0 and not o.window_full
    # a steady state at x = 0 with c = 0.01: every lateral innovation is −0.01 → z = −0.01/2
    o2 = Observer(dataclasses.replace(_toy(window=4), K_full=(0.0,) * 9))
    o2.step(0.0, 0.0, 0.0, 0.0, 0.0, True)
    ys = []
    for _ in range(4):
        o2.step(0.0, 0.0, 0.0, 0.0, 0.0, True)
        ys.append(o2.nu_lat)
    assert o2.window_full
    z = [n / 2.0 for n in ys]
    assert o2.T_lat == pytest.approx(sum(z) ** 2 / 4)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-5, 5), min_size=1, max_size=30), st.integers(1, 8))
def test_window_statistic_is_the_last_window(zs, N):
    """T is (Σ of the last N normalised innovations)² / N, however many came before."""
    o = Observer(dataclasses.replace(_toy(window=N), S_full=(1.0, 1.0, 1.0)))
    for z in zs:
        o._window(z, 0.0, 0.0)
    if len(zs) >= N:
        assert o.T_lat == pytest.approx(sum(zs[-N:]) ** 2 / N, abs=1e-9)
    else:
        assert not o.window_full


@pytest.fixture(scope="module")
def cfg():
    return config.load()


def _rear_model(cfg):
    """The rear carrier's held model as the design builds it, built here from its parts:
    Ad, Qd (zero-order hold of the continuous model) and C (y, ψ, Δω by relation (4))."""
    o = cfg.observer
    A, Bc = od.continuous_model(cfg, "rear", cfg.plant.D_min if o.D is None else o.D)
    Ad, _, Qd = od.discretise(A, Bc, np.diag([o.q_y ** 2, 0, o.q_psi_acc ** 2]), cfg.controller.h)
    gy, gr, _ = od.dw_row(cfg)
    return Ad, Qd, np.array([[1.0, 0, 0], [0, 1, 0], [gy, 0, gr]])


def test_design_solves_its_riccati_equation(cfg):
    """K and S of the design satisfy the steady-state Kalman relations of the held model."""
    d = od.design(cfg, "rear")
    o = cfg.observer
    Ad, Qd, C = _rear_model(cfg)
    K = np.array(d.K_full).reshape(3, 3)
    S = np.diag(d.S_full)
    assert np.allclose(np.array(d.A).reshape(3, 3), Ad)
    # innovation variances are at least the sensor noise, and the filter is stable
    w = od._lateral_weights(cfg, "rear")[1]
    n = o.noise
    assert S[0, 0] > (w[0] ** 2 + w[1] ** 2) * n.lateral_laser_m ** 2
    assert S[2, 2] > 2 * n.encoder_rad_s ** 2
    closed = (np.eye(3) - K @ C) @ Ad
    assert max(abs(np.linalg.eigvals(closed))) < 1.0
    assert max(abs(np.linalg.eigvals((np.eye(3) - np.array(d.K_nolat).reshape(3, 2) @ C[1:]) @ Ad))) < 1.0


def test_design_matches_relation_4(cfg):
    """∂Δω/∂y = Γvb/(2r0²), ∂Δω/∂ψ̇ = b/(2r0) (b = 0.3, r0 = 0.075: 2.0)."""
    gy, gr, gu = od.dw_row(cfg)
    p = cfg.plant
    assert gr == pytest.approx(2.0)
    assert gy == pytest.approx(p.Gamma * p.v * p.b / (2 * p.r0 ** 2))
    assert gu == pytest.approx(p.v * p.k_tau / (p.r0 ** 2 * p.c11))


def test_lateral_force_enters_as_the_plants_creep_velocity(cfg):
    """The held model's force column: y moves by ≈ h·|v|/(2 c̄11) per N over one period (the
    plant's ẏ += |v| F_y/(2 c22), c22 ≈ c̄11; exact to the small decay −a y over h), ψ not at
    all; the carrier's F/T sensors are those of its two wheels."""
    d = od.design(cfg, "rear")
    p, h = cfg.plant, cfg.controller.h
    assert d.F[0] == pytest.approx(h * abs(p.v) / (2 * p.c11), rel=1e-2)
    assert d.F[0] > 0 and d.F[1] == 0.0 and d.F[2] == 0.0
    assert d.ft_sensors == ("ft_rl", "ft_rr")
    o = Observer(dataclasses.replace(_toy(), F=(0.5, 0.0, 0.0)))
    o.step(1.0, 0.5, 0.0, 0.0, 0.0, True)
    o.step(2.0, 1.0, 20.0, 1.0, 0.4, True, f_lat=0.2)       # prediction of y: 1.11 + 0.5·0.2
    assert o.nu_lat == pytest.approx(0.79)


def test_lateral_weights_of_the_geometry(cfg):
    """y_r = y_m − l0 sin ψ_m: ∂y_r/∂b_r = 1/2 + l0/l_L, ∂y_r/∂b_f = 1/2 − l0/l_L."""
    lasers, w = od._lateral_weights(cfg, "rear")
    k = cfg.geometry.l0 / cfg.geometry.l_L
    assert lasers == ("b_r", "b_f") and w == pytest.approx((0.5 + k, 0.5 - k))
    assert od._lateral_weights(cfg, "front")[0] == ("b_f", "b_r")


def test_no_observer_without_its_section(cfg):
    assert od.designs(dataclasses.replace(cfg, observer=None, degraded=config.Degraded())) == {}


def _stats(T_lat=0.0, T_psi=0.0, T_dw=0.0, full=True, lat_used=1.0):
    o = Observer(_toy())
    o.T_lat, o.T_psi, o.T_dw = T_lat, T_psi, T_dw
    o._n = o._N if full else 0
    o.lat_used = lat_used
    return o


def test_innovation_rule_names_the_sensor(cfg):
    lim = dataclasses.replace(cfg.limits, innovation_chi2=30.0)
    assert innovation(_stats(), lim) is None
    assert innovation(_stats(T_lat=100.0, full=False), lim) is None        # window not full yet
    f = innovation(_stats(T_lat=31.0), lim)
    assert (f.device, f.check, f.value, f.limit) == ("b_r/b_f", "innovation", 31.0, 30.0)
    f = innovation(_stats(T_psi=31.0, T_lat=99.0), lim)
    assert f.device == "s_rl/s_rr" and "cannot tell" in f.message
    f = innovation(_stats(T_dw=31.0), lim)
    assert f.device == "b_r|rl/rr" and "cannot tell the lateral laser from the encoders" in f.message
    assert innovation(_stats(T_lat=1e9), dataclasses.replace(lim, innovation_chi2=None)) is None
    # the latest estimate did not use the lateral lasers (isolated, unfit): no lateral evidence,
    # the window they left behind is not judged; Δω still is
    assert innovation(_stats(T_lat=99.0, lat_used=0.0), lim) is None
    assert innovation(_stats(T_lat=99.0, T_dw=31.0, lat_used=0.0), lim).device == "b_r|rl/rr"


def test_the_cycle_modules_do_not_import_scipy():
    """The observer and the lanes run in the loop's process: no scipy there (the design
    module, which uses it, is the application's)."""
    code = ("import sys, rig_runtime.observer, rig_runtime.lanes; "
            "print(any(m == 'scipy' or m.startswith('scipy.') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    import ast
    import rig_runtime.loop as loop_mod
    tree = ast.parse(open(loop_mod.__file__).read())
    names = {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert not any("observer_design" in n or "scipy" in n for n in names)


def test_outage_sigma_grows_to_the_no_lateral_filters_steady_state(cfg):
    """The design's σ_ŷ(k): the full filter's steady-state corrected σ at k = 0, never
    falling, levelling off at the corrected σ of the yaw-and-Δω filter's own Riccati solution
    (an independent check: the fixed no-lateral gain is that filter's optimal one)."""
    from scipy.linalg import solve_discrete_are
    d = od.design(cfg, "rear")
    o = cfg.observer
    Ad, Qd, C = _rear_model(cfg)
    w = od._lateral_weights(cfg, "rear")[1]
    n = o.noise
    R = np.diag([(w[0] ** 2 + w[1] ** 2) * n.lateral_laser_m ** 2, 2 * n.yaw_laser_m ** 2 / cfg.geometry.d0 ** 2,
                 2 * n.encoder_rad_s ** 2])
    corrected = []
    for Cm, Rm in ((C, R), (C[1:], R[1:, 1:])):
        s2 = 1e6
        P = solve_discrete_are(Ad.T, Cm.T, Qd * s2, Rm * s2) / s2
        K = P @ Cm.T @ np.linalg.inv(Cm @ P @ Cm.T + Rm)
        corrected.append(math.sqrt(((np.eye(3) - K @ Cm) @ P)[0, 0]))
    tab = np.array(d.sigma_y_outage)
    assert tab[0] == pytest.approx(corrected[0], rel=1e-6)
    assert tab[-1] == pytest.approx(corrected[1], rel=1e-4)
    assert np.all(np.diff(tab) >= -1e-15 * tab[-1])
    assert 1 < len(tab) <= math.ceil(cfg.degraded.max_s / cfg.controller.h) + 2


def test_observer_reports_sigma_after_the_outage_it_counts():
    o = Observer(dataclasses.replace(_toy(), sigma_y_outage=(1.0, 2.0, 3.0)))
    assert o.sigma_y == 1.0
    o.step(0.0, 0.0, 0.0, 0.0, 0.0, True)                  # start
    for k, want in ((1, 2.0), (2, 3.0), (3, 3.0), (4, 3.0)):      # the last value holds
        o.step(0.0, 0.0, 0.0, 0.0, 0.0, False)
        assert (o.outage, o.sigma_y) == (k, want)
    o.step(0.0, 0.0, 0.0, 0.0, 0.0, True)                  # a lateral update ends the outage
    assert (o.outage, o.sigma_y) == (0, 1.0)
    assert math.isnan(Observer(_toy()).sigma_y)             # no table: no σ


def test_degraded_covariance_rule(cfg):
    from rig_runtime.safety import degraded_covariance
    o = Observer(dataclasses.replace(_toy(), sigma_y_outage=(1e-6, 2e-4)))
    deg = dataclasses.replace(cfg.degraded, sigma_y_max=1e-4)
    assert degraded_covariance(o, deg) is None
    o.outage, o.sigma_y = 1, 2e-4
    f = degraded_covariance(o, deg)
    assert (f.device, f.check, f.value, f.limit) == ("b_r/b_f", "sigma_y", 2e-4, 1e-4)
    assert "rear carrier" in f.message and "degraded.sigma_y_max" in f.message


def test_the_rules_follow_the_observers_lead(cfg):
    """An observer that names the measurement whose fault explains its innovations best (the
    joint filter's views: ``lead``) is judged on that one only; "" (the other carrier's, or not
    yet confirmed) raises nothing on this carrier; without a lead the rules' order decides."""
    lim = dataclasses.replace(cfg.limits, innovation_chi2=30.0)

    def led(lead, **kw):
        o = _stats(**kw)
        o.lead = lead
        return o
    assert innovation(led("lat", T_psi=40.0, T_lat=99.0), lim).device == "b_r/b_f"
    assert innovation(led("psi", T_psi=40.0, T_lat=99.0), lim).device == "s_rl/s_rr"
    assert innovation(led("dw", T_psi=40.0, T_dw=35.0), lim).device == "b_r|rl/rr"
    assert innovation(led("", T_psi=40.0, T_lat=99.0, T_dw=50.0), lim) is None
    assert innovation(led(None, T_psi=40.0, T_lat=99.0), lim).device == "s_rl/s_rr"
