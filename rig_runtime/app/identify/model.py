"""The yaw model (6)-(9) with law (7), integrated by the project's own plant integrator
(``sim_backend.plant.Plant``) — the same equations and code the simulator uses.

The integrator is exact for a held input over any step length where the yaw angle moves
monotonically or the model is linear, so the model is stepped from output sample to output
sample and split where the input changes: a slow sine or a long step costs a few thousand
steps instead of one per 5 ms cycle. One exception: with the hysteresis, right after an input
change (D near D_min) the carrier rings at the stiffness of a fresh reversal (on the shipped
plant ω0 √(a + (1 − a)(1 + (β − γ)/(β + γ))) ≈ 117 rad/s, a half period of ~27 ms), and the
integrator only splits a step at a reversal it sees (ψ̇ of another sign at the step's end):
two reversals inside one long step are missed and the Bouc-Wen state goes wrong (on the
shipped plant's sine record, steps of 0.25 s gave errors up to 6 µrad against 5 ms steps,
enough to bias K by 0.1 % and beta − gamma by 2 %). So for ``SETTLE_S`` after every input
change (and after the start) the model is stepped every ``FINE_STEP`` samples.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np

from rig_runtime.config import BoucWen, Plant as PlantParams
from sim_backend.plant import LiftedCarrier, Plant

SETTLE_S = 0.5      # after an input change: D back at D_max (~0.25 s), no more ringing
FINE_STEP = 2       # samples per integrator call within SETTLE_S of an input change
REST_S = 0.5        # the rest at the start of a record: its mean is the initial angle


def yaw_params(base: PlantParams, **kw) -> PlantParams:
    """``base`` with yaw parameters replaced (``bouc_wen=None``: the linear model). No carrier
    on the rollers: the model is read for the yaw only, which no lateral or wheel-speed state
    feeds (the plant does not integrate those then; the yaw's floats are the same)."""
    return replace(base, front_contact=False, rear_contact=False, **kw)


def bouc_wen(a: float, beta: float, gamma: float) -> BoucWen:
    return BoucWen(a=min(max(a, 0.0), 1.0), A=1.0, beta=max(beta, 1e-12), gamma=gamma, n=1)


def _marks(params: PlantParams, u: np.ndarray, h: float, k0: int, k1: int, out: np.ndarray,
           lifted: Optional[LiftedCarrier]) -> np.ndarray:
    ch = np.flatnonzero(np.diff(u[k0:k1]) != 0.0) + k0 + 1
    marks = np.union1d(ch, out)
    bw = params.bouc_wen
    if lifted is None and bw is not None and bw.a < 1.0:
        w = max(int(round(SETTLE_S / h)), 1)
        fine = (np.arange(0, w, FINE_STEP)[None, :] + np.concatenate(([k0], ch))[:, None]).ravel()
        marks = np.union1d(marks, fine)
    return marks[(marks > k0) & (marks <= k1)]


def simulate_psi(params: PlantParams, u: np.ndarray, h: float, k0: int, k1: int, out: np.ndarray, *,
                 psi0: float, rate0: float = 0.0, z0: Optional[float] = None, u_before: Optional[float] = None,
                 lifted: Optional[LiftedCarrier] = None) -> np.ndarray:
    """psi at the sample indices ``out`` (sorted, within [k0, k1]) of the rear carrier started at
    sample k0 with (psi0, rate0, z0) and its input filter settled on ``u_before`` (default u[k0]),
    driven by u[k] held over [t_k, t_k+1)."""
    pl = Plant(params, rear_lifted=lifted)
    ub = float(u[k0] if u_before is None else u_before)
    pl.reset(psi_ar=psi0, psi_rate_r=rate0, z_r=z0, du_r=ub)
    marks = _marks(params, u, h, k0, k1, out, lifted)
    res = np.empty(len(out))
    j = 0
    if len(out) and out[0] == k0:
        res[0] = psi0
        j = 1
    k = k0
    step = pl.step
    for m in marks.tolist():
        step((m - k) * h, 0.0, float(u[k]))
        k = m
        if j < len(out) and out[j] == m:
            res[j] = pl.psi_ar
            j += 1
    return res


def record_start(params: PlantParams, u: np.ndarray, h: float, psi: np.ndarray) -> tuple[float, float]:
    """(psi0, z0) of a record that starts at rest: psi0 the mean measured angle over the
    first ``REST_S`` (at most until the input first changes), z0 the hysteresis state that
    holds the carrier at rest there, a psi0 + (1 − a) z0 = K u0 + psi_off (so the model's rest
    angle is the measured one whatever the carrier's history). One noisy sample as psi0 = z0
    would leave its noise in z for good (the hysteresis remembers it: on the simulated rig a
    first sample 7 µrad off shifted the whole record by 1.8 µrad)."""
    n = max(int(round(REST_S / h)), 1)
    ch = np.flatnonzero(np.diff(u) != 0.0)
    if len(ch):
        n = max(min(n, int(ch[0]) + 1), 1)
    head = psi[:n]
    ok = np.isfinite(head)
    psi0 = float(np.mean(head[ok])) if ok.any() else float(psi[np.isfinite(psi)][0])
    bw = params.bouc_wen
    if bw is None or bw.a >= 1.0:
        return psi0, psi0
    return psi0, (params.K * float(u[0]) + params.psi_off - bw.a * psi0) / (1.0 - bw.a)


def simulate_record(params: PlantParams, u: np.ndarray, h: float, psi: np.ndarray, out: np.ndarray) -> np.ndarray:
    """psi at the sample indices ``out`` of a whole record started at rest (``record_start``)."""
    p0, z0 = record_start(params, u, h, psi)
    return simulate_psi(params, u, h, 0, int(out[-1]), out, psi0=p0, z0=z0)
