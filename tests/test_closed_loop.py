"""The paper's experiments in lockstep against the simulated plant (Sec. 3, 4.3.4, 5.2.4,
5.2.5): closed-loop tracking and robustness, open-loop step and hysteresis behaviour."""

import numpy as np
import pytest

from .e2e import assert_steps_tracked, run

pytestmark = pytest.mark.slow


def _window(r, t0, t1):
    t = r.col("t_run")
    return (t >= t0) & (t < t1)


STEP_SEQUENCE_LEVELS_MM = (-3.5, -0.7, -0.1, 0.1, 0.3, 3.5)


def part_of_step_sequence(levels_mm):
    """The shipped step-sequence scenario with only the steps to ``levels_mm`` and back, in
    the shipped order, each level held as long as in the shipped file (its timing shifted
    so that the kept steps follow one another)."""
    import dataclasses
    from rig_runtime.scenario import load_scenario
    sc = load_scenario("step-sequence")
    ref = sc.reference
    assert ref[0].y_mm == 0.0 and all(p.y_mm == 0.0 for p in ref[2::2])     # 0 -> level -> 0 -> …
    pairs = [(a, b) for a, b in zip(ref[1::2], ref[2::2])]
    ends = [b.t for b in ref[3::2]] + [sc.duration_s]                      # each pair's 0 is held up to the next level
    kept = [(a, b, end) for (a, b), end in zip(pairs, ends) if a.y_mm in levels_mm]
    assert [a.y_mm for a, _, _ in kept] == sorted(levels_mm, key=[a.y_mm for a, _ in pairs].index)
    pts, t = [ref[0]], ref[1].t
    for a, b, end in kept:
        pts += [dataclasses.replace(a, t=t), dataclasses.replace(b, t=t + b.t - a.t)]
        t += end - a.t
    return dataclasses.replace(sc, name="step-sequence-part", reference=tuple(pts), duration_s=t)


def test_step_sequence(tmp_path, cfg):
    """Sec. 5.2.4 on a part of the step-sequence scenario, judged as the whole sequence is
    (tests/e2e.py assert_steps_tracked: every step's steady-state error < 2 % of the step or
    < 5 µm, current within ±u_max in the log and on the wire, no faults, median rise and
    settling times). The part keeps, in the shipped order and each held 20 s as shipped, the
    largest steps (±3.5 mm: the largest current), the smallest (±0.1 mm, where the 5 µm
    bound and the slow high-damped tail matter) and the two levels whose steps came closest
    to their bound in the whole sequence at seed 0 (-0.7 and +0.3 mm: 55 % and 54 %): 12 of
    its 72 steps, 241 s instead of 1441 s simulated. The whole sequence is the acceptance
    run benchmarks/step_sequence.py, judged by the same check (docs/performance.md)."""
    sc = part_of_step_sequence(STEP_SEQUENCE_LEVELS_MM)
    assert sc.duration_s == 241.0
    r = run(tmp_path, sc)
    assert_steps_tracked(r, cfg, n_steps=2 * len(STEP_SEQUENCE_LEVELS_MM))


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
    high-damped tail. The run ends at 261 s: the three steps judged are over by 260 s (the
    scenario's last two, at 260 and 320 s, are not judged; a run is causal, so what
    happened up to 260 s is the same in the 380 s run)."""
    r = run(tmp_path, "open-loop-steps", duration_s=261.0)
    assert r.summary["final_state"] == "IDLE"
    t, psi = r.col("t_run"), r.col("psi_ar")
    for t0, t_next in ((20.0, 80.0), (80.0, 140.0), (200.0, 260.0)):
        before = np.mean(psi[(t > t0 - 1.0) & (t < t0)])
        jump = np.mean(psi[(t > t0 + 0.3) & (t < t0 + 0.4)]) - before
        total = np.mean(psi[(t > t_next - 1.0) & (t < t_next)]) - before
        assert 0.15 < jump / total < 0.85, (t0, jump, total)   # a jump, then more to come
        tail = np.mean(psi[(t > t0 + 20) & (t < t0 + 21)]) - before
        assert abs(tail) < abs(total)                          # still creeping after 20 s
