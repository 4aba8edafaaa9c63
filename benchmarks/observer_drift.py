"""Drifting lasers on the vehicle with the innovation rule on (docs/observer.md, "Drift"):
each named laser's reading creeps off the truth at RATE mm/s from T0 s of vehicle-steps
(v = +1) or vehicle-reverse (v = −1), in lockstep on ``--config`` (default configs/vehicle.yaml;
``--chi2``/``--window`` set limits.innovation_chi2/innovation_window for the run if given).
Per run: when and on what the first innovation finding came (the event or fault), the
drifting laser's bias then, and how the run ended; then a table.

    python benchmarks/observer_drift.py [--lasers b_f b_r s_fl ...] [--rates 0.05 0.1] [--v 1 -1]
        [--t0 4] [--duration 12] [--seed 0]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import h5py  # noqa: E402
import numpy as np  # noqa: E402

from rig_runtime import config  # noqa: E402
from rig_runtime.app.dryrun import TRUTH_GROUP, run_lockstep  # noqa: E402
from rig_runtime.scenario import FaultInjection, load_scenario  # noqa: E402

LASERS = ("b_f", "b_r", "s_fl", "s_fr", "s_rl", "s_rr")


def first_finding(summary: dict) -> tuple[float, str, str] | None:
    """(run time, device, how) of the first innovation finding: a fault, or a DEGRADED interval
    that began on the innovation check."""
    t0 = summary["run_started_t"]
    cands = [(f["t"] - t0, f["device"], "FAULT") for f in summary["faults"] if f["check"] == "innovation"]
    cands += [(d["t_start"] - t0 if d["t_start"] > t0 / 2 else d["t_start"], d["laser"], "DEGRADED")
              for d in summary.get("degraded") or [] if d.get("check") == "innovation"]
    return min(cands) if cands else None


def worst_error_mm(log: Path) -> float:
    """Largest |ŷ − y_true| over RUNNING after 2 s, both carriers (mm)."""
    with h5py.File(log, "r") as f:
        cyc = f["cycles"]
        t, st, tr_run = cyc["t"][:], cyc["state"][:], cyc["t_run"][:]
        tr = {k: f[TRUTH_GROUP][k][:] for k in f[TRUTH_GROUP]}
        idx = np.clip(np.searchsorted(tr["t"], t - 1e-9), 0, len(tr["t"]) - 1)
        sel = (st == 2.0) & (tr_run >= 2.0)
        return max(float(np.max(np.abs(cyc[f"{c}_obs_y_hat"][:][sel] - tr[k][idx][sel]))) * 1e3
                   for c, k in (("front", "y_f"), ("rear", "y_r")))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="vehicle.yaml")
    ap.add_argument("--lasers", nargs="*", default=list(LASERS))
    ap.add_argument("--rates", type=float, nargs="*", default=[0.05, 0.1])
    ap.add_argument("--v", type=float, nargs="*", default=[1.0, -1.0])
    ap.add_argument("--t0", type=float, default=4.0)
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--chi2", type=float, default=None)
    ap.add_argument("--window", type=int, default=None)
    a = ap.parse_args()
    cfg = config.load(config.resolve_config_path(a.config))
    lim = cfg.limits
    if a.chi2 is not None:
        lim = dataclasses.replace(lim, innovation_chi2=a.chi2)
    if a.window is not None:
        lim = dataclasses.replace(lim, innovation_window=a.window)
    cfg = dataclasses.replace(cfg, limits=lim)
    print(f"{a.config}: innovation_chi2 {lim.innovation_chi2}, window {lim.innovation_window}; drift from {a.t0} s, "
          f"seed {a.seed}", flush=True)
    rows = []
    for v in a.v:
        base = load_scenario("vehicle-steps" if v > 0 else "vehicle-reverse")
        for rate in a.rates:
            for laser in a.lasers:
                sc = dataclasses.replace(base, faults=(FaultInjection(kind="drift", t=a.t0, device=laser,
                                                                      rate_mm_s=rate),), expect_fault=None)
                with tempfile.TemporaryDirectory() as d:
                    log = Path(d) / "run.h5"
                    summary, _ = run_lockstep(cfg, sc, log, seed=a.seed, duration_s=a.duration)
                    err = worst_error_mm(log)
                ff = first_finding(summary)
                if ff is None:
                    found, bias, named, how = "-", "-", "-", "-"
                else:
                    found, bias, named, how = f"{ff[0]:.3f} s", f"{rate * (ff[0] - a.t0):.3f} mm", ff[1], ff[2]
                right = ff is not None and laser in ff[1].replace("|", "/").split("/")
                end = summary["final_state"] + ("" if not summary["faults"] else
                                                " " + ", ".join(f"{f['check']} {f['device']}" for f in summary["faults"]))
                row = (f"{v:+g}", f"{rate:g}", laser, found, bias, named + ("" if right or ff is None else " (WRONG)"),
                       how, end, f"{err:.3f}")
                rows.append(row)
                print(" | ".join(row), flush=True)
    print("\n| v | mm/s | drifting | found (run time) | bias then | named | as | end | max abs(ŷ − y_true) mm |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
