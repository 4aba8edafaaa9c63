"""Lateral dynamics (2b) with offset (Sec. 4.1.2): y_off and l0, the measured ψ as input.

    ẏ = −(c̄_y v/(2 l0)) y + c̄_y v ψ + (v/(2 l0)) y_off,    y(0) = y_meas(0)

c̄_y comes from δ0 of relation (4) (fitted before). The ODE is linear in y with a measured
input, so it is integrated exactly for ψ linear between samples (first-order hold).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.signal import lfilter

from rig_runtime.config import Plant as PlantParams

from . import fit
from .experiments import Experiment


def simulate(P: PlantParams, e: Experiment, l0: float, y_off: float, y0: float | None = None) -> np.ndarray:
    cv = P.c_y * P.v
    a = cv / (2 * l0)
    h = e.h
    phi = np.exp(-a * h)
    w = (1 - phi) / a                         # ∫ e^{-a(h-s)} ds
    w1 = (h - w) / (a * h)                    # ∫ e^{-a(h-s)} s/h ds
    psi = np.nan_to_num(e.psi, nan=float(np.nanmedian(e.psi)))
    g = cv * psi + P.v / (2 * l0) * y_off
    # y_{k+1} = phi y_k + (w - w1) g_k + w1 g_{k+1}
    f = (w - w1) * g[:-1] + w1 * g[1:]
    yi = float(e.y[np.isfinite(e.y)][0]) if y0 is None else y0
    y, _ = lfilter([1.0], [1.0, -phi], f, zi=[phi * yi])
    return np.concatenate(([yi], y))


def identify(P: PlantParams, exps: list[Experiment]) -> fit.Fit:
    def res(x):
        out = []
        for e in exps:
            r = e.y - simulate(P, e, x[0], x[1])
            out.append(r[np.isfinite(r)])
        return np.concatenate(out)
    return fit.solve(res, [P.l0, 0.0], ("l0", "y_off"), [0.01, -0.05], [10.0, 0.05])


def with_delta0(P: PlantParams, delta0: float) -> PlantParams:
    return replace(P, delta0=delta0)
