"""Issue 25's disturbance demand on lockstep runs of a vehicle config: lateral pulses and side
forces on either carrier (as the `robustness` scenario, on the vehicle), each carrier's reference 0;
the time after each pulse ends (and after a side force starts or stops) until both carriers are
back within 0.1 mm (demand: ≤ 3 s after a pulse).

    .venv/bin/python -m benchmarks.vehicle_robustness [--config configs/vehicle.yaml] [--speeds 1,-1]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import h5py
import numpy as np

from rig_runtime import config
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.scenario import load_scenario

SCENARIO = """name: vehicle-robustness
description: pulses and side forces on either carrier of the vehicle
duration_s: 70
speed: [{{t: 0, v: {v}}}]
reference:
  front: [{{t: 0, y_mm: 0}}]
  rear: [{{t: 0, y_mm: 0}}]
disturbances:
  - {{kind: pulse, carrier: front, t: 10, duration_s: 0.3, F_y: 150}}
  - {{kind: pulse, carrier: rear, t: 15, duration_s: 0.3, F_y: 300}}
  - {{kind: pulse, carrier: front, t: 20, duration_s: 0.3, F_y: 500}}
  - {{kind: constant, carrier: rear, t: 25, duration_s: 10, F_y: 100}}
  - {{kind: constant, carrier: front, t: 45, duration_s: 10, F_y: -100}}
"""
EVENTS = ((10.3, "150 N pulse on the front ends"), (15.3, "300 N pulse on the rear ends"),
          (20.3, "500 N pulse on the front ends"), (25.0, "100 N on the rear starts"),
          (35.0, "100 N on the rear stops"), (45.0, "-100 N on the front starts"),
          (55.0, "-100 N on the front stops"))
WINDOW_S = 4.6          # up to the next event


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(config.CONFIG_DIR / "vehicle.yaml"))
    ap.add_argument("--speeds", default="1,-1")
    a = ap.parse_args(argv)
    cfg = config.load(a.config)
    with tempfile.TemporaryDirectory() as d:
        for v in (float(x) for x in a.speeds.split(",")):
            sc = Path(d) / f"rob{v:+g}.yaml"
            sc.write_text(SCENARIO.format(v=v))
            log = Path(d) / f"rob{v:+g}.h5"
            summary, code = run_lockstep(cfg, load_scenario(sc), log)
            with h5py.File(log) as f:
                c = {k: f["cycles"][k][()] for k in ("t_run", "y_f", "y_r", "front_u_cmd", "rear_u_cmd")}
            t = c["t_run"]
            print(f"v = {v:+g} m/s: exit {code}, faults {summary.get('faults')}, peak |u| "
                  f"{max(np.abs(c['front_u_cmd']).max(), np.abs(c['rear_u_cmd']).max()):.2f} A")
            for t0, what in EVENTS:
                sel = (t >= t0) & (t < t0 + WINDOW_S)
                y = np.maximum(np.abs(c["y_f"][sel]), np.abs(c["y_r"][sel]))
                out = np.nonzero(y > 1e-4)[0]
                back = 0.0 if not len(out) else (t[sel][out[-1] + 1] - t0 if out[-1] + 1 < len(y) else float("inf"))
                print(f"  {what:32s} peak {1e3 * y.max():.3f} mm, within 0.1 mm after {back:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
