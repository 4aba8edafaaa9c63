"""Joint refinement of the yaw model on the steps and the sines together.

The paper fits the damping on the steps with a linear model and the hysteresis on the sines
with the damping fixed. With the hysteresis in the model the two are coupled: the linear
damping fits absorb the hysteresis (on the simulated rig D_max 1.5x, D_min 1.6x too high), and
the sines barely reach the saturation of z (1/(beta+gamma)), which the long steps show in their
stationary values. After the sequential fits, one problem (1) over both records refines
K, a, beta, gamma, D_min, D_max, c_udot_max with one psi_off per experiment kind (the paper
reports psi_off per experiment; the sines' one goes to the plant, as in Table 3's last row).
Each record is simulated from its measured rest at the start (``model.record_start``); the
first seconds are left out of the residual.
"""

from __future__ import annotations

import numpy as np

from rig_runtime.config import Plant as PlantParams

from . import fit
from .experiments import Experiment, segments
from .model import bouc_wen, simulate_record, yaw_params

STEP_FINE_S = 1.0     # after every input change of a steps record: every sample for 1 s
STEP_EVERY = 10       # then every 10th
SINE_EVERY_S = 0.25
SKIP_S = 20.0         # residuals start here (initial hysteresis state unknown)
_MEMO = 64            # residuals of one record kept by their parameters (a Jacobian needs 10 per record)


def _steps_grid(e: Experiment):
    idx = [np.arange(a, min(a + int(STEP_FINE_S / e.h), b)) for a, b in segments(e.u)]
    idx.append(np.arange(0, len(e.u), STEP_EVERY))
    ii = np.unique(np.concatenate(idx))
    return ii, np.isfinite(e.psi[ii]) & (e.t[ii] >= min(SKIP_S, 0.5 * e.t[-1]))


def _sine_grid(e: Experiment):
    ii = np.arange(0, len(e.t), max(int(round(SINE_EVERY_S / e.h)), 1))
    return ii, np.isfinite(e.psi[ii]) & (e.t[ii] >= SKIP_S)


def _sim(P: PlantParams, e: Experiment, ii: np.ndarray) -> np.ndarray:
    return simulate_record(P, e.u, e.h, e.psi, ii)


NAMES = ("K", "bouc_wen.a", "bouc_wen.beta", "bouc_wen.gamma", "D_min", "D_max", "c_udot_max",
         "psi_off_steps", "psi_off")


def refine(P: PlantParams, steps_exps: list[Experiment], sine_exps: list[Experiment],
           psi_off_steps: float, tol: float = 1e-6) -> fit.Fit:
    """``P`` carries the sequential estimates (start values). Returns the fit in ``NAMES``."""
    data = [(e, *_steps_grid(e), 0) for e in steps_exps] + [(e, *_sine_grid(e), 1) for e in sine_exps]
    bw = P.bouc_wen

    # A record's residual depends on the common parameters and its own kind's offset only:
    # the Jacobian column of psi_off_steps leaves the sines' residuals as they were at x, that
    # of psi_off the steps' ones. Those are taken from the evaluation at x (the same numbers).
    memo: dict = {}

    def res(x):
        K, a, s, d, dmin, dmax, lc, off_st, off_sn = x
        xb = np.asarray(x, float)
        common = xb[:7].tobytes()           # by their bits: -0.0 and 0.0 are not taken for one another
        base = None
        out = []
        for i, (e, ii, ok, kind) in enumerate(data):
            key = (i, common, xb[8 if kind else 7].tobytes())
            r = memo.get(key)
            if r is None:
                if base is None:
                    base = yaw_params(P, K=K, D_min=dmin, D_max=max(dmax, dmin), c_udot_max=float(np.exp(lc)),
                                      bouc_wen=bouc_wen(a, 0.5 * (s + d), 0.5 * (s - d)))
                Pp = yaw_params(base, psi_off=off_sn if kind else off_st)
                r = (e.psi[ii] - _sim(Pp, e, ii))[ok]
                if len(memo) >= _MEMO:
                    memo.pop(next(iter(memo)))
                memo[key] = r
            out.append(r)
        return np.concatenate(out)
    x0 = [P.K, bw.a, bw.beta + bw.gamma, bw.beta - bw.gamma, P.D_min, P.D_max, np.log(P.c_udot_max),
          psi_off_steps, P.psi_off]
    lo = [1e-5, 0.01, 1.0, 10.0, 1e-2, 1.0, np.log(1e-9), -0.05, -0.05]
    hi = [1.0, 0.99, 1e5, 1e6, 1e3, 1e4, np.log(1e3), 0.05, 0.05]
    f = fit.solve(res, x0, ("K", "a", "s", "d", "D_min", "D_max", "log_c", "psi_off_steps", "psi_off"),
                  lo, hi, diff_step=1e-4, tol=tol, parallel=True)
    K, a, s, d, dmin, dmax, lc, o1, o2 = f.values
    c = float(np.exp(lc))
    T = np.eye(9)
    T[2, 2:4] = [0.5, 0.5]
    T[3, 2:4] = [0.5, -0.5]
    T[6, 6] = c
    return fit.transform(f, NAMES, np.array([K, a, 0.5 * (s + d), 0.5 * (s - d), dmin, dmax, c, o1, o2]), T)
