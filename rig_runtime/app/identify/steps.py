"""Damping (Sec. 4.3.3): K and psi_off from the stationary values of long current steps,
D_min and D_max from the response before and after the first 0.2 s, then c_udot_max of the
variable-damping law (7) from the whole response (input derivative from the 10 Hz filtered
input, as the plant integrator has it).

Every step i (a change of the input followed by at least ``MIN_HOLD_S`` of constant input)
is one window. The model is (6) without hysteresis; its stationary value for step i is the
step's own final value psi_inf_i (so K and psi_off only enter as K u_i + psi_off = psi_inf_i
and the damping fits are not biased by the hysteresis' history-dependent rest angle).
psi_inf_i is fitted with D_max on the tail (a 60 s tail with D_max = 100 has not quite settled),
started at the mean of the last 5 s; K and psi_off are the straight line through
(u_i, psi_inf_i), including the level before the first step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from rig_runtime.config import Plant as PlantParams

from . import fit
from .experiments import Experiment, segments
from .model import simulate_psi, yaw_params

MIN_HOLD_S = 20.0
FAST_S = 0.2          # the paper's split: low damping before, high damping after
TAIL_EVERY = 10       # tail residuals every 10th sample (the tail is slow)
SETTLED_S = 5.0       # stationary value: mean over the last 5 s of a step


@dataclass(frozen=True)
class Step:
    exp: Experiment
    k0: int           # first sample with the new input
    k1: int           # last sample of the step
    u: float
    u_before: float
    psi_end: float    # mean of the last SETTLED_S


@dataclass(frozen=True)
class StepsResult:
    steps: list
    tail: fit.Fit          # D_max and psi_inf per step
    static: fit.Fit        # K, psi_off
    fast: fit.Fit          # D_min
    law: fit.Fit           # c_udot_max
    psi_inf: np.ndarray


def find_steps(e: Experiment) -> tuple[list[Step], Optional[tuple[float, float]]]:
    """The steps, and (u, psi_end) of the level the record starts with if it lasts at least
    2·SETTLED_S (the rest before the first step, Fig. 8), else None."""
    h = e.h
    out, start = [], None
    for a, b in segments(e.u):
        long_ = (b - a) * h >= MIN_HOLD_S
        if not long_ and not (a == 0 and (b - a) * h >= 2 * SETTLED_S):   # the rest level at the start
            continue
        tail = e.psi[b - int(SETTLED_S / h):b]
        psi_end = float(np.nanmean(tail))
        if a == 0:
            start = (float(e.u[a]), psi_end)
        else:
            out.append(Step(e, a, b - 1, float(e.u[a]), float(e.u[a - 1]), psi_end))
    return out, start


def _start(s: Step) -> float:
    e = s.exp
    pre = e.psi[max(s.k0 - 4, 0):s.k0 + 1]
    return float(np.nanmean(pre))


def identify(P: PlantParams, exps: list[Experiment]) -> StepsResult:
    steps = []
    for e in exps:
        steps += find_steps(e)[0]
    if not steps:
        raise ValueError(f"steps: no input step held at least {MIN_HOLD_S:g} s")
    h = steps[0].exp.h
    nf = int(round(FAST_S / h))

    # -- tail: D_max and the stationary values, model started 0.2 s after each step
    tails = []
    for s in steps:
        e = s.exp
        ka = s.k0 + nf
        idx = np.arange(ka, s.k1 + 1, TAIL_EVERY)
        w = 10
        rate0 = float((np.nanmean(e.psi[ka:ka + w]) - np.nanmean(e.psi[ka - w:ka])) / (w * h))
        y = e.psi[idx]
        ok = np.isfinite(y)
        tails.append((s, ka, idx[ok], y[ok], rate0))

    def res_tail(x):
        D = x[0]
        out = []
        for i, (s, ka, idx, y, rate0) in enumerate(tails):
            Pp = yaw_params(P, bouc_wen=None, D_min=D, D_max=D, K=1.0, psi_off=x[1 + i] - s.u)
            out.append(y - simulate_psi(Pp, s.exp.u, h, ka, s.k1, idx, psi0=y[0], rate0=rate0))
        return np.concatenate(out)
    names = ["D_max"] + [f"psi_inf[{i}]" for i in range(len(steps))]
    tail = fit.solve(res_tail, [max(P.D_max, 10.0)] + [s.psi_end for s in steps], names,
                     [1.0] + [-0.1] * len(steps), [1e4] + [0.1] * len(steps))
    psi_inf = tail.values[1:]

    # -- stationary values: psi_inf = K u + psi_off (the level before the first step included)
    us = [s.u for s in steps]
    ps = list(psi_inf)
    for e in exps:
        lv = find_steps(e)[1]
        if lv is not None:
            us.append(lv[0])
            ps.append(lv[1])
    us, ps = np.array(us), np.array(ps)
    static = fit.solve(lambda x: ps - (x[0] * us + x[1]), [P.K, 0.0], ("K", "psi_off"), [-1.0, -0.1], [1.0, 0.1])

    # -- fast part: D_min over the first 0.2 s of every step
    fasts = []
    for s, pinf in zip(steps, psi_inf):
        idx = np.arange(s.k0, s.k0 + nf + 1)
        fasts.append((s, idx, s.exp.psi[idx], pinf))

    def res_fast(x):
        out = []
        for s, idx, y, pinf in fasts:
            Pp = yaw_params(P, bouc_wen=None, D_min=x[0], D_max=x[0], K=1.0, psi_off=pinf - s.u)
            r = y - simulate_psi(Pp, s.exp.u, h, s.k0, s.k0 + nf, idx, psi0=_start(s), u_before=s.u_before)
            out.append(r[np.isfinite(r)])
        return np.concatenate(out)
    fast = fit.solve(res_fast, [P.D_min], ("D_min",), [1e-3], [1e3])
    D_min, D_max = fast.values[0], tail.values[0]

    # -- law (7): c_udot_max over the whole step, D_min and D_max fixed
    wins = []
    for s, pinf in zip(steps, psi_inf):
        n1 = int(1.0 / h)
        idx = np.concatenate([np.arange(s.k0, s.k0 + n1), np.arange(s.k0 + n1, s.k1 + 1, TAIL_EVERY)])
        wins.append((s, idx, s.exp.psi[idx], pinf))

    def res_law(x):
        out = []
        for s, idx, y, pinf in wins:
            Pp = yaw_params(P, bouc_wen=None, D_min=D_min, D_max=max(D_max, D_min), K=1.0, psi_off=pinf - s.u,
                            c_udot_max=float(np.exp(x[0])))
            r = y - simulate_psi(Pp, s.exp.u, h, s.k0, s.k1, idx, psi0=_start(s), u_before=s.u_before)
            out.append(r[np.isfinite(r)])
        return np.concatenate(out)
    lf = fit.solve(res_law, [np.log(P.c_udot_max)], ("log_c_udot_max",), [np.log(1e-9)], [np.log(1e3)],
                   diff_step=1e-3)
    c = float(np.exp(lf.values[0]))
    law = fit.transform(lf, ("c_udot_max",), np.array([c]), np.array([[c]]))
    return StepsResult(steps, tail, static, fast, law, psi_inf)

