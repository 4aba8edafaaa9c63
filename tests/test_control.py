"""The discrete PI-PD law against its continuous counterpart, saturation, anti-windup,
bumpless start; the P baseline and the open-loop input generators."""

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from rig_runtime import analysis
from rig_runtime.control import (PController, PIPDController, Sinusoid, StepSequence, ZeroInput,
                                 make_controller)


def _zoh(A, B, h):
    n = A.shape[0]
    M = expm(np.block([[A, B[:, None]], [np.zeros((1, n + 1))]]) * h)
    return M[:n, :n], M[:n, n]


def _simulate_discrete(cfg, ctrl, y_ref, t_end):
    A, B = analysis.model_10(cfg)
    Ad, Bd = _zoh(A, B, cfg.controller.h)
    x = np.zeros(3)
    ctrl.start(0.0, 0.0, 0.0)   # at rest before the step (else the bumpless start absorbs it)
    ys, us = [], []
    for k in range(int(round(t_end / cfg.controller.h)) + 1):
        u = ctrl.step(y_ref, x[0], x[1])
        ys.append(x[0]); us.append(u)
        x = Ad @ x + Bd * u
    return np.array(ys), np.array(us)


def _simulate_continuous(cfg, y_ref, t):
    """Same law in continuous time: D term on e_ψ through s/(T s + 1), exact integrator."""
    A, B = analysis.model_10(cfg)
    g = cfg.controller.pipd
    T = g.T_f_psi

    def f(_, s):
        x, x_I, x_f = s[:3], s[3], s[4]
        e_y = y_ref - x[0]
        e_psi = g.K_P_y * e_y + g.K_I_y * x_I - x[1]
        u = g.K_P_psi * e_psi + g.K_D_psi * (e_psi - x_f / T) / T
        return np.r_[A @ x + B * u, e_y, -x_f / T + e_psi]

    sol = solve_ivp(f, (t[0], t[-1]), np.zeros(5), t_eval=t, method="Radau", rtol=1e-10, atol=1e-13)
    return sol.y[0]


def test_discrete_law_reproduces_continuous_step_response(cfg):
    """Tolerance: |y_discrete − y_continuous| ≤ 1 % of the step over 15 s (measured 0.1 %)."""
    step = 1e-3
    t = np.arange(0, 15 + 1e-9, cfg.controller.h)
    y_d, u_d = _simulate_discrete(cfg, PIPDController(cfg.controller, cfg.limits.u_max), step, 15.0)
    y_c = _simulate_continuous(cfg, step, t)
    err = np.max(np.abs(y_d[: len(t)] - y_c))
    assert err <= 0.01 * step, err
    assert abs(y_d[-1] - step) < 0.01 * step     # the integrator removes the steady-state error
    assert np.max(np.abs(u_d)) < cfg.limits.u_max  # no saturation in this small step


def test_discrete_loop_eigenvalues_match_continuous(cfg):
    """The sampled loop's eigenvalues (ln z / h) are close to the continuous loop of the same law."""
    ev = analysis.sampled_closed_loop(cfg)
    slow = sorted(ev, key=lambda e: -e.real)[:2]
    assert all(e.real < 0 for e in ev)
    assert all(-1.3 < e.real < -0.9 for e in slow)   # the (10)-model's slow pair ≈ −1.13 ± 0.74j


def test_saturation_and_anti_windup(cfg):
    ctrl = PIPDController(cfg.controller, cfg.limits.u_max)
    y_big = 0.05  # 50 mm: far beyond what 4 A can do quickly
    ys, us = _simulate_discrete(cfg, ctrl, y_big, 0.5)
    assert np.max(np.abs(us)) <= cfg.limits.u_max
    assert np.isclose(np.max(us), cfg.limits.u_max)
    # while saturated high with a positive error, x_I must not grow
    c2 = PIPDController(cfg.controller, cfg.limits.u_max)
    c2.step(0.0, 0.0, 0.0)
    x_I = c2.st.x_I
    for _ in range(50):
        u = c2.step(y_big, 0.0, -0.04)
        assert u == cfg.limits.u_max
        assert c2.st.x_I <= x_I + 1e-15
        x_I = c2.st.x_I


