"""The paper's experiments in lockstep against the simulated plant (Sec. 3, 4.3.4, 5.2.4,
5.2.5): closed-loop tracking and robustness, open-loop step and hysteresis behaviour."""

import numpy as np
import pytest

from .e2e import run

pytestmark = pytest.mark.slow


def _window(r, t0, t1):
    t = r.col("t_run")
    return (t >= t0) & (t < t1)


def test_step_sequence(tmp_path, cfg):
    """Sec. 5.2.4 ("negligible steady-state error"): every step tracked with a steady-state
    error < 2 % of the step or, for the 0.1 mm steps where 2 % is 2 µm, < 5 µm (the
    hysteresis' slow tail can outlast their 20 s window: 3.7 µm on one of them at seed 0
    since the drives are enabled at ARM); current within ±4 A, no faults, rise/settling
    times of a few seconds."""
    r = run(tmp_path, "step-sequence")
    s = r.summary
    assert s["final_state"] == "IDLE" and s["faults"] == []
    assert s["max_abs_current_A"] <= cfg.limits.u_max
    assert all(abs(i) <= cfg.limits.u_max for _, _, i in r.wire)
    steps = s["steps"]
    assert len(steps) == 72
    for st in steps:
        size = abs(st["to_mm"] - st["from_mm"])
        assert abs(st["steady_state_error_mm"]) < max(0.02 * size, 0.005), st
    rise = np.median([st["rise_time_s"] for st in steps])
    settle = np.median([st["settling_time_s"] for st in steps if st["settling_time_s"] is not None])
    assert 0.5 < rise < 5.0 and 2.0 < settle < 15.0


def test_robustness(tmp_path):
    """Sec. 5.2.5: back to y_ref = 0 within a few seconds after each pulse; the constant
    side force's offset is removed by the integrator."""
    r = run(tmp_path, "robustness")
    assert r.summary["final_state"] == "IDLE" and r.summary["faults"] == []
    y = r.col("y_r")
    for tp in (10.0, 15.0, 20.0):
        peak = np.max(np.abs(y[_window(r, tp, tp + 2.0)]))
        assert peak > 0.05e-3                                   # the pulse did move the carrier
        assert np.max(np.abs(y[_window(r, tp + 4.0, tp + 5.0)])) < 0.25 * peak
    for t0 in (25.0, 45.0):
        peak = np.max(np.abs(y[_window(r, t0, t0 + 5.0)]))
        assert peak > 0.05e-3
        assert np.max(np.abs(y[_window(r, t0 + 8.0, t0 + 10.0)])) < 0.2 * peak   # offset removed under load


def _loop_width(t, u, psi, t0, period):
    """Vertical width of the ψ–u loop at u = 0 over one period starting at t0 (its first
    quarter, the way in from the previous state, is left out): ψ on the falling minus
    the rising branch."""
    s = (t > t0 + period / 4) & (t < t0 + period)
    uu, pp = u[s], psi[s]
    du = np.gradient(uu)
    near = np.abs(uu) < 0.05
    return float(np.mean(pp[(du < 0) & near]) - np.mean(pp[(du > 0) & near]))


P1, P2 = 1 / 4.8e-3, 1 / 2.4e-3


def test_sine_hysteresis(tmp_path, cfg):
    """Sec. 4.3.4 / Fig. 9: with hysteresis the ψ–Δu loop barely changes between 4.8 and
    2.4 mHz (full protocol path); the linear model with the high damping (as the paper
    compares, plant alone) has a loop that shrinks with the frequency."""
    import dataclasses
    import math
    from sim_backend.plant import Plant
    r = run(tmp_path, "sine-hysteresis")
    assert r.summary["final_state"] == "IDLE", r.summary["faults"]
    t, u, psi = r.col("t_run"), r.col("rear_u_lim"), r.col("psi_ar")
    h1, h2 = _loop_width(t, u, psi, 0.0, P1), _loop_width(t, u, psi, P1, P2)
    assert h1 > 1e-3 and h2 > 1e-3
    assert 0.8 < h2 / h1 < 1.25, (h1, h2)            # rate independent

    p = cfg.plant
    lin = Plant(dataclasses.replace(p, bouc_wen=None, D_min=p.D_max))
    lin.reset()
    h = cfg.controller.h
    n = int(round((P1 + P2) / h))
    tt, uu, pp = np.empty(n), np.empty(n), np.empty(n)
    for k in range(n):
        tk = k * h
        uk = 0.7 * math.sin(2 * math.pi * (4.8e-3 * tk if tk < P1 else 2.4e-3 * (tk - P1)))
        lin.step(h, 0.0, uk)
        tt[k], uu[k], pp[k] = tk + h, uk, lin.psi_ar
    l1, l2 = _loop_width(tt, uu, pp, 0.0, P1), _loop_width(tt, uu, pp, P1, P2)
    assert l2 / l1 < 0.7, (l1, l2)                   # rate dependent
    assert h2 > 2 * l2


def test_open_loop_steps(tmp_path):
    """Sec. 3 / Fig. 8: a fast, low-damped jump right after a step, then a slow,
    high-damped tail."""
    r = run(tmp_path, "open-loop-steps")
    assert r.summary["final_state"] == "IDLE"
    t, psi = r.col("t_run"), r.col("psi_ar")
    for t0, t_next in ((20.0, 80.0), (80.0, 140.0), (200.0, 260.0)):
        before = np.mean(psi[(t > t0 - 1.0) & (t < t0)])
        jump = np.mean(psi[(t > t0 + 0.3) & (t < t0 + 0.4)]) - before
        total = np.mean(psi[(t > t_next - 1.0) & (t < t_next)]) - before
        assert 0.15 < jump / total < 0.85, (t0, jump, total)   # a jump, then more to come
        tail = np.mean(psi[(t > t0 + 20) & (t < t0 + 21)]) - before
        assert abs(tail) < abs(total)                          # still creeping after 20 s
