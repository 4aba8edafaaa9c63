"""The yaw model (6)-(9) with law (7), integrated by the project's own plant integrator
(``sim_backend.plant.Plant``) — the same equations and code the simulator uses.

The integrator is exact for a held input over any step length (adaptive sub-steps where D
varies or the hysteresis flips), so the model is stepped from output sample to output sample
and split only where the input changes: a slow sine or a long step costs a few thousand
steps instead of one per 5 ms cycle.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np

from rig_runtime.config import BoucWen, Plant as PlantParams
from sim_backend.plant import LiftedCarrier, Plant


def yaw_params(base: PlantParams, **kw) -> PlantParams:
    """``base`` with yaw parameters replaced (``bouc_wen=None``: the linear model)."""
    return replace(base, front_contact=False, **kw)


def bouc_wen(a: float, beta: float, gamma: float) -> BoucWen:
    return BoucWen(a=min(max(a, 0.0), 1.0), A=1.0, beta=max(beta, 1e-12), gamma=gamma, n=1)


def simulate_psi(params: PlantParams, u: np.ndarray, h: float, k0: int, k1: int, out: np.ndarray, *,
                 psi0: float, rate0: float = 0.0, z0: Optional[float] = None, u_before: Optional[float] = None,
                 lifted: Optional[LiftedCarrier] = None) -> np.ndarray:
    """psi at the sample indices ``out`` (sorted, within [k0, k1]) of the rear carrier started at
    sample k0 with (psi0, rate0, z0) and its input filter settled on ``u_before`` (default u[k0]),
    driven by u[k] held over [t_k, t_k+1)."""
    pl = Plant(params, rear_lifted=lifted)
    ub = float(u[k0] if u_before is None else u_before)
    pl.reset(psi_ar=psi0, psi_rate_r=rate0, z_r=z0, du_r=ub)
    ch = np.flatnonzero(np.diff(u[k0:k1]) != 0.0) + k0 + 1
    marks = np.union1d(ch, out)
    marks = marks[(marks > k0) & (marks <= k1)]
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