def test_anti_windup_limits_overshoot(cfg):
    """With conditional integration the saturated step overshoots less than with a
    winding-up integrator (u_max huge inside, clipped outside)."""
    step = 0.003   # needs ≈ 0.87 A in steady state: reachable under a 1 A clip, but saturates first
    A, B = analysis.model_10(cfg)
    Ad, Bd = _zoh(A, B, cfg.controller.h)

    def run(ctrl, clip):
        x = np.zeros(3); peak = 0.0
        ctrl.start(0.0, 0.0, 0.0)
        for _ in range(int(20 / cfg.controller.h)):
            u = max(-clip, min(clip, ctrl.step(step, x[0], x[1])))
            x = Ad @ x + Bd * u
            peak = max(peak, x[0])
        return peak, x[0]

    p_aw, end_aw = run(PIPDController(cfg.controller, 1.0), 1.0)
    p_wu, end_wu = run(PIPDController(cfg.controller, 1e9), 1.0)
    assert p_aw < p_wu
    assert end_aw == pytest.approx(step, rel=0.02)


def test_limit_feedback_undoes_integration(cfg):
    c = PIPDController(cfg.controller, cfg.limits.u_max)
    c.step(0.0, 0.0, 0.0)
    before = c.st.x_I
    u = c.step(0.001, 0.0, 0.0)
    assert c.st.x_I > before
    c.limit_feedback(u * 0.5)      # safety applied less than asked
    assert c.st.x_I == pytest.approx(before)


def test_bumpless_start_and_reset(cfg):
    c = PIPDController(cfg.controller, cfg.limits.u_max)
    u0 = c.step(0.002, 0.002, 0.007)   # start at rest on a non-zero yaw angle
    assert abs(u0) < 1e-12
    u1 = c.step(0.002, 0.002, 0.007)
    assert abs(u1) < 1e-12
    c.reset()
    assert c.st.x_I == 0.0 and not c._started


def test_p_baseline(cfg):
    c = make_controller(cfg.controller.__class__(h=0.005, law="p", pipd=cfg.controller.pipd, K_P=500.0),
                        cfg.limits.u_max)
    assert isinstance(c, PController)
    assert c.step(0.0002, 0.0, 0.0) == pytest.approx(0.1)     # 500 A/m · 0.2 mm
    assert c.step(0.02, 0.0, 0.0) == cfg.limits.u_max          # saturated


def test_open_loop_generators():
    s = StepSequence([(0, 0.0), (20, 0.7), (40, -0.7), (60, 0.0)])
    assert [s(t) for t in (0, 19.99, 20, 39, 40, 61)] == [0.0, 0.0, 0.7, 0.7, -0.7, 0.0]
    sin = Sinusoid(0.7, 4.8)
    assert sin(1 / 4.8e-3 / 4) == pytest.approx(0.7)          # a quarter period: the peak
    assert sin(1 / 4.8e-3 / 2) == pytest.approx(0.0, abs=1e-12)
    assert ZeroInput()(12.3) == 0.0
    assert math.isclose(Sinusoid(1.0, 2.4, bias=0.1, t0=10)(5), 0.1)


# --------------------------------------------------------------------------- the description
def _step_description(L, x, w):
    """One step of a DiscreteLaw by its matrices: (x⁺, out)."""
    xn = [sum(a * xi for a, xi in zip(L.A[r], x)) + sum(b * wi for b, wi in zip(L.B[r], w))
          for r in range(len(L.states))]
    out = [sum(c * xi for c, xi in zip(L.C[r], x)) + sum(d * wi for d, wi in zip(L.D[r], w))
           for r in range(len(L.outputs))]
    return xn, out


