"""Speed of the simulated rig, with the stiff scipy reference as the baseline of the same run.

- ``full_path_rtf``: real-time factor of a lockstep dry run over the full protocol path
  (laser lines, CAN, Modbus TCP frames — on in-process wires with the default `sim.wires: memory` —
  the runtime's own drivers, loop, supervisor and recorder);
- ``plant_rtf``: the plant alone on the open-loop steps scenario (Fig. 3 style, the stiff
  D = 100 / D_min switching and the hysteresis);
- ``reference_rtf``: ``scipy.integrate.solve_ivp(Radau, rtol=1e-10, atol=1e-12)`` on the
  same scenario;
- ``plant_max_error_rel``: the plant's largest yaw-angle error against that reference,
  relative to the range of the yaw angle.

    python benchmarks/sim_speed.py [--plant-seconds T] [--dry-run-seconds T] [--repeat N] [--json]

``--repeat N`` runs the dry run N times and reports the median (other processes on the
machine make single runs noisy); ``cpu_steal_pct_runs`` is the CPU time the hypervisor
took away during each of them, in % of its wall time (summed over CPUs; a shared VM).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

from rig_runtime import config  # noqa: E402
from rig_runtime.scenario import load_scenario  # noqa: E402
from sim_backend import plant as plant_mod  # noqa: E402
from rig_runtime.app.dryrun import run_lockstep  # noqa: E402
from tests import plant_reference  # noqa: E402

from _machine import StealMeter  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plant-seconds", type=float, default=120.0, help="simulated seconds for plant and reference")
    ap.add_argument("--dry-run-seconds", type=float, default=15.0, help="simulated seconds of RUNNING for the full path")
    ap.add_argument("--repeat", type=int, default=1, help="dry runs; the median is reported")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    cfg = config.load()

    sc = plant_reference.scenario_open_loop_steps(cfg.plant, h=cfg.controller.h, t_end=args.plant_seconds)
    t0 = time.perf_counter()
    x = plant_reference.simulate(sc)
    t_plant = time.perf_counter() - t0
    t0 = time.perf_counter()
    x_ref = plant_reference.reference(sc)
    t_ref = time.perf_counter() - t0
    i_psi = plant_mod.STATE_NAMES.index("psi_ar")
    psi, psi_ref = x[:, i_psi], x_ref[:, i_psi]
    err_rel = float(np.max(np.abs(psi - psi_ref)) / (psi_ref.max() - psi_ref.min()))

    runs = []
    for _ in range(max(1, args.repeat)):
        with tempfile.TemporaryDirectory() as d, StealMeter() as steal:
            runs.append(run_lockstep(cfg, load_scenario("single-step"), Path(d) / "bench.h5",
                                     duration_s=args.dry_run_seconds)[0])
        runs[-1]["steal_pct"] = steal.percent
    runs.sort(key=lambda r: r["wall_time_s"] / r["cycles"])
    s = runs[len(runs) // 2]
    full_rtf = s["sim_time_s"] / s["wall_time_s"]

    out = {"full_path_rtf": full_rtf, "plant_rtf": args.plant_seconds / t_plant,
           "reference_rtf": args.plant_seconds / t_ref, "plant_max_error_rel": err_rel,
           "plant_us_per_step": t_plant / len(sc.inputs) * 1e6,
           "full_path_us_per_cycle": s["wall_time_s"] / s["cycles"] * 1e6,
           "full_path_per_plant_step": (s["wall_time_s"] / s["cycles"]) / (t_plant / len(sc.inputs)),
           "plant_seconds": args.plant_seconds, "dry_run_sim_seconds": s["sim_time_s"],
           "full_path_rtf_runs": [r["sim_time_s"] / r["wall_time_s"] for r in runs],
           "cpu_steal_pct_runs": [r["steal_pct"] for r in runs]}
    if args.json:
        print(json.dumps(out))
    else:
        print(f"full protocol path (lockstep dry run): {full_rtf:6.1f}x real time  ({out['full_path_us_per_cycle']:.0f} us per 5 ms cycle)")
        print(f"plant alone:                           {out['plant_rtf']:6.1f}x real time  ({out['plant_us_per_step']:.1f} us per step)")
        print(f"scipy Radau reference (same scenario): {out['reference_rtf']:6.1f}x real time")
        print(f"plant / reference speed: {out['plant_rtf'] / out['reference_rtf']:.1f}x; "
              f"largest yaw-angle error: {err_rel:.2e} of its range")
    return 0


if __name__ == "__main__":
    sys.exit(main())
