"""Stored runs of the plant before per-carrier parameters and the time-varying speed (issue 18):
the paper's set-up and the other set-ups of that code, so that tests/test_vehicle_plant.py can
check they are unchanged bit for bit. ``python -m tests.plant_golden`` rewrote
tests/data/plant_golden.json with the code of commit 318336a (do not regenerate it with newer
code: it is the old code path's record)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from rig_runtime.config import load
from sim_backend.plant import LiftedCarrier, Plant

H = 0.005
EVERY = 100                      # stored every EVERY steps (and the last step)
PATH = Path(__file__).resolve().parent / "data" / "plant_golden.json"


def inputs(n: int) -> np.ndarray:
    """du_f, du_r, F_y_f, F_y_r, M_z_f, M_z_r held per step: steps, pulses, side wind."""
    t = np.arange(n) * H
    U = np.zeros((n, 6))
    U[:, 1] = 1.0 * (t >= 0.5) - 2.0 * (t >= 4.0) + 0.6 * (t >= 7.0)
    U[:, 0] = 0.5 * (t >= 2.0) - 0.8 * (t >= 5.0)
    U[(t >= 3.0) & (t < 3.05), 3] = 150.0
    U[(t >= 6.0) & (t < 6.02), 5] = 1.5
    U[t >= 8.0, 2] = 40.0
    return U


def cases():
    """(name, plant constructor kwargs, reset kwargs, seconds)."""
    P = load().plant
    lin = replace(P, bouc_wen=None)
    return [
        ("paper", dict(params=P), {}, 10.0),
        ("paper_dynamic", dict(params=P, wheel_dynamics="dynamic"), {}, 10.0),
        ("paper_linear", dict(params=lin), {}, 10.0),
        ("paper_substeps4", dict(params=P, substeps=4), {}, 10.0),
        ("paper_reverse", dict(params=replace(P, v=-1.0)), {}, 3.0),
        ("rear_lifted", dict(params=P, rear_lifted=LiftedCarrier(0.28, 1.7e-3)), {"psi_ar": 0.01}, 3.0),
        ("both_contact", dict(params=replace(P, front_contact=True)), {}, 10.0),
        ("both_contact_dynamic_linear", dict(params=replace(lin, front_contact=True, v=0.5),
                                             wheel_dynamics="dynamic"), {}, 10.0),
    ]


def run(kw: dict, reset: dict, seconds: float) -> list[list[float]]:
    pl = Plant(**kw)
    pl.reset(**reset)
    n = int(round(seconds / H))
    U = inputs(n)
    rows = []

    def row():
        ft = pl.ft_readings()
        return ([pl.t] + pl.state_vector().tolist() + [pl.dw_f, pl.dw_r, pl.omega_fl, pl.omega_fr,
                                                       pl.omega_rl, pl.omega_rr]
                + [x for k in ("fl", "fr", "rl", "rr") for x in ft[k]])
    rows.append(row())
    for k, u in enumerate(U.tolist()):
        pl.step(H, *u)
        if (k + 1) % EVERY == 0 or k + 1 == n:
            rows.append(row())
    return rows


def main() -> None:
    out = {name: run(kw, reset, s) for name, kw, reset, s in cases()}
    PATH.write_text(json.dumps(out, separators=(",", ":")))
    print(PATH, PATH.stat().st_size)


if __name__ == "__main__":
    main()
