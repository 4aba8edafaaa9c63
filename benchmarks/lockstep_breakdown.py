"""Where a lockstep dry-run cycle spends its time: wraps the simulated rig's and the
device set's per-cycle calls with timers and runs the single-step scenario.

    python benchmarks/lockstep_breakdown.py [--duration S]
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import sim_backend.rig as rigmod  # noqa: E402
from rig_runtime import config  # noqa: E402
from rig_runtime.scenario import load_scenario  # noqa: E402
from sim_backend import dryrun  # noqa: E402

acc: dict[str, float] = collections.defaultdict(float)


def wrap(obj, name: str, key: str) -> None:
    f = getattr(obj, name)

    def timed(*a, **k):
        t = time.perf_counter()
        r = f(*a, **k)
        acc[key] += time.perf_counter() - t
        return r
    setattr(obj, name, timed)


def prepare(sim, dev, clock) -> None:
    wrap(sim, "advance", "sim: advance (all below)")
    wrap(sim.plant, "step", "sim:   plant step")
    wrap(sim.drives, "service", "sim:   virtual drives")
    wrap(sim.ft, "set_wrench", "sim:   F/T registers")
    if dev.ft is not None:
        wrap(dev.ft, "poll_devices_once", "sim:   F/T Modbus polls (lockstep)")
    orig = rigmod.emit_all

    def emit(ls, t):
        t0 = time.perf_counter()
        r = orig(ls, t)
        acc["sim:   laser frames to ptys"] += time.perf_counter() - t0
        return r
    rigmod.emit_all = emit
    wrap(dev, "poll", "runtime: devices.poll (all below)")
    for d in dev.lasers:
        wrap(d, "poll", "runtime:   laser polls")
    wrap(dev.drives, "poll", "runtime:   drive bus poll")
    wrap(dev, "write", "runtime: devices.write")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0)
    args = ap.parse_args()
    cfg = config.load()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        s, _ = dryrun.run_lockstep(cfg, load_scenario("single-step"), Path(d) / "x.h5",
                                   duration_s=args.duration, prepare=prepare)
    wall = time.perf_counter() - t0
    n = s["cycles"]
    print(f"{n} cycles, {wall / n * 1e6:.0f} us per cycle in all (incl. set-up)")
    for k, v in sorted(acc.items()):
        print(f"  {k:40s} {v / n * 1e6:8.1f} us/cycle")
    return 0


if __name__ == "__main__":
    sys.exit(main())
