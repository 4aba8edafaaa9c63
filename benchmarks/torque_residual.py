"""The torque response rule's margin on healthy runs (docs/safety.md, "Drive outages"):
every fault-free shipped scenario given here, in lockstep with ``degraded.on_drive_loss:
reallocate``, for each seed; per run the largest residual the rule judged (a drive's
reported torque actual against its latest commands, while they were all at least
``degraded.torque_residual_A``) and whether anything was reconfigured (a false detection).

    python benchmarks/torque_residual.py [--seeds 0-9] [--scenario sim.yaml:single-step ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from rig_runtime.safety import supervisor as supervisor_module  # noqa: E402
from rig_runtime.scenario import load_scenario  # noqa: E402

PLAN = ("sim.yaml:single-step", "sim.yaml:robustness", "vehicle.yaml:vehicle-steps",
        "vehicle.yaml:vehicle-reverse", "vehicle.yaml:vehicle-reversal")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-9", help="a range a-b or a comma list")
    ap.add_argument("--scenario", action="append", help="CONFIG:SCENARIO (default: the fault-free shipped ones)")
    a = ap.parse_args()
    if "-" in a.seeds:
        lo, hi = (int(x) for x in a.seeds.split("-"))
        seeds = list(range(lo, hi + 1))
    else:
        seeds = [int(x) for x in a.seeds.split(",")]
    sups = []
    init = supervisor_module.Supervisor.__init__

    def keep(self, *args, **kw):           # the run's supervisor, to read its statistics after
        init(self, *args, **kw)
        sups.append(self)
    supervisor_module.Supervisor.__init__ = keep
    from tests.e2e import run               # noqa: E402 - after the hook
    worst, false = 0.0, 0
    for seed in seeds:
        for item in a.scenario or PLAN:
            cfg_name, scen = item.split(":")
            cfg = config.load(config.resolve_config_path(cfg_name))
            cfg = dataclasses.replace(cfg, degraded=dataclasses.replace(cfg.degraded, on_drive_loss="reallocate"))
            t0 = time.time()
            r = run(Path(tempfile.mkdtemp(prefix="torque-residual-")), load_scenario(scen), cfg=cfg, seed=seed)
            s = r.summary
            m = max(sups[-1].torque_residual_max.values(), default=0.0)
            n = len(s.get("reconfigured", []))
            worst, false = max(worst, m), false + n
            print(f"seed {seed} {cfg_name} {scen}: {s['final_state']}, faults {len(s['faults'])}, reconfigured {n}, "
                  f"largest judged residual {m:.4f} A ({time.time() - t0:.0f} s wall)", flush=True)
    print(f"largest healthy residual {worst:.4f} A; runs with a reconfiguration: {false}")
    return 0 if false == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
