"""A lateral laser lost on the vehicle (docs/observer.md, "Degraded mode on the vehicle"):
b_f or b_r silent (dropout) for DURATION s from T0 s of vehicle-steps (v = +1) or
vehicle-reverse (v = −1), lockstep on the shipped configs/vehicle.yaml. Per run: the DEGRADED
intervals and how they ended, how the run ended, and the largest |ŷ − y_true| of either
carrier while the laser was out (the acceptance: within 0.1 mm).

    python benchmarks/observer_loss.py [--lasers b_f b_r] [--v 1 -1] [--t0 4] [--duration 6] [--seed 0]
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


def error_during(log: Path, t_a: float, t_b: float) -> float:
    """Largest |ŷ − y_true| of both carriers over run time [t_a, t_b] (mm)."""
    with h5py.File(log, "r") as f:
        cyc = f["cycles"]
        t, tr_run = cyc["t"][:], cyc["t_run"][:]
        tr = {k: f[TRUTH_GROUP][k][:] for k in f[TRUTH_GROUP]}
        idx = np.clip(np.searchsorted(tr["t"], t - 1e-9), 0, len(tr["t"]) - 1)
        sel = (cyc["state"][:] == 2.0) & (tr_run >= t_a) & (tr_run <= t_b)
        return max(float(np.max(np.abs(cyc[f"{c}_obs_y_hat"][:][sel] - tr[k][idx][sel]))) * 1e3
                   for c, k in (("front", "y_f"), ("rear", "y_r")))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="vehicle.yaml")
    ap.add_argument("--lasers", nargs="*", default=["b_f", "b_r"])
    ap.add_argument("--v", type=float, nargs="*", default=[1.0, -1.0])
    ap.add_argument("--t0", type=float, default=4.0)
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    cfg = config.load(config.resolve_config_path(a.config))
    print(f"{a.config}: controller.law {cfg.controller.law}, innovation_chi2 {cfg.limits.innovation_chi2}, "
          f"q_psi_acc {cfg.observer.q_psi_acc}, yaw_model {cfg.observer.yaw_model}", flush=True)
    print("| v | lost | DEGRADED (run time) | ended by | run ends | max abs(ŷ − y_true) while lost |")
    print("| --- | --- | --- | --- | --- | --- |")
    for v in a.v:
        base = load_scenario("vehicle-steps" if v > 0 else "vehicle-reverse")
        for laser in a.lasers:
            sc = dataclasses.replace(base, faults=(FaultInjection(kind="dropout", t=a.t0, duration_s=a.duration,
                                                                  device=laser),), expect_fault=None)
            with tempfile.TemporaryDirectory() as d:
                log = Path(d) / "run.h5"
                summary, _ = run_lockstep(cfg, sc, log, seed=a.seed, duration_s=a.t0 + a.duration + 4.0)
                err = error_during(log, a.t0, a.t0 + a.duration)
            t0 = summary["run_started_t"]
            degr = summary.get("degraded") or []
            spans = sorted({(round(dd["t_start"] - t0 if dd["t_start"] > t0 / 2 else dd["t_start"], 3),
                             round((dd["t_end"] - t0 if dd["t_end"] > t0 / 2 else dd["t_end"]) if dd.get("t_end") is not None else -1, 3),
                             dd.get("end", "")) for dd in degr})
            end = summary["final_state"] + ("" if not summary["faults"] else " " + ", ".join(
                f"{f['check']} {f['device']}" for f in summary["faults"]))
            print(f"| {v:+g} | {laser} | {'; '.join(f'{s[0]:.3f}–{s[1]:.3f} s' for s in spans) or '-'} | "
                  f"{'; '.join(s[2] for s in spans) or '-'} | {end} | {err:.4f} mm |", flush=True)


if __name__ == "__main__":
    main()
