"""Verification (Sec. 4.3.5): the identified model against the held-out open-loop steps.

The yaw model (6)-(9) with law (7) is simulated over the whole record from its measured rest
at the start (``model.record_start``) with the measured input and compared with the measured yaw angle; the same
for the configured (nominal) plant. The lateral displacement is simulated from the simulated
yaw angle with (2b)."""

from __future__ import annotations

import numpy as np

from rig_runtime.config import Plant as PlantParams

from . import lateral
from .experiments import Experiment
from .model import simulate_record


def simulate(P: PlantParams, e: Experiment) -> np.ndarray:
    return simulate_record(P, e.u, e.h, e.psi, np.arange(len(e.t)))


def errors(P: PlantParams, e: Experiment) -> dict:
    psi = simulate(P, e)
    ok = np.isfinite(e.psi)
    d = psi[ok] - e.psi[ok]
    ys = lateral.simulate(P, _with_psi(e, psi), P.l0, P.y_off)
    okk = np.isfinite(e.y)
    dy = ys[okk] - e.y[okk]
    return {"psi_rms_rad": float(np.sqrt(np.mean(d ** 2))), "psi_max_abs_rad": float(np.max(np.abs(d))),
            "y_rms_m": float(np.sqrt(np.mean(dy ** 2))), "y_max_abs_m": float(np.max(np.abs(dy)))}


def _with_psi(e: Experiment, psi: np.ndarray) -> Experiment:
    from dataclasses import replace
    return replace(e, psi=psi)
