"""Cost of the CAN wire in a lockstep cycle, part by part: four virtual CiA 402 drives
(``VirtualDriveSet``) and the runtime's ``DriveBus`` on the in-process ``LockstepBus``,
stepped as ``SimulatedRig.advance`` and the loop step them — the drives take last cycle's
SYNC and RPDOs and answer with TPDOs (held, then sent), the wheel speeds are set, the
applied currents read, then the runtime polls and writes (SYNC, four RPDOs, its heartbeat
every 100 ms). The drives are OPERATION ENABLED with currents commanded. Per part: the mean
and median of the thread's CPU time per call (``time.thread_time``, what holds on a loaded
machine; each reading costs a system call, ≈ 0.3 µs, which is in every figure).

    python benchmarks/can_lockstep_cost.py [--cycles N] [--config PATH]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from drivers.canopen402 import DriveBus  # noqa: E402
from rig_runtime import config  # noqa: E402
from sim_backend.lockstep_bus import LockstepBus  # noqa: E402
from sim_backend.virtual_drive import VirtualDriveSet  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=6000)
    ap.add_argument("--config", default="configs/sim.yaml")
    args = ap.parse_args()
    cfg = config.load(args.config)
    h = cfg.controller.h
    channel = f"can-cost-{time.monotonic_ns()}"
    sim_bus, runtime_bus = LockstepBus(channel=channel), LockstepBus(channel=channel)
    drives = VirtualDriveSet(cfg.devices.can, sim_bus)
    driver = DriveBus(cfg.devices.can, bus=runtime_bus, period_s=h)
    parts: dict[str, list[float]] = {k: [] for k in (
        "virtual drives: service (frames in, TPDOs out)", "virtual drives: frames sent (release)",
        "virtual drives: wheel speeds set", "virtual drives: applied currents read",
        "DriveBus.poll", "DriveBus.write")}
    spent = list(parts.values())
    tt = time.thread_time
    currents = {"fl": 0.4, "fr": -0.4, "rl": 1.2, "rr": -1.2}
    speeds = [13.3, 13.3, 13.2, 13.2]
    wheel_drives = [drives.drives[w] for w in ("fl", "fr", "rl", "rr")]
    try:
        with drives.serving(0.0):
            driver.configure()
        driver.activate(0.0)
        t = 0.0
        warm_up = 200
        for k in range(args.cycles + warm_up):
            t += h
            a = tt()
            drives.hold()
            drives.service(t - h)
            b = tt()
            drives.release()
            c = tt()
            drives.set_wheel_speeds(speeds)
            d = tt()
            for vd in wheel_drives:
                vd.current_A()
            e = tt()
            driver.poll(t)
            f = tt()
            driver.write(currents, t)
            g = tt()
            if k >= warm_up:
                for out, x in zip(spent, (b - a, c - b, d - c, e - d, f - e, g - f)):
                    out.append(x)
        if not driver.enabled:
            print("the drives did not reach OPERATION ENABLED", file=sys.stderr)
            return 1
    finally:
        driver.close()
        drives.close()
        sim_bus.shutdown()
        runtime_bus.shutdown()
    total = 0.0
    print(f"{args.config}, {args.cycles} cycles, CPU time per call (thread_time)")
    for name, v in parts.items():
        total += statistics.fmean(v)
        print(f"  {name:48s} mean {statistics.fmean(v) * 1e6:6.2f} µs  median {statistics.median(v) * 1e6:6.2f} µs")
    print(f"  {'all of the above, per cycle':48s} mean {total * 1e6:6.2f} µs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
