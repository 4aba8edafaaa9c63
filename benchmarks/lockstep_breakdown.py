"""Where a lockstep dry-run cycle spends its time: wraps the simulated rig's and the
device set's per-cycle calls with timers and runs the single-step scenario.

Per part: the mean per cycle (what the real-time factor pays) and the median per call
(robust against other processes preempting this one). In the simulator, "virtual
drives" handles the runtime's frames (the replies wait in an outbox), "frames sent" sends
the replies; both the replies, the wheel speeds and the F/T work run while the kernel
delivers the laser bytes; what is left of that wait is "wait until the laser bytes are
delivered", the last part of ``advance``. "advance" is the whole simulator step (the
parts plus what is not timed separately).

    python benchmarks/lockstep_breakdown.py [--duration S]
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
from rig_runtime.scenario import load_scenario  # noqa: E402
from rig_runtime.app import dryrun  # noqa: E402

samples: dict[str, list[float]] = collections.defaultdict(list)


def timed(f, key: str):
    out = samples[key]
    pc = time.perf_counter

    def call(*a, **k):
        t = pc()
        r = f(*a, **k)
        out.append(pc() - t)
        return r
    return call


def wrap(obj, name: str, key: str) -> None:
    setattr(obj, name, timed(getattr(obj, name), key))


def prepare(sim, dev, clock) -> None:
    if hasattr(clock, "_advance"):          # the clock holds the bound method already
        clock._advance = timed(clock._advance, "sim: advance (all below)")
    wrap(sim.plant, "step", "sim:   plant step")
    wrap(sim.drives, "service", "sim:   virtual drives")
    wrap(sim.drives, "release", "sim:   virtual drives: frames sent")
    wrap(sim, "set_laser_distances", "sim:   laser distances (geometry)")
    wrap(sim._laser_group, "emit", "sim:   laser frames written to ptys")
    wrap(sim, "set_wheel_speeds", "sim:   wheel speeds")
    if sim.ft is not None:
        wrap(sim.ft, "set_wrench", "sim:   F/T registers")
        wrap(sim.ft, "answer_pending", "sim:   F/T requests answered")
    wrap(sim._laser_group, "wait", "sim:   wait until the laser bytes are delivered")
    if dev.ft is not None:
        wrap(dev.ft, "poll", "runtime:   F/T poll (inline: sends and collects)")
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
    print(f"{n} cycles, {wall / n * 1e6:.0f} us per cycle in all (incl. set-up), "
          f"{s['wall_time_s'] / n * 1e6:.0f} us in the loop")
    print(f"  {'':42s} {'mean us/cycle':>14s} {'p50 us/call':>12s} {'calls/cycle':>12s}")
    for k, v in samples.items():
        if v:
            print(f"  {k:42s} {sum(v) / n * 1e6:14.1f} {statistics.median(v) * 1e6:12.1f} {len(v) / n:12.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
