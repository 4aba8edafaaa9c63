"""Lateral dynamics with offset (Sec. 4.1.2): y_off and l0 of the carrier in rolling contact,
the other carrier out of contact (its y ≡ 0), the measured ψ as input.

    rear  (2b), v > 0:  ẏ_r = −(c̄_y v/(2 l0)) y_r + c̄_y v ψ_ar + (v/(2 l0)) y_off
    front (2a), v < 0:  ẏ_f = +(c̄_y v/(2 l0)) y_f + c̄_y v ψ_af + (v/(2 l0)) y_off

with each carrier's own c̄_y, l0, y_off (the simulator's model, sim_backend/plant.py: the
offset term of the front is the rear's, (v/(2 l0)) y_off). Each is stable only for the
trailing carrier: the rear at v > 0 (the paper's set-up), the front at v < 0 (the mirrored
one); ``identify`` refuses the other direction. c̄_y comes from δ0 of relation (4) (fitted
before). The ODE is linear in y with a measured input, so it is integrated exactly for ψ
linear between samples (first-order hold).
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from rig_runtime.config import Plant as PlantParams

from . import fit
from .experiments import Experiment

SIGMA = {"rear": -1.0, "front": 1.0}


def coefficients(P: PlantParams, carrier: str, v: float, l0: float) -> tuple[float, float, float]:
    """(decay λ, input gain, offset gain) of ẏ = −λ y + (c̄_y v) ψ + g_off y_off for ``carrier``
    in contact alone at speed v (λ > 0: stable)."""
    return -SIGMA[carrier] * P.c_y * v / (2 * l0), P.c_y * v, v / (2 * l0)


def speed(P: PlantParams, e: Experiment) -> float:
    return P.v if e.v is None else e.v


def simulate(P: PlantParams, e: Experiment, l0: float, y_off: float, y0: float | None = None) -> np.ndarray:
    lam, cv, goff = coefficients(P, e.carrier, speed(P, e), l0)
    h = e.h
    phi = np.exp(-lam * h)
    w = (1 - phi) / lam                       # ∫ e^{-λ(h-s)} ds
    w1 = (h - w) / (lam * h)                  # ∫ e^{-λ(h-s)} s/h ds
    psi = np.nan_to_num(e.psi, nan=float(np.nanmedian(e.psi)))
    g = cv * psi + goff * y_off
    # y_{k+1} = phi y_k + (w - w1) g_k + w1 g_{k+1}
    f = (w - w1) * g[:-1] + w1 * g[1:]
    yi = float(e.y[np.isfinite(e.y)][0]) if y0 is None else y0
    y, _ = lfilter([1.0], [1.0, -phi], f, zi=[phi * yi])
    return np.concatenate(([yi], y))


def check_direction(P: PlantParams, e: Experiment) -> None:
    """The set-up: the other carrier out of contact (its y ≡ 0), and the carrier's lateral
    dynamics stable in the experiment's direction."""
    if e.other_rolling:
        other = "front" if e.carrier == "rear" else "rear"
        raise ValueError(f"{e.name}: the {other} carrier was on the rollers too (the log's config: "
                         f"plant.{other}_contact true); the {e.carrier}'s lateral fit needs it out of contact")
    lam, _, _ = coefficients(P, e.carrier, speed(P, e), P.l0)
    if not lam > 0:
        want = "v > 0" if e.carrier == "rear" else "v < 0"
        raise ValueError(f"{e.name}: the {e.carrier} carrier's lateral dynamics are unstable at "
                         f"v = {speed(P, e):+.3g} m/s; identify it at {want} (the trailing carrier)")


def identify(P: PlantParams, exps: list[Experiment]) -> fit.Fit:
    for e in exps:
        check_direction(P, e)

    def res(x):
        out = []
        for e in exps:
            r = e.y - simulate(P, e, x[0], x[1])
            out.append(r[np.isfinite(r)])
        return np.concatenate(out)
    return fit.solve(res, [P.l0, 0.0], ("l0", "y_off"), [0.01, -0.05], [10.0, 0.05])
