"""The plant with both carriers on the rollers, per-carrier values and a time-varying speed
(issue 18): the paper's set-up unchanged, the coupled lateral update for a_f != a_r, the
integrator against the stiff reference with per-carrier values and a speed reversal, the
mirrored identification set-ups of the front carrier, the speed in the wheel encoders."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import quad, solve_ivp
from scipy.linalg import expm

from rig_runtime.config import CarrierPlant, load
from sim_backend.plant import STATE_NAMES, LiftedCarrier, Plant, _exp_ints, _hermite_weights_coupled
from tests import plant_golden
from tests.plant_reference import Scenario, reference, simulate

H = 0.005
IDX = {n: i for i, n in enumerate(STATE_NAMES)}


@pytest.fixture(scope="module")
def P():
    return load().plant


def front_differs(P, **kw):
    """Both carriers in contact, the front's values a few to 30 % off the rear's."""
    own = dict(delta0=P.delta0 * 1.2, l0=P.l0 * 0.9, K=P.K * 1.1, omega0=P.omega0 * 0.85,
               psi_off=1.0e-3, D_min=P.D_min * 1.3, r0=P.r0 * 1.02, c11=P.c11 * 0.8, k_tau=P.k_tau * 1.1,
               y_off=2e-4)
    own.update(kw)
    return replace(P, front_contact=True, front=CarrierPlant(**own))


def rel_err(x, xr, name):
    i = IDX[name]
    return np.max(np.abs(x[:, i] - xr[:, i])) / np.ptp(xr[:, i])


# --------------------------------------------------------------------------- unchanged set-ups
def _same(new, ref, name):
    """Equal to 1e-12 of each column's largest value (measured: 1e-17 absolute in Δω_r, from
    the last bit of the lateral Hermite weights, now computed by _exp_ints; all else identical)."""
    scale = np.maximum(np.max(np.abs(ref), axis=0), 1e-300)
    assert np.all(np.abs(new - ref) <= 1e-12 * scale), name


def test_the_old_set_ups_are_unchanged():
    """tests/data/plant_golden.json was written by the code before this change: the paper's
    set-up (front lifted, v = +1, hysteresis, dynamic wheels, fixed sub-steps), the lifted rear
    and both carriers in contact with equal values give the same numbers (to 1e-12 of each
    signal's size; the lifted rear and both carriers in contact bit for bit). At v = -1 the
    input's creep term of (4) differs: |v| k_tau/(r0^2 c11) now, v k_tau/(...) before."""
    old = json.loads(plant_golden.PATH.read_text())
    P = load().plant
    for name, kw, reset, seconds in plant_golden.cases():
        new = np.array(plant_golden.run(kw, reset, seconds))
        ref = np.array(old[name])
        if name in ("rear_lifted", "both_contact", "both_contact_dynamic_linear"):
            assert np.array_equal(new, ref), name
        if name != "paper_reverse":
            _same(new, ref, name)
            continue
        cols = {"dw_r": 12, "omega_rl": 15, "omega_rr": 16}
        keep = [j for j in range(ref.shape[1]) if j not in cols.values()]
        _same(new[:, keep], ref[:, keep], name)
        U = plant_golden.inputs(int(round(seconds / H)))
        k = [min(int(round(t / H)), len(U)) - 1 for t in ref[1:, 0]]
        du_r = np.concatenate(([0.0], U[k, 1]))
        vk = P.k_tau / (P.r0 ** 2 * P.c11)
        np.testing.assert_allclose(new[:, cols["dw_r"]] - ref[:, cols["dw_r"]], 2 * vk * du_r, rtol=1e-9, atol=1e-15)


def test_per_carrier_values_reach_each_carrier(P):
    Pv = front_differs(P)
    pl = Plant(Pv)
    Pf, Pr = Pv.carrier("front"), Pv.carrier("rear")
    assert pl.a_f == pytest.approx(Pf.c_y * Pv.v / (2 * Pf.l0), rel=1e-15)
    assert pl.a_r == pytest.approx(Pr.c_y * Pv.v / (2 * Pr.l0), rel=1e-15) and pl.a_r == pl.a_lat
    assert pl.a_f / pl.a_r > 1.05                             # front: shorter l0 (c̄_y falls a little with δ0)
    assert pl._front.K == Pf.K and pl._front.w0 == Pf.omega0 and pl._rear.K == Pr.K
    pl.reset(y_f=1e-3, y_r=-1e-3, psi_rate_f=0.02, psi_rate_r=0.01, du_f=0.5, du_r=-0.5)
    for name, Pc, y, p, du, dw in (("front", Pf, 1e-3, 0.02, 0.5, pl.dw_f), ("rear", Pr, -1e-3, 0.01, -0.5, pl.dw_r)):
        expect = (Pc.Gamma * Pv.v * Pc.b / (2 * Pc.r0 ** 2) * y + Pc.b / (2 * Pc.r0) * p
                  + abs(Pv.v) * Pc.k_tau / (Pc.r0 ** 2 * Pc.c11) * du)
        assert dw == pytest.approx(expect, rel=1e-13), name
    assert pl.omega_fl == pytest.approx(Pv.v / Pf.r0 + pl.dw_f / 2, rel=1e-15)
    assert pl.omega_rr == pytest.approx(Pv.v / Pr.r0 - pl.dw_r / 2, rel=1e-15)
    fx = pl.ft_loads()
    assert fx["fl"][0] == pytest.approx(Pf.k_tau * 0.5 / (2 * Pf.r0)) and fx["rl"][0] == pytest.approx(Pr.k_tau * -0.5 / (2 * Pr.r0))


# --------------------------------------------------------------------------- the coupled lateral update
def _hermite_g(h):
    g = lambda t: 1e-3 * (0.3 - 2 * t + 5 * t * t - 40 * t ** 3)
    dg = lambda t: 1e-3 * (-2 + 10 * t - 120 * t * t)
    return g, (g(0.0), dg(0.0), g(h), dg(h))


@pytest.mark.parametrize("a_f,a_r,h", [(1.746, 1.746, 0.05), (2.4, 1.746, 0.05), (-2.4, -1.746, 0.05),
                                       (1.746 * (1 + 1e-9), 1.746, 0.05), (3.0, 0.5, 0.5), (0.5, 3.0, 1.0),
                                       (40.0, 1.0, 0.1), (0.0, 0.0, 0.05)])
def test_coupled_weights_are_exact_for_cubics_with_unequal_carriers(a_f, a_r, h):
    M = np.array([[a_f, -a_f], [a_r, -a_r]])
    phi, W = _hermite_weights_coupled(a_f, h, a_r)
    np.testing.assert_allclose(phi, expm(M * h), rtol=1e-11, atol=1e-15)   # expm itself: ~1e-12 at mu h = 3.9
    g, df = _hermite_g(h)
    Y0 = np.array([1e-3, -2e-3])
    sol = solve_ivp(lambda t, y: M @ y + [g(t), -0.5 * g(t)], (0.0, h), Y0, method="Radau",
                    rtol=1e-13, atol=1e-17)
    G = [np.array([d, -0.5 * d]) for d in df]
    got = np.array(phi) @ Y0 + sum(np.array(Wk) @ Gk for Wk, Gk in zip(W, G))
    np.testing.assert_allclose(got, sol.y[:, -1], rtol=1e-9, atol=1e-15)


def test_coupled_weights_equal_carriers_match_the_jordan_form_and_are_continuous():
    """mu = a_f - a_r -> 0: the general weights tend to the Jordan-block ones (no cancellation)."""
    phi0, W0 = _hermite_weights_coupled(1.746, H)
    for eps in (1e-12, 1e-8, 1e-4):
        phi, W = _hermite_weights_coupled(1.746 + eps, H, 1.746)
        np.testing.assert_allclose(phi, phi0, rtol=0, atol=2 * eps * H)
        np.testing.assert_allclose(W, W0, rtol=0, atol=2 * eps * H ** 2)


@pytest.mark.parametrize("x", [0.0, 1e-6, -3e-3, 0.4999, 0.5, -0.5, -0.4999, 2.0, -7.0, 30.0])
def test_exponential_integrals(x):
    J, K = _exp_ints(x)
    for j in range(4):
        Jq = quad(lambda s: math.exp(-x * (1 - s)) * s ** j, 0.0, 1.0, epsabs=0, epsrel=1e-13)[0]
        assert J[j] == pytest.approx(Jq, rel=1e-12)
        Kq = quad(lambda s: (math.expm1(-x * (1 - s)) / (-x) if x else (1 - s)) * s ** j, 0.0, 1.0,
                  epsabs=0, epsrel=1e-13)[0]
        assert K[j] == pytest.approx(Kq, rel=1e-11 if abs(x) < 20 else 1e-9)


def test_jordan_block_equal_carriers_and_two_poles_otherwise(P):
    """Both carriers in contact, linear yaw held: the lateral step map (y_f, y_r) has the double
    eigenvalue 1 = e^{0 h} with a non-trivial Jordan block for equal carriers (the frame yaw
    psi_m integrates), and the eigenvalues 1, e^{(a_f - a_r) h} for unequal ones; the same
    for v = -1 (a changes sign with v)."""
    for v in (1.0, -1.0):
        for Pp in (replace(P, front_contact=True, v=v, bouc_wen=None), front_differs(replace(P, v=v), K=P.K)):
            pl = Plant(Pp)
            x0 = pl.state_vector()

            def step_map(x):
                pl.set_state_vector(x, t=0.0)
                pl.step(H, 0.0, 0.0)
                return pl.state_vector()
            idx = [IDX["y_f"], IDX["y_r"]]
            Jd = np.zeros((2, 2))
            for j, k in enumerate(idx):
                dx = np.zeros_like(x0)
                dx[k] = 1e-6
                Jd[:, j] = (step_map(x0 + dx)[idx] - step_map(x0 - dx)[idx]) / 2e-6
            a_f, a_r = pl.a_f, pl.a_r
            np.testing.assert_allclose(Jd, expm(np.array([[a_f, -a_f], [a_r, -a_r]]) * H), rtol=1e-8, atol=1e-12)
            ev = np.sort(np.linalg.eigvals(Jd).real)
            np.testing.assert_allclose(ev, np.sort([1.0, math.exp((a_f - a_r) * H)]), rtol=0, atol=1e-9)
            if Pp.front is None:
                assert a_f == a_r and np.linalg.matrix_rank(Jd - np.eye(2), tol=1e-6 * H) == 1   # Jordan block


def test_the_frame_yaw_integrates_with_equal_carriers(P):
    """Equal carriers, v = 1, no input: the carriers' yaw offsets differ by 1 mrad, so psi_m =
    (y_f - y_r)/(2 l0) grows linearly, c̄_y v dpsi/(2 l0), and the mean y quadratically."""
    Pp = replace(P, front_contact=True, bouc_wen=None)
    pl = Plant(Pp)
    du_f = 1e-3 / P.K                                        # holds psi_af at psi_off + 1 mrad
    pl.reset(du_f=du_f, y_f=0.0, y_r=0.0)
    psi_m = []
    for k in range(400):
        pl.step(H, du_f, 0.0)
        psi_m.append((pl.y_f - pl.y_r) / (2 * P.l0))
    assert pl.psi_af - pl.psi_ar == pytest.approx(1e-3, rel=1e-12)
    rate = np.diff(psi_m) / H
    assert rate[-1] == pytest.approx(P.c_y * P.v * 1e-3 / (2 * P.l0), rel=1e-6)
    assert rate[100] == pytest.approx(rate[-1], rel=1e-6)       # constant: an integrator, not a pole


# --------------------------------------------------------------------------- vs the stiff reference
def _mixed_inputs(n):
    t = np.arange(n) * H
    U = np.zeros((n, 6))
    U[:, 0] = 0.4 * (t >= 0.2) - 0.9 * (t >= 1.1)
    U[:, 1] = -0.6 * (t >= 0.1) + 0.8 * (t >= 1.5)
    U[(t >= 0.6) & (t < 0.65), 3] = 200.0     # rail-irregularity pulse, rear
    U[(t >= 0.8) & (t < 0.82), 4] = 2.0       # yaw-moment pulse, front
    U[t >= 1.0, 2] = 50.0                     # side wind, front
    return t, U


@pytest.mark.parametrize("hyst", [False, True])
def test_per_carrier_values_and_a_speed_reversal_match_radau(P, hyst):
    """Both carriers in contact with different values, both driven, pulses and side wind, the
    speed ramping from +1 through 0 to -1 m/s and back up (held per step): the integrator
    against Radau (rtol 1e-10). Measured errors: docs/vehicle.md."""
    Pp = front_differs(P if hyst else replace(P, bouc_wen=None))
    n = 500
    t, U = _mixed_inputs(n)
    V = np.interp(t, [0.0, 0.3, 1.3, 1.8, 2.5], [1.0, 1.0, -1.0, -1.0, -0.2])
    sc = Scenario("reversal", Pp, H, U, speed=V)
    x, xr = simulate(sc), reference(sc)
    for name in ("y_f", "y_r", "psi_af", "psi_ar"):
        assert rel_err(x, xr, name) <= 2e-5, name
    for name in ("psi_rate_f", "psi_rate_r"):
        assert rel_err(x, xr, name) <= 3e-4, name


def test_mirrored_front_only_in_contact_matches_radau(P):
    Pp = replace(front_differs(P, K=P.K), front_contact=True, rear_contact=False, v=-1.0, bouc_wen=None)
    n = 400
    _, U = _mixed_inputs(n)
    sc = Scenario("mirrored", Pp, H, U)
    x, xr = simulate(sc), reference(sc)
    assert rel_err(x, xr, "y_f") <= 1e-5 and rel_err(x, xr, "psi_af") <= 1e-5
    assert np.all(x[:, IDX["y_r"]] == 0.0) and np.all(xr[:, IDX["y_r"]] == 0.0)


# --------------------------------------------------------------------------- the speed
def test_set_speed_recomputes_what_scales_with_v(P):
    Pv = front_differs(P)
    pl = Plant(Pv)
    a_f, a_r = pl.a_f, pl.a_r
    pl.set_speed(-0.5)
    assert pl.v == -0.5 and pl.a_f == pytest.approx(-0.5 * a_f) and pl.a_r == pytest.approx(-0.5 * a_r)
    # a fresh plant at that speed has the same constants
    fresh = Plant(replace(Pv, v=-0.5))
    for k in ("_cyv_f", "_cyv_r", "_off_f", "_off_r", "_fy_f", "_fy_r", "_gvb_f", "_gvb_r", "_vk_f", "_vk_r",
              "_w_nom_f", "_w_nom_r"):
        assert getattr(pl, k) == getattr(fresh, k), k
    assert pl._vk_f > 0 and pl._fy_r > 0                     # creep terms go with |v|
    pl.step(H, 0.0, 0.0)
    fresh.step(H, 0.0, 0.0)
    assert pl._lat2 == fresh._lat2                           # the lateral weights follow v
    pl.set_speed(Pv.v)                                       # back: the weights of the configured speed
    again = Plant(Pv)
    again.step(H, 0.0, 0.0)
    assert pl._lat2 == again._lat2 and pl.a_f == a_f


def test_at_standstill_the_lateral_input_has_no_effect(P):
    """v = 0: y' = c̄_y v psi = 0 whatever the yaw does (not controllable), the wheels turn
    only with the yaw rate (Δω = b/(2 r0) psi_dot) and a lateral force does not move y."""
    pl = Plant(front_differs(P))
    pl.reset(y_f=1e-3, y_r=-5e-4)
    pl.set_speed(0.0)
    for k in range(200):
        pl.step(H, 1.0, -1.0, F_y_f=100.0, F_y_r=-50.0)
        assert pl.y_f == 1e-3 and pl.y_r == -5e-4
        assert pl.dw_r == pytest.approx(P.b / (2 * P.r0) * pl.psi_rate_r, rel=1e-14, abs=1e-18)
    assert pl.omega_fl + pl.omega_fr == 0.0 and pl.omega_rl + pl.omega_rr == 0.0
    assert abs(pl.psi_ar - P.psi_off) > 3e-3                # the yaw moved


def test_dynamic_wheels_keep_their_fixed_positive_speed(P):
    pl = Plant(P, wheel_dynamics="dynamic")
    pl.set_speed(P.v)                                        # unchanged: fine
    with pytest.raises(ValueError, match="fixed v"):
        pl.set_speed(0.5)
    with pytest.raises(ValueError):
        Plant(replace(P, v=0.0), wheel_dynamics="dynamic")


def test_state_snapshot_carries_the_speed(P):
    a = Plant(front_differs(P))
    a.set_speed(-0.7)
    for _ in range(50):
        a.step(H, 0.3, -0.2)
    b = Plant(front_differs(P))
    b.set_state(a.state)
    assert b.v == -0.7
    for _ in range(50):
        a.step(H, 0.1, 0.4)
        b.step(H, 0.1, 0.4)
    assert a.state == b.state


# --------------------------------------------------------------------------- mirrored set-ups
def test_mirrored_set_up_is_the_paper_set_up_mirrored(P):
    """Front in contact, rear out of contact, v = -1, front values = the paper's rear values:
    y_f = -y_r, psi_af = psi_ar and Δω_f = Δω_r of the paper's set-up at v = +1 with the same
    input on the other carrier; the rear stays at y_r = 0, Δω_r = 0."""
    paper = Plant(P)
    mirr = Plant(replace(P, front_contact=True, rear_contact=False, v=-1.0))
    assert mirr.y_f == pytest.approx(-paper.y_r, rel=1e-15)
    t, U = _mixed_inputs(1000)
    for u in U:
        du_f, du_r, Ff, Fr, Mf, Mr = u
        paper.step(H, 0.0, du_r, 0.0, Fr, 0.0, Mr)
        mirr.step(H, du_r, 0.0, -Fr, 0.0, Mr, 0.0)
        assert mirr.y_f == pytest.approx(-paper.y_r, rel=1e-12, abs=1e-18)
        assert mirr.psi_af == paper.psi_ar and mirr.z_f == paper.z_r
        assert mirr.dw_f == pytest.approx(paper.dw_r, rel=1e-12, abs=1e-15)
        assert mirr.y_r == 0.0 and mirr.dw_r == 0.0
    assert mirr.omega_fl == pytest.approx(-paper.omega_rr, rel=1e-12)   # turning backwards
    ft = mirr.ft_readings()
    assert ft["rl"] == ft["rr"] == (0.0,) * 6                           # rear: no contact, no load


def test_lifted_front_free_response_mirrors_the_lifted_rear(P):
    lc = LiftedCarrier(D=0.28, psi_off=1.7e-3)
    with pytest.raises(ValueError, match="rear_contact"):
        Plant(P, front_lifted=lc)                              # the rear still rolls: refused
    pl = Plant(replace(P, rear_contact=False), front_lifted=lc)
    rear = Plant(P, rear_lifted=lc)
    pl.reset(psi_af=0.01, y_f=1e-3)
    rear.reset(psi_ar=0.01, y_r=1e-3)
    for _ in range(400):
        pl.step(H, 0.0, 0.0)
        rear.step(H, 0.0, 0.0)
        assert pl.psi_af == rear.psi_ar
    assert pl.y_f == 1e-3 and pl.dw_f == 0.0 and pl.z_f == 0.0 and pl.y_r == 0.0
    assert pl.ft_readings()["fl"][2] == 0.0 and pl.ft_loads()["fl"][2] == 0.0


# --------------------------------------------------------------------------- the simulated rig
def _rig_cfg(plant=None, **sim):
    import dataclasses
    cfg = load()
    return dataclasses.replace(cfg, plant=plant or cfg.plant, sim={**(cfg.sim or {}), **sim})


def test_simulated_rig_applies_the_speed_profile_and_the_encoders_show_it():
    """v = +1 for 0.1 s, then a ramp to -1 over 0.4 s (through standstill): the plant's speed
    is the profile at each step's start (ZOH) and the wheel speeds are v/r0 ± Δω/2."""
    from rig_runtime.scenario import Scenario as Sc, SpeedPoint
    from sim_backend.rig import SimulatedRig
    cfg = _rig_cfg(replace(load().plant, front_contact=True, front=CarrierPlant(r0=0.08)), encoder_noise_rad_s=0.0)
    sc = Sc(name="reversal", duration_s=1.0, speed=(SpeedPoint(t=0.0, v=1.0), SpeedPoint(t=0.1, v=-1.0, ramp_s=0.4)))
    with SimulatedRig(cfg, sc, seed=0) as sim:
        assert sim.plant.v == 1.0
        sim.start_scenario(sim.t)
        seen = []
        for k in range(120):
            tau = sim.t - sim.t_run0
            sim.step(H, [0.3, -0.3, 0.2, -0.2])
            assert sim.plant.v == sc.speed_profile(cfg.plant.v)(tau)
            seen.append(sim.plant.v)
            p = sim.plant
            assert p.omega_fl == pytest.approx(p.v / 0.08 + p.dw_f / 2, rel=1e-14, abs=1e-14)
            assert p.omega_rr == pytest.approx(p.v / 0.075 - p.dw_r / 2, rel=1e-14, abs=1e-14)
        assert min(seen) == -1.0 and min(map(abs, seen)) < 0.02 and seen[0] == 1.0
        sim.set_wheel_speeds()
        om = [sim.drives.drives[w].omega for w in ("fl", "fr", "rl", "rr")]
        assert om == [p.omega_fl, p.omega_fr, p.omega_rl, p.omega_rr]
        assert sum(om) < -4 * 0.99 / 0.08


def test_simulated_rig_refuses_what_it_cannot_simulate():
    from rig_runtime.errors import ConfigError
    from rig_runtime.scenario import Scenario as Sc, SpeedPoint
    from sim_backend.rig import SimulatedRig
    P = load().plant
    rev = Sc(name="rev", duration_s=1.0, speed=(SpeedPoint(t=0.0, v=1.0), SpeedPoint(t=0.5, v=-1.0)))
    with pytest.raises(ConfigError, match="wheel_dynamics"):
        SimulatedRig(_rig_cfg(wheel_dynamics="dynamic"), rev, seed=0)
    lift_front = Sc(name="lift-front", duration_s=1.0, lifted_carrier="front")
    with pytest.raises(ConfigError, match="plant.rear_contact"):
        SimulatedRig(_rig_cfg(), lift_front, seed=0)
    lift_rear = Sc(name="lift-rear", duration_s=1.0, lifted_carrier="rear")
    with pytest.raises(ConfigError, match="plant.front_contact"):
        SimulatedRig(_rig_cfg(replace(P, front_contact=True)), lift_rear, seed=0)


def test_simulated_rig_mirrored_set_ups():
    """``plant: {front_contact: true, rear_contact: false}`` at v = -1: the front rolls alone,
    at its rest position; with ``lifted_carrier: front`` (and the front lifted) the front swings
    from ``initial_psi_mrad`` with the contact-free damping."""
    from rig_runtime.scenario import OpenLoop, Scenario as Sc
    from sim_backend.rig import SimulatedRig
    P = replace(load().plant, front_contact=True, rear_contact=False, v=-1.0)
    steps = Sc(name="mirrored-steps", duration_s=1.0, open_loop=OpenLoop(carrier="front", steps=((0.0, 0.5),)))
    with SimulatedRig(_rig_cfg(P), steps, seed=0) as sim:
        p = sim.plant
        assert p.front_contact and not p.rear_contact
        assert p.y_f == pytest.approx(-2 * P.l0 * P.psi_off, rel=1e-12) and p.y_r == 0.0   # mirror of y_r
        sim.start_scenario(sim.t)
        for _ in range(100):
            sim.step(H, [0.25, -0.25, 0.0, 0.0])
        assert p.y_r == 0.0 and p.dw_r == 0.0 and p.dw_f != 0.0 and p.psi_af > P.psi_off
    free = Sc(name="front-free", duration_s=1.0, lifted_carrier="front", initial_psi_mrad=8.0)
    with SimulatedRig(_rig_cfg(P, lifted_D=0.3, lifted_psi_off=1e-3), free, seed=0) as sim:
        p = sim.plant
        assert p.front_lifted is not None and not p.front_contact and p.psi_af == 8e-3
        sim.start_scenario(sim.t)
        low = []
        for _ in range(60):
            sim.step(H, [0.0, 0.0, 0.0, 0.0])
            low.append(p.psi_af)
        assert p.dw_f == 0.0 and p.z_f == 0.0
        # swung through its offset (1 mrad): the undershoot of D = 0.3, 0.37 of the 7 mrad start
        assert min(low) == pytest.approx(1e-3 - 7e-3 * math.exp(-math.pi * 0.3 / math.sqrt(1 - 0.09)), rel=0.02)
        assert p.ft_readings()["fl"][2] == 0.0


# --------------------------------------------------------------------------- configs/vehicle-plant.yaml
def _vehicle_cfg(tmp_path):
    """configs/vehicle.yaml: configs/vehicle-plant.yaml with the rest of the simulated vehicle."""
    from rig_runtime.config import CONFIG_DIR
    return load(CONFIG_DIR / "vehicle.yaml")


def test_vehicle_plant_config_has_both_carriers_in_contact_and_a_front_of_its_own(tmp_path):
    cfg = _vehicle_cfg(tmp_path)
    P = cfg.plant
    assert P.front_contact and P.rear_contact and P.rear is None
    Pf, Pr = P.carrier("front"), P.carrier("rear")
    assert Pr == replace(load().plant, front_contact=True)           # the rear: the paper's carrier
    for k in ("delta0", "l0", "K", "omega0", "D_min"):
        assert 0.02 <= abs(getattr(Pf, k) / getattr(Pr, k) - 1) <= 0.06, k   # "a few % off"
    pl = Plant(P)
    assert pl.a_f - pl.a_r == pytest.approx(0.050, abs=0.002)               # the docs' numbers
    assert cfg.sim == load().sim                                            # as sim.yaml's sim: section


def test_open_loop_vehicle_drifts_as_the_coupled_model_says(tmp_path):
    """A lockstep dry run with configs/vehicle-plant.yaml, zero input on both carriers: the
    log's sim_truth group holds both carriers' true y and psi, the yaw stays at rest and the
    lateral pair drifts exactly as (2a)/(2b) solved in closed form (the matrix exponential of
    [[M, g], [0, 0]]): psi_m = (y_f - y_r)/(2 l0) is not at rest, y_f grows quadratically."""
    import h5py
    from rig_runtime.app.dryrun import run_lockstep
    from rig_runtime.scenario import OpenLoop, Scenario as Sc
    cfg = _vehicle_cfg(tmp_path)
    sc = Sc(name="vehicle-drift", duration_s=1.5, open_loop=OpenLoop(carrier="both", steps=((0.0, 0.0),)))
    log = tmp_path / "drift.h5"
    summary, code = run_lockstep(cfg, sc, log)
    assert code == 0 and summary["max_abs_current_A"] == 0.0
    with h5py.File(log) as f:
        g = f["sim_truth"]
        t, yf, yr, pf, pr = (g[k][:] for k in ("t", "y_f", "y_r", "psi_af", "psi_ar"))
    Pf, Pr = cfg.plant.carrier("front"), cfg.plant.carrier("rear")
    assert np.all(pf == Pf.psi_off) and np.all(pr == Pr.psi_off)             # yaw at rest, z = psi
    pl = Plant(cfg.plant)
    a_f, a_r = pl.a_f, pl.a_r
    A = np.array([[a_f, -a_f, Pf.c_y * Pf.psi_off], [a_r, -a_r, Pr.c_y * Pr.psi_off], [0.0, 0.0, 0.0]])
    x0 = np.array([yf[0], yr[0], 1.0])
    pred = np.array([expm(A * (tk - t[0])) @ x0 for tk in t])
    np.testing.assert_allclose(yf, pred[:, 0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(yr, pred[:, 1], rtol=0, atol=1e-12)
    assert abs(yf[-1] - yf[0]) > 5e-4 and np.ptp(yf - yr) > 1e-4                # psi_m moves: > 0.2 mrad
    rate = np.diff(yf) / np.diff(t)
    assert rate[-1] > 1.5 * rate[0] > 0                                       # speeding up: not a stable pole
