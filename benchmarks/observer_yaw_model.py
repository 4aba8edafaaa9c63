"""The hysteresis and damping law in the observer's model, in and out (docs/observer.md,
"The hysteresis and the damping in the model"): healthy lockstep dry runs with
``observer.yaw_model`` on and off and a choice of ``observer.q_psi_acc``; per observed
carrier the innovations' RMS normalised by the design's steady-state √S (1 when the model's
noise is what the innovations show; below 1 where the process noise overstates what the
model leaves out), the largest window statistic per measurement, and ŷ − y_true after 2 s.

    python benchmarks/observer_yaw_model.py SCENARIO [--config FILE] [--duration S] [--seeds 0 ...]
        [--q 0.5 0.05 ...] [--yaw on off]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
from pathlib import Path

import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from rig_runtime.app import observer_design as od  # noqa: E402
from rig_runtime.app.dryrun import TRUTH_GROUP, run_lockstep  # noqa: E402
from rig_runtime.observer import JointCarrier  # noqa: E402
from rig_runtime.scenario import load_scenario  # noqa: E402


def steady_std(cfg, carrier: str) -> dict[str, float]:
    """√S of the carrier's lateral, ψ and Δω innovation at the config's design speed (all
    lasers in use)."""
    d = od.designs(cfg)[carrier]
    if isinstance(d, JointCarrier):
        S = d.joint.S[0]
        i = 0 if carrier == "front" else 1
        return {"lat": math.sqrt(S[i]), "psi": math.sqrt(S[2 + i]), "dw": math.sqrt(S[4 + i])}
    return {m: math.sqrt(s) for m, s in zip(("lat", "psi", "dw"), d.S_full)}


def judge(log: Path, cfg, startup_s: float = 2.0) -> dict:
    with h5py.File(log, "r") as f:
        cyc = f["cycles"]
        cols = [c.decode() if isinstance(c, bytes) else c for c in cyc.attrs["columns"]]
        data = {c: cyc[c][:] for c in cols}
        tr = {k: f[TRUTH_GROUP][k][:] for k in f[TRUTH_GROUP]}
    idx = np.clip(np.searchsorted(tr["t"], data["t"] - 1e-9), 0, len(tr["t"]) - 1)
    sel = (data["state"] == 2.0) & (data["t_run"] >= startup_s)
    out = {}
    for car, key in (("front", "y_f"), ("rear", "y_r")):
        if f"{car}_obs_y_hat" not in data:
            continue
        sd = steady_std(cfg, car)
        r = {}
        for m in ("lat", "psi", "dw"):
            nu = data[f"{car}_obs_nu_{m}"][sel]
            nu = nu[np.isfinite(nu)]
            r[f"rms_nu_{m}/sqrtS"] = float(np.sqrt(np.mean(nu ** 2)) / sd[m]) if nu.size else math.nan
            r[f"max_T_{m}"] = float(np.nanmax(data[f"{car}_obs_T_{m}"][sel]))
        e = data[f"{car}_obs_y_hat"][sel] - tr[key][idx][sel]
        r["err_rms_mm"] = float(np.sqrt(np.mean(e ** 2)) * 1e3)
        r["err_max_mm"] = float(np.max(np.abs(e)) * 1e3)
        out[car] = r
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenario")
    ap.add_argument("--config", default=None)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--seeds", type=int, nargs="*", default=[0])
    ap.add_argument("--q", type=float, nargs="*", default=[None], help="observer.q_psi_acc (default: the config's)")
    ap.add_argument("--yaw", nargs="*", default=["on", "off"], choices=["on", "off"])
    a = ap.parse_args()
    base = config.load(a.config)
    sc = load_scenario(a.scenario)
    for q in a.q:
        for yaw in a.yaw:
            o = dataclasses.replace(base.observer, yaw_model=(yaw == "on"),
                                    **({} if q is None else {"q_psi_acc": q}))
            cfg = dataclasses.replace(base, observer=o)
            for seed in a.seeds:
                with tempfile.TemporaryDirectory() as d:
                    log = Path(d) / "run.h5"
                    summary, _ = run_lockstep(cfg, sc, log, seed=seed, duration_s=a.duration)
                    res = judge(log, cfg)
                print(f"{a.scenario} q_psi_acc={o.q_psi_acc:g} yaw_model={yaw} seed={seed} "
                      f"final={summary['final_state']} faults={[(f['device'], f['check']) for f in summary['faults']]}",
                      flush=True)
                for car, r in res.items():
                    print("   ", car, " ".join(f"{k} {v:.3g}" for k, v in r.items()), flush=True)


if __name__ == "__main__":
    main()