@pytest.mark.parametrize("g", [1.0, 0.5, -2.0])
def test_the_description_is_the_law_the_runtime_steps(cfg, g):
    """The PI-PD's DiscreteLaw, stepped by its matrices, gives the runtime controller's output and
    its logged states (x_I, e_y, e_ψ, ê_ψ) at every step of a random input sequence (no limits
    reached), at the schedule's factor g."""
    from rig_runtime.control import PIPDLaw
    ctrl = PIPDController(cfg.controller, u_max=1e9)
    ctrl.set_gain_factor(g)
    ctrl.start(0.0, 0.0, 0.0)
    L = PIPDLaw.of(cfg.controller.pipd, cfg.controller.h).discrete(g)
    assert L.inputs == ("y_ref", "y", "psi") and L.states == ("x_I", "e_y", "e_psi", "de_psi")
    assert L.outputs == ("u",) and L.g == g and L.h == cfg.controller.h
    rng = np.random.default_rng(1)
    x = [ctrl.st.x_I, ctrl.st.e_y, ctrl.st.e_psi, ctrl.st.de_psi]
    for _ in range(200):
        w = rng.normal(0, 1e-3, 3).tolist()
        u = ctrl.step(*w)
        x, (u_d,) = _step_description(L, x, w)
        st = ctrl.st
        assert u == pytest.approx(u_d, rel=1e-9, abs=1e-12)
        assert [st.x_I, st.e_y, st.e_psi, st.de_psi] == pytest.approx(x, rel=1e-9, abs=1e-15)


def test_the_p_description_is_the_p_law(cfg):
    from rig_runtime.control import PLaw
    L = PLaw(500.0, 0.005).discrete(2.0)
    assert L.states == () and L.D == ((1000.0, -1000.0, 0.0),)
    c = PController(cfg.controller.__class__(h=0.005, law="p", pipd=cfg.controller.pipd, K_P=500.0), 1e9)
    c.set_gain_factor(2.0)
    assert c.step(1e-3, 4e-4, 0.3) == pytest.approx(_step_description(L, [], [1e-3, 4e-4, 0.3])[1][0], rel=1e-15)


def test_the_continuous_description_is_the_paper_law(cfg):
    """PI-PD as designed (11)–(14): its transfer function y → u equals the Tustin law's at low
    frequency (the two describe one law)."""
    from rig_runtime.control import PIPDLaw
    law = PIPDLaw.of(cfg.controller.pipd, cfg.controller.h)
    Lc, Ld = law.continuous(1.0), law.discrete(1.0)
    h = cfg.controller.h
    for f in (0.05, 0.5, 2.0):
        s = 2j * math.pi * f
        z = np.exp(s * h)
        def tf(L, lam):
            A, B, C, D = (np.array(m, dtype=float).reshape(len(r), -1) if len(r) else np.zeros((0, 3))
                          for m, r in ((L.A, L.states), (L.B, L.states), (L.C, L.outputs), (L.D, L.outputs)))
            n = len(L.states)
            return (C @ np.linalg.solve(lam * np.eye(n) - A, B) + D)[0]
        gc, gd = tf(Lc, s), tf(Ld, z)
        assert gd[1] == pytest.approx(gc[1], rel=0.02)     # the y channel
        assert gd[2] == pytest.approx(gc[2], rel=0.02)     # the ψ channel


# --------------------------------------------------------------------------- law decoupled
class _Pair:
    def __init__(self):
        self.ys = {"front": 0.0, "rear": 0.0}

    def y(self, c):
        return self.ys[c]


def _decoupled(cfg, **kw):
    import dataclasses
    from rig_runtime.config import DecoupledGains
    g = DecoupledGains(K_P_y=6.0, K_I_y=3.0, K_P_psi=40.0, K_D_psi=5.0, T_f_psi=0.034144, b_y=0.25, K_x_y=9.0,
                       K_I_psi=60.0, T_x_y=0.1, K_t_y=4.0)
    g = dataclasses.replace(g, **kw)
    return dataclasses.replace(cfg.controller, law="decoupled", decoupled=g), g


