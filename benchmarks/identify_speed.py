"""Time of `rig identify` on the standard experiment set, per step of the procedure.

Records the four shipped experiment scenarios (ident-free-response, ident-steps, ident-sine,
open-loop-steps) in lockstep on the shipped simulated plant (or reuses logs given with
``--logs DIR``), then runs the identification ``--repeat`` times and reports the median wall
time per step, the total, the CPU time, the load average and the CPU time the hypervisor
stole (a shared 2-core VM). Also prints the identified values next to Table 3's.

    python benchmarks/identify_speed.py [--logs DIR] [--repeat N] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from rig_runtime.app.identify import procedure  # noqa: E402
from rig_runtime.app.identify.experiments import load_experiment  # noqa: E402

from _machine import StealMeter  # noqa: E402

TABLE3 = {"omega0": 18.8, "D_min": 2.2, "D_max": 100, "c_udot_max": 3.0e-5, "K": 6.3e-3, "psi_off": -1.4e-3,
          "bouc_wen.a": 0.48, "bouc_wen.beta": 7362, "bouc_wen.gamma": -7164}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", help="directory with the four logs (<scenario>.h5); recorded if missing")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    cfg = config.load()
    d = Path(args.logs) if args.logs else Path(tempfile.mkdtemp(prefix="identify-bench-"))
    d.mkdir(parents=True, exist_ok=True)
    names = ("open-loop-steps", "ident-free-response", "ident-steps", "ident-sine")
    t_rec = 0.0
    for n in names:
        if not (d / f"{n}.h5").exists():
            from rig_runtime.scenario import load_scenario
            from rig_runtime.app.dryrun import run_lockstep
            t0 = time.perf_counter()
            run_lockstep(cfg, load_scenario(n), d / f"{n}.h5")
            t_rec += time.perf_counter() - t0
    runs = []
    for _ in range(max(1, args.repeat)):
        with StealMeter() as steal:
            ch0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            c0, t0 = time.process_time(), time.perf_counter()
            exps = [load_experiment(d / f"{n}.h5") for n in names]
            t_load = time.perf_counter() - t0
            r = procedure.run(cfg.plant, exps)
            wall = time.perf_counter() - t0
            cpu = time.process_time() - c0
            ch1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu_workers = (ch1.ru_utime + ch1.ru_stime) - (ch0.ru_utime + ch0.ru_stime)
        runs.append({"wall_s": wall, "cpu_s_main_process": cpu, "cpu_s_workers": cpu_workers, "load_s": t_load, "steps_s": r["timing_s"],
                     "steal_pct": steal.percent, "loadavg_1min": os.getloadavg()[0]})
    runs.sort(key=lambda x: x["wall_s"])
    med = runs[len(runs) // 2]
    par = {k: v["value"] for k, v in r["parameters"].items()}
    out = {"median": med, "walls_s": [x["wall_s"] for x in runs], "record_s": t_rec, "logs": str(d),
           "parameters": par, "table3": TABLE3,
           "verification_psi_rms_rad": r["verification"]["identified"][0]["psi_rms_rad"],
           "true_model_psi_rms_rad": r["verification"]["configured"][0]["psi_rms_rad"]}
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"logs: {d} (recorded in {t_rec:.1f} s)" if t_rec else f"logs: {d}")
    print(f"identification of the standard set: median {med['wall_s']:.1f} s wall "
          f"(runs: {', '.join(f'{x:.1f}' for x in out['walls_s'])}), CPU {med['cpu_s_main_process']:.1f} s main + "
          f"{med['cpu_s_workers']:.1f} s Jacobian workers, "
          f"load average {med['loadavg_1min']:.1f}, steal {med['steal_pct']:.1f} %" if med['steal_pct'] is not None
          else f"load average {med['loadavg_1min']:.1f}")
    print("per step (s): " + ", ".join(f"{k} {v:.2f}" for k, v in med["steps_s"].items()))
    print("\nparameter        identified    Table 3")
    for k, v in TABLE3.items():
        print(f"{k:<16}{par[k]:>12.4g}{v:>11.4g}")
    print(f"\nverification yaw RMS: identified {out['verification_psi_rms_rad']:.3g} rad, "
          f"true (configured) model {out['true_model_psi_rms_rad']:.3g} rad")
    return 0


if __name__ == "__main__":
    sys.exit(main())
