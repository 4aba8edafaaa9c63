"""The runtime's own per-cycle cost in a lockstep run, stage by stage, without the simulated
wires: the median per cycle of each stage of loop.py (geometry, measured speed, supervisor,
observer, control, output limit, log row) and of ``devices.poll``'s own work (the poll minus
the drivers' polls inside it: filing the readings under their names). Medians of many cycles:
robust against the other processes of a shared machine preempting this one.

Runs the code on ``sys.path`` (to compare two trees, run it from each with PYTHONPATH set to
that tree; ``--repeat`` runs and the median of each stage's per-run medians):

    python benchmarks/runtime_stage_cost.py [--config configs/vehicle.yaml] [--duration S] [--repeat N]
"""

from __future__ import annotations

import argparse
import collections
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from rig_runtime.loop import ControlLoop  # noqa: E402
from rig_runtime.speed import SpeedEstimate  # noqa: E402
from rig_runtime.scenario import load_scenario  # noqa: E402
from rig_runtime.app import dryrun  # noqa: E402

STAGES = ((ControlLoop, "_measure", "geometry (_measure)"),
          (SpeedEstimate, "update", "measured speed"),
          (ControlLoop, "_supervise", "supervisor"),
          (ControlLoop, "_estimate", "observer (_estimate)"),
          (ControlLoop, "_control", "control"),
          (ControlLoop, "_limit", "output limit"),
          (ControlLoop, "row", "log row"))
POLL_OWN = "devices.poll: own work (minus the drivers)"


def one_run(path: str, scenario: str, duration: float) -> dict[str, float]:
    pc = time.perf_counter
    samples: dict[str, list[float]] = collections.defaultdict(list)
    inner = [0.0]

    def timed(f, key):
        out = samples[key]

        def call(*a, **k):
            t = pc()
            r = f(*a, **k)
            out.append(pc() - t)
            return r
        return call

    def child(f):
        def call(*a, **k):
            t = pc()
            r = f(*a, **k)
            inner[0] += pc() - t
            return r
        return call

    def prepare(sim, dev, clock):
        for d in dev.lasers:
            d.poll = child(d.poll)
        dev.drives.poll = child(dev.drives.poll)
        if dev.ft is not None:
            dev.ft.poll = child(dev.ft.poll)
        outer = dev.poll
        own = samples[POLL_OWN]

        def poll(now):
            inner[0] = 0.0
            t = pc()
            r = outer(now)
            own.append(pc() - t - inner[0])
            return r
        dev.poll = poll

    cfg = config.load(path)
    originals = [(cls, name, getattr(cls, name)) for cls, name, _ in STAGES]
    for cls, name, key in STAGES:
        setattr(cls, name, timed(getattr(cls, name), key))
    try:
        with tempfile.TemporaryDirectory() as d:
            dryrun.run_lockstep(cfg, load_scenario(scenario), Path(d) / "x.h5", duration_s=duration, prepare=prepare)
    finally:
        for cls, name, f in originals:
            setattr(cls, name, f)
    return {k: statistics.median(v) * 1e6 for k, v in samples.items() if v}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(config.CONFIG_DIR / "sim.yaml"))
    ap.add_argument("--scenario", default="single-step")
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    runs = [one_run(a.config, a.scenario, a.duration) for _ in range(a.repeat)]
    keys = [k for _, _, k in STAGES] + [POLL_OWN]
    print(f"median µs per call ({a.scenario}, {a.duration:g} s, {Path(a.config).name}, "
          f"median of {a.repeat} runs)")
    total = 0.0
    for k in keys:
        v = statistics.median(r.get(k, 0.0) for r in runs)
        total += v
        print(f"  {k:46s} {v:7.2f}")
    print(f"  {'sum':46s} {total:7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