@pytest.mark.parametrize("gf", [0.8, -0.8])
@pytest.mark.parametrize("carrier", ["front", "rear"])
def test_the_decoupled_description_is_the_law_the_runtime_steps(cfg, carrier, gf):
    """Law decoupled: its DiscreteLaw (inputs y_ref, y, ψ, y.front, y.rear) stepped by its matrices
    gives the runtime controller's output, the other carrier's y read through the cross-lane stage."""
    from rig_runtime.control import DecoupledController, law_of
    c, _ = _decoupled(cfg)
    ctrl = make_controller(c, 1e9, None, carrier)
    assert isinstance(ctrl, DecoupledController)
    pair = _Pair()
    ctrl.couple(pair)
    ctrl.set_gain_factor(gf)
    ctrl.start(0.0, 0.0, 0.0)
    L = law_of(c, carrier).discrete(gf)
    assert L.inputs == ("y_ref", "y", "psi", "y.front", "y.rear") and L.law == "decoupled"
    assert L.states == ("x_I", "e_y", "e_psi", "de_psi", "x_I_psi", "d_y", "dd_y")
    rng = np.random.default_rng(2)
    x = [ctrl.st.x_I, ctrl.st.e_y, ctrl.st.e_psi, ctrl.st.de_psi, ctrl.x_I_psi, ctrl.d_y, ctrl.dd_y]
    for _ in range(200):
        y_ref, y, psi, y_other = rng.normal(0, 1e-3, 4).tolist()
        pair.ys[carrier] = y
        pair.ys["rear" if carrier == "front" else "front"] = y_other
        u = ctrl.step(y_ref, y, psi)
        x, (u_d,) = _step_description(L, x, [y_ref, y, psi, pair.ys["front"], pair.ys["rear"]])
        assert u == pytest.approx(u_d, rel=1e-9, abs=1e-12)
        assert [ctrl.x_I_psi, ctrl.d_y, ctrl.dd_y] == pytest.approx(x[4:], rel=1e-9, abs=1e-15)


def test_decoupled_law_weights_the_setpoint_and_decouples(cfg):
    """A reference step moves ψ_ref by K_P,y b_y Δy_ref (not K_P,y Δy_ref); a difference
    y_f − y_r lowers ψ_ref by K_x,y (y_f − y_r)."""
    c, g = _decoupled(cfg, T_x_y=0.0, K_t_y=0.0)
    ctrl = make_controller(c, 1e9, None, "rear")
    pair = _Pair()
    ctrl.couple(pair)
    ctrl.start(0.0, 0.0, 0.0)
    ctrl.step(1e-3, 0.0, 0.0)
    h = cfg.controller.h
    assert ctrl.st.psi_ref == pytest.approx(g.K_P_y * g.b_y * 1e-3 + g.K_I_y * 0.5 * h * 1e-3, rel=1e-12)
    c2 = make_controller(c, 1e9, None, "rear")
    c2.couple(pair)
    c2.start(0.0, 0.0, 0.0)
    pair.ys["front"] = 2e-4
    c2.step(0.0, 0.0, 0.0)
    assert c2.st.psi_ref == pytest.approx(-g.K_x_y * 2e-4, rel=1e-12)


@pytest.mark.parametrize("gf, trailing", [(1.25, "rear"), (-1.25, "front")])
def test_the_trailing_carrier_follows_the_leading_one(cfg, gf, trailing):
    """K_t,y acts on the trailing carrier only (the rear where g > 0, the front where g < 0):
    ψ_ref raised by K_t,y |g| (y_f − y_r); the leading carrier's ψ_ref has the decoupling alone."""
    c, g = _decoupled(cfg, T_x_y=0.0, b_y=1.0, K_I_y=0.0)
    pair = _Pair()
    psi_ref = {}
    for carrier in ("front", "rear"):
        ctrl = make_controller(c, 1e9, None, carrier)
        ctrl.couple(pair)
        ctrl.set_gain_factor(gf)
        pair.ys.update(front=0.0, rear=0.0)
        ctrl.start(0.0, 0.0, 0.0)
        pair.ys.update(front=2e-4, rear=0.0)
        ctrl.step(0.0, 0.0, 0.0)
        psi_ref[carrier] = ctrl.st.psi_ref
    leading = "front" if trailing == "rear" else "rear"
    assert psi_ref[leading] == pytest.approx(-g.K_x_y * 2e-4, rel=1e-12)
    assert psi_ref[trailing] == pytest.approx((-g.K_x_y + g.K_t_y * abs(gf)) * 2e-4, rel=1e-12)


@pytest.mark.parametrize("name,value", [("K_P_y", 4.0), ("K_I_y", 5.0), ("b_y", 0.6), ("K_x_y", 7.0),
                                        ("K_I_psi", 30.0), ("T_x_y", 0.3), ("K_t_y", 2.0)])
