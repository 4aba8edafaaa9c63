"""Relation (4) with offset (Sec. 4.2): delta0, c11, dw_off from the measured wheel speeds.

    dw = Γ(δ0) v b/(2 r0²) y + b/(2 r0) ψ̇ + v k_τ/(r0² c̄11) Δu + dw_off

with y = y_meas, ψ̇ from the measured ψ by central differences, Δu the input held over the
last period, v the experiment's speed (the same relation for either carrier in contact, with
its own Γ, b, r0; the front's experiments run at v < 0). The input term has |v|: the creep
forces of (3) go with the creepage, slip over |v| (as the simulator, sim_backend/plant.py),
while the rolling-radius term Γ v y changes sign with the direction. The raw measurement is fitted; the 0.5 Hz forward-backward filter of the paper
is only for the plot (``display_filter``).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.signal import butter, filtfilt

from rig_runtime.config import Plant as PlantParams

from . import fit
from .experiments import Experiment
from .lateral import speed


def _gamma(delta0: float, P: PlantParams) -> float:
    return replace(P, delta0=delta0).Gamma


def predict(P: PlantParams, e: Experiment, delta0: float, c11: float, dw_off: float) -> np.ndarray:
    h = e.h
    v = speed(P, e)
    rate = np.full(len(e.psi), np.nan)
    rate[1:-1] = (e.psi[2:] - e.psi[:-2]) / (2 * h)
    u_last = np.concatenate(([e.u[0]], e.u[:-1]))
    return (_gamma(delta0, P) * v * P.b / (2 * P.r0 ** 2) * e.y + P.b / (2 * P.r0) * rate
            + abs(v) * P.k_tau / (P.r0 ** 2 * c11) * u_last + dw_off)


def identify(P: PlantParams, exps: list[Experiment]) -> fit.Fit:
    """Fitted in (δ0, k_u, dw_off) with k_u = k_τ/(r0² c̄11) (rad/s per A and m/s of |v|: the input
    term is linear in it and of a sensible size), reported as (δ0, c11, dw_off)."""
    cu = P.k_tau / P.r0 ** 2

    def res(x):
        out = []
        for e in exps:
            r = e.dw - predict(P, e, x[0], cu / x[1], x[2])
            out.append(r[np.isfinite(r)])
        return np.concatenate(out)
    f = fit.solve(res, [P.delta0, cu / P.c11, 0.0], ("delta0", "k_u", "dw_off"),
                  [1e-4, 1e-9, -1.0], [math.pi / 4 - 1e-3, 10.0, 1.0])
    d0, ku, off = f.values
    T = np.diag([1.0, -cu / ku ** 2, 1.0])
    return fit.transform(f, ("delta0", "c11", "dw_off"), np.array([d0, cu / ku, off]), T)


def display_filter(x: np.ndarray, h: float, hz: float = 0.5) -> np.ndarray:
    """The paper's forward-backward low pass (display only)."""
    b, a = butter(1, hz * 2 * h)
    ok = np.isfinite(x)
    out = np.full_like(x, np.nan)
    out[ok] = filtfilt(b, a, x[ok])
    return out
