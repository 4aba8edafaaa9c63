"""Natural frequency (Sec. 4.3.2): omega0, the lifted carrier's D and psi_off from free responses.

The carrier is off the rollers (no hysteresis, constant damping) and swings freely after it is
let go with zero input. Each release is found in the record (``releases``): the first sample,
if the carrier is away from rest there, and the end of every hold (the carrier held still away
from rest by hand, then let go). Every release is one segment of model (6) with f_hyst = 0;
the segments share omega0, D, psi_off, and each has its own start (psi, psi_dot) as nuisance
parameters (the paper's x(0) = x_meas(0), made robust to the noise of one sample).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rig_runtime.config import Plant as PlantParams
from sim_backend.plant import LiftedCarrier

from . import fit
from .experiments import Experiment
from .model import simulate_psi, yaw_params

AWAY_RAD = 2e-3      # a carrier this far from rest counts as deflected
HOLD_S = 0.3         # held still at least this long before a release
SEGMENT_S = 2.5      # seconds of free response fitted after each release
LEFT_RAD = 3e-4      # the carrier has left the held angle (far above the sensor noise)


@dataclass(frozen=True)
class Segment:
    exp: Experiment
    k0: int
    k1: int


def releases(e: Experiment) -> list[Segment]:
    psi, h = e.psi, e.h
    n = len(psi)
    ok = np.isfinite(psi)
    rest = float(np.median(psi[ok][-max(int(1.0 / h), 1):]))
    away = np.abs(psi - rest) > AWAY_RAD
    w = max(int(0.05 / h), 2)
    rate = np.zeros(n)
    rate[w:-w] = (psi[2 * w:] - psi[:-2 * w]) / (2 * w * h)
    still = away & (np.abs(rate) < 0.02)
    starts = [0] if away[0] else []
    holds = []                      # first sample of every hold of at least HOLD_S
    run = 0
    need = int(HOLD_S / h)
    for k in range(n - 1):
        run = run + 1 if still[k] else 0
        if run == need:
            holds.append(k - need + 1)
        if run >= need and not still[k + 1]:
            # let go: the segment starts at the first sample clearly off the held angle (the
            # rate test above reacts ~50 ms early); psi0, psi_dot0 there are fitted
            held = float(np.nanmean(psi[k - need + 1:k + 1]))
            off = np.flatnonzero(np.abs(psi[k:] - held) > LEFT_RAD)
            if len(off):
                starts.append(k + int(off[0]))
    segs = []
    m = int(SEGMENT_S / h)
    for k0 in sorted(set(starts)):
        # stop a second before the next hold begins (the hand pushes the carrier there)
        nxt = [k for k in holds if k > k0]
        k1 = min(k0 + m, n - 1, (nxt[0] - int(1.0 / h)) if nxt else n - 1)
        if k1 - k0 > int(0.5 / h):
            segs.append(Segment(e, k0, k1))
    return segs


def identify(P: PlantParams, exps: list[Experiment]) -> tuple[fit.Fit, list[Segment]]:
    segs = [s for e in exps for s in releases(e)]
    if not segs:
        raise ValueError("free response: no release found (deflect the carrier by more than "
                         f"{AWAY_RAD * 1e3:g} mrad, hold it still {HOLD_S} s, let go)")
    data = []
    for s in segs:
        idx = np.arange(s.k0, s.k1 + 1)
        y = s.exp.psi[idx]
        ok = np.isfinite(y)
        data.append((idx[ok], y[ok]))

    def res(x):
        w0, D, off = x[:3]
        Pp = yaw_params(P, omega0=w0)
        lc = LiftedCarrier(D=D, psi_off=off)
        out = []
        for i, (s, (idx, y)) in enumerate(zip(segs, data)):
            psi0, rate0 = x[3 + 2 * i], x[4 + 2 * i]
            out.append(y - simulate_psi(Pp, s.exp.u, s.exp.h, s.k0, s.k1, idx, psi0=psi0, rate0=rate0,
                                        lifted=lc))
        return np.concatenate(out)

    rest = float(np.median([np.median(y[-20:]) for _, y in data]))
    x0 = [P.omega0, 0.3, rest]
    lo, hi = [1.0, 1e-3, -0.05], [200.0, 5.0, 0.05]
    names = ["omega0", "D", "psi_off"]
    for i, (idx, y) in enumerate(data):
        x0 += [float(y[0]), 0.0]
        lo += [-0.1, -5.0]
        hi += [0.1, 5.0]
        names += [f"psi0[{i}]", f"rate0[{i}]"]
    return fit.solve(res, x0, names, lo, hi), segs