def test_decoupled_gain_change_keeps_psi_ref(cfg, name, value):
    """`rig ctl set` on the outer gains, the setpoint weight or the decoupling gain: x_I is
    re-seeded so that ψ_ref (with the feed term) is what the last step made it."""
    c, _ = _decoupled(cfg)
    ctrl = make_controller(c, 1e9, None, "front")
    pair = _Pair()
    ctrl.couple(pair)
    ctrl.start(0.0, 0.0, 0.0)
    pair.ys.update(front=3e-4, rear=-1e-4)
    for _ in range(20):
        ctrl.step(1e-3, 3e-4, 1e-4)
    law = ctrl.law
    i_term = law.K_I_psi * ctrl.x_I_psi
    before = law.psi_ref(ctrl.g, ctrl.st.e_y, ctrl.st.x_I) - law.feed(ctrl.g, *ctrl._fed)
    ctrl.set_gain(name, value)
    law = ctrl.law
    assert getattr(law, name) == value
    after = law.psi_ref(ctrl.g, ctrl.st.e_y, ctrl.st.x_I) - law.feed(ctrl.g, *ctrl._fed)
    assert after == pytest.approx(before, rel=1e-12)
    assert law.K_I_psi * ctrl.x_I_psi == pytest.approx(i_term, rel=1e-12)      # the yaw integral's share of u
    with pytest.raises(ValueError):
        ctrl.set_gain("b_y", 1.5)


def test_lanes_give_a_decoupled_law_both_carriers():
    """The one cross-lane stage: each decoupled controller reads the lanes' y by carrier name."""
    import dataclasses
    from rig_runtime import config
    from rig_runtime.lanes import make_lanes
    vcfg = config.load(config.CONFIG_DIR / "vehicle.yaml")
    c, _ = _decoupled(vcfg)
    lanes = make_lanes(dataclasses.replace(vcfg, controller=c), lambda t: 0.0)
    by = {l.carrier: l for l in lanes}
    by["front"].y, by["rear"].y = 1e-3, -2e-3
    for l in lanes:
        assert l.controller.pair.y("front") == 1e-3 and l.controller.pair.y("rear") == -2e-3


def test_rig_ctl_set_judges_the_decoupled_law_with_the_same_gate():
    """On configs/vehicle.yaml (law decoupled) `rig ctl set` takes the law's own gains within their
    bounds, refuses one outside them, and the stability gate analyses the decoupled law: a yaw
    loop too soft for the outer gains is refused naming controller.decoupled."""
    import dataclasses
    from rig_runtime import analysis, config, tuning
    vcfg = config.load(config.CONFIG_DIR / "vehicle.yaml")
    assert vcfg.controller.law == "decoupled"
    assert tuning.check(vcfg, "K_x_y", 4.0).new == 4.0
    with pytest.raises(tuning.TuningError, match="outside its bounds"):
        tuning.check(vcfg, "b_y", 0.9)
    soft = dataclasses.replace(vcfg.controller.decoupled, K_P_psi=1.0, K_D_psi=0.1, K_I_y=60.0)
    bad = dataclasses.replace(vcfg, controller=dataclasses.replace(vcfg.controller, decoupled=soft))
    with pytest.raises(analysis.UnstableLoopError, match="controller.decoupled"):
        analysis.stability_gate(bad)


# ------------------------------------------------------------------ the damping schedule (D_sched)
def _yaw(cfg):
    from rig_runtime.damping import YawDamping
    return YawDamping.of(cfg.plant.carrier("rear"))


def test_the_law_knows_the_damping_the_plant_has(cfg):
    """D̂ of (7) from the law's own commands (damping.InputDamping) is the simulated plant's D at
    the end of every period (the same filter and the same function), through D_min, the linear
    part of (7) and D_max, and when a limit downstream applied another current (``correct``)."""
    from rig_runtime.damping import InputDamping
    from sim_backend.plant import Plant
    h = cfg.controller.h
    P = cfg.plant
    pl = Plant(P)
    est = InputDamping(_yaw(cfg), h)
    rng = np.random.default_rng(4)
    u, seen = 0.0, set()
    for k in range(600):
        # moves of 1 A (D_min), of 1e-7 A (|u̇| below c_udot_max: between), and none (back to D_max)
        u += (1.0 if k % 150 == 0 else 0.0) + (rng.normal(0, 1e-7) if 300 <= k < 450 else 0.0)
        est.hold(u)
        if k % 150 == 10:                       # a limit downstream applied less (limit_feedback)
            u = 0.5 * u
            est.correct(u)
        pl.step(h, 0.0, u)
        assert est.now == pytest.approx(pl.D_r, rel=1e-9)
        seen.add("min" if est.now == P.D_min else "max" if est.now > P.D_max - 1e-3 else "between")
    assert seen == {"min", "max", "between"}


