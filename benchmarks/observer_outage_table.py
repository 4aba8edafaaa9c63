"""Which lateral-laser losses the vehicle can carry (docs/observer.md, "Degraded mode on the
vehicle"): the steady-state Riccati σ of ŷ's error per carrier, per lost laser, per speed and
direction — the joint filter's outage tables (``observer_design.joint_design``) beside the
per-carrier filters' (``observer_design.design``, which drop both lateral lasers on any loss),
against ``degraded.sigma_y_max``.

    python benchmarks/observer_outage_table.py [--config configs/vehicle.yaml] [--speeds 1 0.5 ...]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):     # as the `rig` command does
    os.environ.setdefault(_v, "1")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from rig_runtime.app import observer_design as od  # noqa: E402

LOST = {1: "b_r", 2: "b_f", 3: "b_f+b_r"}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="configs/vehicle.yaml")
    ap.add_argument("--speeds", type=float, nargs="*", default=[1.5, 1.0, 0.5, 0.2, 0.1])
    a = ap.parse_args()
    cfg = config.load(a.config)
    h, bound = cfg.controller.h, cfg.degraded.sigma_y_max
    k = round(0.1 / h)
    print(f"sigma_y bound {bound * 1e6:g} um; k = {k} cycles = 0.1 s; 'end': the table's last value "
          f"(levelled off, or at degraded.max_s = {cfg.degraded.max_s:g} s)")
    print("| v (m/s) | lost | joint: front 0.1 s / end | joint: rear 0.1 s / end | carried | per-carrier: front / rear end |")
    print("| --- | --- | --- | --- | --- | --- |")
    for sp in a.speeds:
        for v in (sp, -sp):
            j = od.joint_design(cfg, v=v)
            per = [od.design(cfg, c, v=v).sigma_y_outage for c in ("front", "rear")]
            for s, name in LOST.items():
                f, r = j.sigma_y[s]
                over = [next((i for i, x in enumerate(t) if x > bound), None) for t in (f, r)]
                over = [i for i in over if i is not None]
                ok = "yes" if not over else f"NO: bound after {min(over) * h:.2f} s"
                pc = " / ".join(f"{t[-1] * 1e6:.1f}" for t in per) if s == 3 else "(as b_f+b_r)"
                print(f"| {v:+g} | {name} | {f[min(k, len(f) - 1)] * 1e6:.2f} / {f[-1] * 1e6:.2f} | "
                      f"{r[min(k, len(r) - 1)] * 1e6:.2f} / {r[-1] * 1e6:.2f} | {ok} | {pc} |")


if __name__ == "__main__":
    main()
