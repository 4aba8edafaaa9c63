"""The observer's estimate against the simulated truth over a lockstep dry run
(docs/observer.md): RMS and largest |ŷ − y_true| after a start-up, per observed carrier,
and the largest innovation statistic seen (the false-alarm margin).

    python benchmarks/observer_accuracy.py [SCENARIO] [--duration S] [--seeds 0 1 ...] [--config FILE]
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
from rig_runtime.app.dryrun import TRUTH_GROUP, run_lockstep  # noqa: E402
from rig_runtime.scenario import load_scenario  # noqa: E402


def judge(log: Path, startup_s: float = 2.0) -> dict:
    """Per observed carrier: RMS and max |ŷ − y_true| (m) over RUNNING after ``startup_s``,
    and the largest window statistic of each measurement."""
    with h5py.File(log, "r") as f:
        cols = [c.decode() if isinstance(c, bytes) else c for c in f["cycles"].attrs["columns"]]
        data = {c: f["cycles"][c][:] for c in cols}
        tr = {k: f[TRUTH_GROUP][k][:] for k in f[TRUTH_GROUP]}
    t = data["t"]
    idx = np.searchsorted(tr["t"], t - 1e-9)
    idx = np.clip(idx, 0, len(tr["t"]) - 1)
    running = data["state"] == 2.0
    t_run = data["t_run"]
    out = {}
    for car, key in (("rear", "y_r"), ("front", "y_f")):
        if f"{car}_obs_y_hat" not in data:
            continue
        e = data[f"{car}_obs_y_hat"] - tr[key][idx]
        sel = running & (t_run >= startup_s)
        out[car] = {"rms_mm": float(np.sqrt(np.mean(e[sel] ** 2)) * 1e3),
                    "max_mm": float(np.max(np.abs(e[sel])) * 1e3),
                    "n": int(sel.sum()),
                    **{f"max_T_{m}": float(np.nanmax(data[f"{car}_obs_T_{m}"][running]))
                       for m in ("lat", "psi", "dw")}}
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenario", nargs="?", default="step-sequence")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--seeds", type=int, nargs="*", default=[0])
    ap.add_argument("--config", default=None)
    ap.add_argument("--chi2", type=float, default=None, help="limits.innovation_chi2 for this run")
    a = ap.parse_args()
    cfg = config.load(a.config)
    if a.chi2 is not None:
        cfg = dataclasses.replace(cfg, limits=dataclasses.replace(cfg.limits, innovation_chi2=a.chi2))
    sc = load_scenario(a.scenario)
    for seed in a.seeds:
        with tempfile.TemporaryDirectory() as d:
            log = Path(d) / "run.h5"
            summary, code = run_lockstep(cfg, sc, log, seed=seed, duration_s=a.duration)
            res = judge(log)
        print(f"{a.scenario} seed={seed} final={summary['final_state']} faults="
              f"{[(f['t'] - summary['run_started_t'], f['device'], f['check'], f['message']) for f in summary['faults']]} "
              f"wall_us/cycle={summary['wall_us_per_cycle']:.0f}")
        for car, r in res.items():
            print("  ", car, {k: (round(v, 4) if isinstance(v, float) and math.isfinite(v) else v) for k, v in r.items()})


if __name__ == "__main__":
    main()
