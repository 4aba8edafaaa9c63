"""The observer's cost per cycle in a lockstep run (docs/observer.md, "Cost"): the loop's
``_estimate`` stage — the observer's whole work per cycle: the lateral lasers' and F/T
sensors' fitness, the forces, the filter step (on the vehicle: the running gear's filter,
both carriers) and the degraded marks — and, in a run of its own (so that neither timing is
inside the other), the filter's ``step`` alone; medians per cycle of the thread's CPU time
(``time.thread_time_ns``: what other processes on a shared machine take is not counted; each
timing includes one clock read, ~0.2 µs).

Each run is a fresh process; with ``--base DIR`` (another checkout of the project, e.g. a
copy of main) the runs alternate between the two trees, so both see the same load:

    python benchmarks/observer_cost.py [--config configs/vehicle.yaml] [--scenario vehicle-steps]
        [--duration S] [--repeat N] [--base DIR] [--linear]

``--linear``: the filter without the hysteresis and damping law in its model
(``observer.yaw_model: false``), for the comparison.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent


def child(tree: str, config_path: str, scenario: str, duration: float, linear: bool, what: str) -> dict:
    """One lockstep run with the tree ``tree`` first on sys.path: the median (µs) per cycle of
    ``what`` (``_estimate``: the loop's stage; ``step``: the observer's step)."""
    sys.path.insert(0, tree)
    import dataclasses
    import tempfile
    import time

    from rig_runtime import config, observer
    from rig_runtime.app import dryrun
    from rig_runtime.loop import ControlLoop
    from rig_runtime.scenario import load_scenario

    clock = time.thread_time_ns
    samples: dict[str, list[int]] = {what: []}

    def timed(cls, name, key):
        f, out = getattr(cls, name), samples[key]

        def call(*a, **k):
            t = clock()
            r = f(*a, **k)
            out.append(clock() - t)
            return r
        setattr(cls, name, call)

    cfg = config.load(config_path)
    if linear:
        cfg = dataclasses.replace(cfg, observer=dataclasses.replace(cfg.observer, yaw_model=False))
    if what == "_estimate":
        timed(ControlLoop, "_estimate", what)
    else:
        timed(observer.JointObserver, "step", what)
        timed(observer.Observer, "step", what)
    with tempfile.TemporaryDirectory() as d:
        dryrun.run_lockstep(cfg, load_scenario(scenario), Path(d) / "x.h5", duration_s=duration)
    return {k: statistics.median(v) / 1e3 for k, v in samples.items() if v} | {
        "cycles": len(samples[what]), "tree": str(Path(observer.__file__).parent.parent)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(HERE / "configs" / "vehicle.yaml"))
    ap.add_argument("--scenario", default="vehicle-steps")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--base", help="another tree to measure in alternation (e.g. a copy of main)")
    ap.add_argument("--linear", action="store_true", help="observer.yaw_model off")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--what", default="_estimate", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(child(a.child, a.config, a.scenario, a.duration, a.linear, a.what)))
        return 0
    trees = [str(HERE)] + ([str(Path(a.base).resolve())] if a.base else [])
    runs: dict[str, dict[str, list[float]]] = {t: {"_estimate": [], "step": []} for t in trees}
    loads = [os.getloadavg()[0]]
    cycles = 0
    for _ in range(a.repeat):
        for what in ("_estimate", "step"):
            for t in trees:
                cmd = [sys.executable, str(Path(__file__).resolve()), "--child", t, "--what", what, "--config",
                       a.config, "--scenario", a.scenario, "--duration", str(a.duration)] + (["--linear"] if a.linear else [])
                out = subprocess.run(cmd, capture_output=True, text=True, check=True,
                                     env=dict(os.environ, OMP_NUM_THREADS="1"))
                r = json.loads(out.stdout.strip().splitlines()[-1])
                runs[t][what].append(r[what])
                cycles = r["cycles"]
                loads.append(os.getloadavg()[0])
    print(f"CPU µs per cycle, median per run ({a.scenario}, {a.duration:g} s, {Path(a.config).name}"
          f"{', yaw_model off' if a.linear else ''}); load average {min(loads):.1f}-{max(loads):.1f} "
          f"on {os.cpu_count()} cores")
    for t in trees:
        est, step = runs[t]["_estimate"], runs[t]["step"]
        print(f"  {t}\n    _estimate {statistics.median(est):6.2f}  ({' '.join(f'{v:.2f}' for v in est)})"
              f"\n    step      {statistics.median(step):6.2f}  ({' '.join(f'{v:.2f}' for v in step)})"
              f"   cycles {cycles}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