def test_the_damping_schedule_keeps_the_law_at_d_min_and_raises_the_yaw_gain_above(cfg):
    """At D̂ = D_min (and without the schedule) the law is the PI-PD bit for bit; above, K_P,ψ is
    raised so that the yaw loop's slow pole (first-order estimate) stays, and κ keeps its static gain."""
    import dataclasses
    from rig_runtime.control import PIPDLaw
    m = _yaw(cfg)
    plain = PIPDLaw.of(cfg.controller.pipd, cfg.controller.h)
    law = PIPDLaw.of(dataclasses.replace(cfg.controller.pipd, D_sched=1.0), cfg.controller.h, m)
    assert law.yaw_gains(m.D_min) == (law.K_P_psi, 1.0) == plain.yaw_gains(m.D_max)
    assert law.discrete(1.0, m.D_min) == plain.discrete(1.0)
    kp, kappa = law.yaw_gains(m.D_max)
    kk, kd = m.K * law.K_P_psi, m.K * m.omega0 ** 2 * law.K_D_psi
    pole = lambda D, k: m.omega0 ** 2 * (1 + m.K * k) / (2 * D * m.omega0 + kd)      # noqa: E731
    assert pole(m.D_max, kp) == pytest.approx(pole(m.D_min, law.K_P_psi), rel=1e-12)
    assert m.K * kp * kappa / (1 + m.K * kp) == pytest.approx(kk / (1 + kk), rel=1e-12)
    twice = dataclasses.replace(law, D_sched=2.0).yaw_gains(m.D_max)[0]
    assert twice - law.K_P_psi == pytest.approx(2 * (kp - law.K_P_psi), rel=1e-12)


def test_a_change_of_the_damping_estimate_does_not_kick_the_current(cfg):
    """The law starts at D̂ = D_min. A still current for one cycle (a blip of (7)) leaves the gains
    alone; still for DAMPING_PERSIST_S, the gains follow D̂ (D_max) — without a jump of u; then ψ
    moves, the D_max gains move u by σ K_P,ψ Δψ, D̂ drops to D_min with the moved current and the
    P term is kept across the change (x_I re-seeded as on a resume): no kick from the schedule."""
    import dataclasses
    from rig_runtime.control import DAMPING_PERSIST_S
    c = dataclasses.replace(cfg.controller, pipd=dataclasses.replace(cfg.controller.pipd, D_sched=2.0))
    ctrl = make_controller(c, 1e9, None, "rear", _yaw(cfg))
    m = _yaw(cfg)
    ctrl.start(0.0, 0.0, 2e-3)
    u0 = ctrl.step(0.0, 0.0, 2e-3)
    assert ctrl.D_hat == m.D_min and u0 == pytest.approx(0.0, abs=1e-12)
    u1 = ctrl.step(0.0, 0.0, 2e-3)                 # one still cycle: D̂ = D_max, the gains stay
    assert ctrl.D_hat == m.D_min and u1 == pytest.approx(u0, abs=1e-9)
    for _ in range(round(DAMPING_PERSIST_S / cfg.controller.h)):
        u1 = ctrl.step(0.0, 0.0, 2e-3)             # still on: the gains follow D̂, u does not jump
    assert ctrl.D_hat == m.D_max and u1 == pytest.approx(u0, abs=1e-9)
    u2 = ctrl.step(0.0, 0.0, 2e-3 + 1e-6)          # ψ moved: the D_max gains move u (σ K_P,ψ Δψ)
    kp = ctrl.law.yaw_gains(m.D_max)[0]
    assert ctrl.D_hat == m.D_max and u2 - u1 == pytest.approx(-kp * 1e-6, rel=0.05)
    u3 = ctrl.step(0.0, 0.0, 2e-3 + 1e-6)          # the current moved: D̂ = D_min, the P term kept
    assert ctrl.D_hat == m.D_min
    assert u3 == pytest.approx(u2, abs=1e-2 * abs(u2 - u1))   # (the D term decays on; a kick would be ~σ × it)
