"""An independent construction of the coupled vehicle loop with python-control: the same blocks
— the lateral pair (2a)/(2b), each carrier's yaw dynamics (6), each carrier's PI (scheduled by
g = v_d/v) and PD with its differentiator s/(T_f s + 1) — connected by name with
``control.interconnect``. Its closed-loop poles at v = ±1 must match `rig tune --json`'s
"coupled" list; the sampled loop (plant by ZOH, PI and PD by Tustin, ``control.c2d``) must
match the spectral radius of "coupled_sampled" and the poles of coupled.sampled_matrix.

Tolerance: 1e-6 relative (plus 1e-6 1/s) per pole, matched as sorted sets. Both sides are
eigenvalue problems of 10 (continuous) / 14 (sampled) states in double precision; the equal
carriers of the first config give repeated pole pairs whose computed values scatter by
~1e-8 relative, well inside it. The second config (carriers differing by 30 %) has simple poles.
"""

from __future__ import annotations

import json
import subprocess
import sys
import warnings

import numpy as np
import pytest

control = pytest.importorskip("control")     # the `test` extra installs it (pyproject.toml)

from rig_runtime import config, coupled   # noqa: E402
from tests.vehicle_configs import write_vehicle   # noqa: E402

from .conftest import ROOT   # noqa: E402

REL, ABS = 1e-6, 1e-6


@pytest.fixture(scope="module", params=["equal", "differing"])
def vehicle(request, tmp_path_factory):
    d = tmp_path_factory.mktemp(request.param)
    plant = {} if request.param == "equal" else {
        "front": {"omega0": 18.774 * 1.3, "K": 6.2937e-3 * 0.8, "D_min": 2.1701 * 0.9, "l0": 0.27625 * 1.2},
        "rear": {"delta0": 0.0626982 * 0.8, "D_max": 70.0}}
    ctl = {} if request.param == "equal" else {
        "front": {"K_P_y": 6.0, "K_I_y": 0.8, "K_P_psi": 45.0, "K_D_psi": 4.5, "T_f_psi": 0.03}}
    path = write_vehicle(d, plant=plant, controller=ctl)
    out = subprocess.run([sys.executable, "-m", "rig_runtime", "tune", "--json", "--config", str(path)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.stdout, out.stderr
    return config.load(path), json.loads(out.stdout)


def _blocks(cfg, v: float, dt=None):
    """The vehicle's blocks, named; continuous (dt None) or sampled at dt."""
    lay = coupled.layout(cfg)
    g = coupled.gain_factor(cfg, v)
    P = {c: cfg.plant.carrier(c) for c in lay.carriers}
    a = {c: P[c].c_y * v / (2 * P[c].l0) for c in lay.carriers}
    lat = control.ss([[a["front"], -a["front"]], [a["rear"], -a["rear"]]],
                     [[P["front"].c_y * v, 0.0], [0.0, P["rear"].c_y * v]], np.eye(2), np.zeros((2, 2)),
                     inputs=["psi_front", "psi_rear"], outputs=["y_front", "y_rear"], name="lateral")
    plants, ctrls = [lat], []
    for c in lay.carriers:
        p = P[c]
        w2 = p.omega0 ** 2
        plants.append(control.ss([[0.0, 1.0], [-w2, -2 * p.D_min * p.omega0]], [[0.0], [p.K * w2]],
                                 [[1.0, 0.0]], [[0.0]], inputs=f"u_{c}", outputs=f"psi_{c}", name=f"yaw_{c}"))
        G = cfg.controller.gains(c)
        pi = control.tf([g * G.K_P_y, g * G.K_I_y], [1.0, 0.0])
        pd = control.tf([G.K_P_psi * G.T_f_psi + G.K_D_psi, G.K_P_psi], [G.T_f_psi, 1.0])
        if dt is not None:
            pi, pd = control.c2d(pi, dt, "tustin"), control.c2d(pd, dt, "tustin")
        ctrls += [control.summing_junction(inputs=[f"yref_{c}", f"-y_{c}"], output=f"ey_{c}", name=f"sum_y_{c}"),
                  control.tf2ss(pi, inputs=f"ey_{c}", outputs=f"psiref_{c}", name=f"pi_{c}"),
                  control.summing_junction(inputs=[f"psiref_{c}", f"-psi_{c}"], output=f"epsi_{c}",
                                           name=f"sum_psi_{c}"),
                  control.tf2ss(pd, inputs=f"epsi_{c}", outputs=f"u_{c}", name=f"pd_{c}")]
    if dt is not None:
        plant = control.interconnect(plants, inplist=["u_front", "u_rear"], outlist=["y_front", "y_rear",
                                                                                      "psi_front", "psi_rear"])
        plant = control.c2d(control.ss(plant.A, plant.B, plant.C, plant.D, inputs=["u_front", "u_rear"],
                                       outputs=["y_front", "y_rear", "psi_front", "psi_rear"]), dt, "zoh")
        plant = control.ss(plant.A, plant.B, plant.C, plant.D, dt, inputs=["u_front", "u_rear"],
                           outputs=["y_front", "y_rear", "psi_front", "psi_rear"], name="plant")
        plants = [plant]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return control.interconnect(plants + ctrls, inplist=["yref_front", "yref_rear"],
                                    outlist=["y_front", "y_rear"])


def _match(got, want):
    got, want = np.sort_complex(np.asarray(got)), np.sort_complex(np.asarray(want))
    assert len(got) == len(want)
    err = np.abs(got - want)
    assert np.all(err <= REL * np.abs(want) + ABS), (got, want)


@pytest.mark.parametrize("v", [1.0, -1.0])
def test_continuous_poles_match_rig_tune(vehicle, v):
    cfg, tune = vehicle
    assert coupled.layout(cfg).controlled == ("front", "rear")
    (entry,) = [p for p in tune["coupled"] if p["v"] == v]
    mine = np.array([complex(re, im) for re, im in entry["eigenvalues"]])
    theirs = _blocks(cfg, v).poles()
    _match(theirs, mine)
    assert entry["stable"] == bool(np.all(theirs.real < 0))


@pytest.mark.parametrize("v", [1.0, -1.0])
def test_sampled_poles_match(vehicle, v):
    cfg, tune = vehicle
    h = cfg.controller.h
    theirs = _blocks(cfg, v, dt=h).poles()
    lay = coupled.layout(cfg)
    mine = np.linalg.eigvals(coupled.sampled_matrix(cfg, v, coupled.d_min(cfg, lay.carriers), lay))
    # the implemented controller carries e_y,prev and e_psi,prev as states: poles at z = 0 that a
    # minimal Tustin realisation does not have
    mine = mine[np.abs(mine) > 1e-9]
    theirs = theirs[np.abs(theirs) > 1e-9]
    _match(theirs, mine)
    (entry,) = [p for p in tune["coupled_sampled"] if p["v"] == v]
    if entry["D"] == coupled.d_min(cfg, lay.carriers):       # the radius at D_min is the reported one
        assert np.max(np.abs(theirs)) == pytest.approx(entry["spectral_radius"], rel=REL)
    else:
        assert np.max(np.abs(theirs)) <= entry["spectral_radius"] * (1 + REL)
