"""Can a law reach issue 25's acceptance on the vehicle? A quick exploration on the linear
sampled coupled model (coupled.step_response: no hysteresis, no limits, no noise):

    .venv/bin/python -m benchmarks.vehicle_law_reach [FAMILY] [--maxiter N] [--popsize N] [--seed S]
        [--every-damping] [--radius-only] [--x0 X,...]

--every-damping: the radius constraint at every D_min/D_max combination (else the gate's cases);
--radius-only: minimise that radius alone (whether any gains of the family are stable there).

Cases: unit reference steps on the front, the rear and both together, at v = ±0.5 … ±1.5 m/s,
every carrier at D_min. Criteria, each normalised so that 1 is its demand: 10–90 % rise / 3 s,
overshoot / 10 %, 2 % settling / 8 s, steady-state error (at 20 s) / 2 %, the held carrier's
excursion / 10 % of the step, peak |u| for a 3 mm step / 3 A; plus the sampled loop's spectral
radius over v_range at D_min and D_max (each carrier) < 1, and Sec. 5.2.3's per-term input
check (K_P,ψ 0.05 rad and K_D,ψ 0.4 rad/s under 2 A) as bounds. The cost is the worst
normalised criterion over all cases (min-max, as MOPS): <= 1 meets the acceptance (linearly).
scipy's differential_evolution over the log of the tunables (exploration, not the runtime).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time

import numpy as np
from scipy.optimize import differential_evolution

from rig_runtime import config, coupled
from rig_runtime.config import DecoupledGains, PIPDGains

SPEEDS = (-1.5, -1.0, -0.5, 0.5, 1.0, 1.5)
CASES = (("front",), ("rear",), ("front", "rear"))
T_END = 20.0


def step_metrics(t, y, target):
    """rise (10–90 %), overshoot %, 2 % settling, |sse| as fraction; NaN-free (inf when not reached)."""
    if target == 0.0:
        return None
    yn = y / target
    above10 = np.nonzero(yn >= 0.1)[0]
    above90 = np.nonzero(yn >= 0.9)[0]
    T = t[-1]
    miss = T * (1.0 + min(10.0, abs(1.0 - float(np.max(yn)))))     # not reached: longer than the run
    rise = (t[above90[0]] - t[above10[0]]) if len(above90) and len(above10) else miss
    over = min(1e4, max(0.0, float(np.max(yn)) - 1.0) * 100.0)
    out = np.nonzero(np.abs(yn - 1.0) > 0.02)[0]
    settle = (t[out[-1] + 1] if out[-1] + 1 < len(t) else T * (1.0 + min(10.0, abs(yn[-1] - 1.0)))) if len(out) else 0.0
    return rise, over, settle, min(1e3, abs(yn[-1] - 1.0))


def evaluate(cfg, laws_at, speeds=SPEEDS, detail=False):
    """The worst normalised criterion over the cases (and per case with ``detail``)."""
    rows = []
    worst = 0.0
    for v in speeds:
        D = coupled.d_min(cfg, ("front", "rear"))
        laws = laws_at(v)
        resp = {c: coupled.step_response(cfg, v, D, c, T_END, laws) for c in CASES[:2]}
        for case in CASES:
            y = {k: sum(resp[(c,)].y[k] for c in case) for k in ("front", "rear")}
            u = {k: sum(resp[(c,)].u[k] for c in case) for k in ("front", "rear")}
            t = resp[("front",)].t
            crit = {}
            for k in ("front", "rear"):
                if k in case:
                    m = step_metrics(t, y[k], 1.0)
                    crit[f"{k}_rise"] = m[0] / 3.0
                    crit[f"{k}_overshoot"] = m[1] / 10.0
                    crit[f"{k}_settling"] = m[2] / 8.0
                    crit[f"{k}_sse"] = m[3] / 0.02
                else:
                    crit[f"{k}_held"] = float(np.max(np.abs(y[k]))) / 0.1
            crit["peak_u"] = max(float(np.max(np.abs(u[k]))) for k in u) * 3e-3 / 3.0
            w = max(crit.values())
            worst = max(worst, w)
            rows.append((v, case, w, crit))
    return (worst, rows) if detail else worst


def radius(cfg, laws_at, every_damping=False):
    """The sampled loop's spectral radius over v_range: at the gate's damping cases (D_min where
    the lateral pair is not open-loop stable), or at every D_min/D_max combination."""
    lay = coupled.layout(cfg)
    r = 0.0
    for v in coupled.speeds(cfg)[0]:
        cases = (coupled.all_damping_cases(cfg, lay.carriers) if every_damping
                 else coupled.damping_cases(cfg, v, lay))
        for D in cases:
            Ad, Bd = coupled.held(cfg, v, D, lay)
            M = coupled.close(Ad, Bd, lay, laws_at(v, D))
            with np.errstate(all="ignore"):
                r = max(r, float(np.max(np.abs(np.linalg.eigvals(M)))))
    return r


def pipd_family(cfg, x):
    """Per-carrier PI-PD, the same gains on both carriers: x = log10 [K_P_y, K_I_y, K_P_psi, K_D_psi]."""
    kpy, kiy, kpp, kdp = (10.0 ** xi for xi in x)
    g = PIPDGains(K_P_y=kpy, K_I_y=kiy, K_P_psi=kpp, K_D_psi=kdp, T_f_psi=cfg.controller.pipd.T_f_psi)
    c = dataclasses.replace(cfg.controller, pipd=g, front=None, rear=None)
    return dataclasses.replace(cfg, controller=c)


def decoupled_family(cfg, x):
    """Law decoupled, the same gains on both carriers: x = log10 [K_P_y, K_I_y, K_P_psi, K_D_psi],
    b_y, K_x_y[, T_x_y, log10 K_I_psi (<= 0: none)[, K_t_y]]."""
    kpy, kiy, kpp, kdp = (10.0 ** xi for xi in x[:4])
    more = {"T_x_y": float(x[6]), "K_I_psi": 10.0 ** float(x[7]) if x[7] > 0.0 else 0.0} if len(x) > 6 else {}
    if len(x) > 8:
        more["K_t_y"] = float(x[8])
    g = DecoupledGains(K_P_y=kpy, K_I_y=kiy, K_P_psi=kpp, K_D_psi=kdp, T_f_psi=cfg.controller.pipd.T_f_psi,
                       b_y=float(x[4]), K_x_y=float(x[5]), **more)
    c = dataclasses.replace(cfg.controller, law="decoupled", decoupled=g, front=None, rear=None)
    return dataclasses.replace(cfg, controller=c)


FAMILIES = {
    # name: (bounds in log10, cfg maker, laws_at(cfg) -> v -> laws)
    "pipd": ([(-1, 1.5), (-1, 1.5), (0, math.log10(40.0)), (-1, math.log10(5.0))], pipd_family),
    # K_P,y <= 7.5 rad/m (Sec. 5.2.3's psi_ref check at y_design = 8 mm)
    "decoupled": ([(-1, math.log10(7.5)), (-1, 1.5), (0, math.log10(40.0)), (-1, math.log10(5.0)), (0.0, 1.0),
                   (0.0, 15.0)],
                  decoupled_family),
    # with the yaw loop's integrator (ψ reaches ψ_ref whatever the yaw statics: K_x,y = 1/(2 l0) decouples)
    # and the decoupling's lead
    "decoupled-i": ([(-1, math.log10(7.5)), (-1, 1.5), (0, math.log10(40.0)), (-1, math.log10(5.0)), (0.0, 1.0),
                     (1.5, 2.2), (0.0, 0.5), (1.0, 3.0)], decoupled_family),
    # as decoupled-i, wider: K_x,y 0–5 rad/m, K_I,ψ 1–3000 A/(rad s) (the search with --every-damping:
    # at D_max the yaw loop is ~10x slower, so the feasible set may lie far from the D_min one)
    "decoupled-i-wide": ([(-1.5, math.log10(7.5)), (-2, 1.5), (0, math.log10(40.0)), (-1, math.log10(5.0)),
                          (0.0, 1.0), (0.0, 5.0), (0.0, 0.5), (0.0, 3.5)], decoupled_family),
    # with the trailing carrier's following K_t,y (0–30 rad/m): the leading carrier at D_max
    # (its yaw ~10x slower) is held through the trailing one (control.DecoupledLaw)
    "decoupled-t": ([(-2, math.log10(7.5)), (-3, 1.3), (0, math.log10(40.0)), (-1, math.log10(5.0)),
                     (0.0, 1.0), (0.0, 10.0), (0.0, 1.0), (-1.0, 4.0), (0.0, 30.0)], decoupled_family),
}


def laws_of(cfg):
    """v, D (None: each carrier's D_min) -> each controlled carrier's law there (a law scheduled on
    its damping at the gains it has at D)."""
    lay = coupled.layout(cfg)
    return lambda v, D=None: {c: coupled.law_at(cfg, c, v, D=None if D is None else D[c]) for c in lay.controlled}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("family", nargs="?", default="pipd", choices=sorted(FAMILIES))
    ap.add_argument("--maxiter", type=int, default=25)
    ap.add_argument("--popsize", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--radius-only", action="store_true",
                    help="minimise the sampled radius alone (is the constraint feasible at all?)")
    ap.add_argument("--x0", help="a start point (comma-separated, in the family's coordinates)")
    ap.add_argument("--every-damping", action="store_true",
                    help="the radius constraint at every D_min/D_max combination (the gate's rule since issue 25)")
    a = ap.parse_args(argv)
    base = config.load("configs/vehicle.yaml")
    bounds, make = FAMILIES[a.family]
    speeds = (-1.5, -0.5, 0.5, 1.5)

    def cost(x):
        cfg = make(base, x)
        laws = laws_of(cfg)
        r = radius(cfg, laws, a.every_damping)
        if a.radius_only:
            return r
        if not r < 1.0:
            return 1e4 + min(r, 1e3)
        return evaluate(cfg, laws, speeds)

    t0 = time.perf_counter()
    x0 = [float(v) for v in a.x0.split(",")] if a.x0 else None
    res = differential_evolution(cost, bounds, maxiter=a.maxiter, popsize=a.popsize, seed=a.seed,
                                 polish=False, tol=1e-3, x0=x0)
    cfg = make(base, res.x)
    worst, rows = evaluate(cfg, laws_of(cfg), SPEEDS, detail=True)
    print(f"{a.family}: x = {[round(float(v), 4) for v in res.x]} (log10 of the first four)  worst normalised criterion {worst:.3f} "
          f"(<= 1 meets the acceptance), radius {radius(cfg, laws_of(cfg)):.5f} at D_min, "
          f"{radius(cfg, laws_of(cfg), True):.5f} at every D_min/D_max combination, "
          f"{res.nfev} evaluations, {time.perf_counter() - t0:.0f} s")
    for v, case, w, crit in rows:
        k = max(crit, key=crit.get)
        print(f"  v={v:+.1f} {'+'.join(case):11s} worst {w:6.3f} ({k})  " +
              " ".join(f"{n}={x:.2f}" for n, x in crit.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
