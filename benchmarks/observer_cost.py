"""Cost of the observer's per-cycle work (docs/performance.md): the lane stage's filter
step (``Observer.step``, one carrier), the supervisor's fitness check of the two lateral
lasers (``Supervisor.fit``: ARM_RULES on two channels) and the innovation rule; median of
repeated timings per call, µs. Then the vehicle's running-gear filter (``JointObserver.step``,
both carriers, vehicle.yaml's speed table) with its per-laser fitness checks, the innovation
rule on both carriers' views and their log rows: the observer's cost per cycle on the vehicle.

    python benchmarks/observer_cost.py [--linear]

``--linear``: the vehicle's filter without the hysteresis and damping law in its model
(``observer.yaw_model: false``), for the comparison.
"""

from __future__ import annotations

import dataclasses
import math
import os
import statistics
import sys
import timeit
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from rig_runtime.app.observer_design import design, joint_speed_table  # noqa: E402
from rig_runtime.hardware import Freshness, Health  # noqa: E402
from rig_runtime.observer import JointObserver, Observer  # noqa: E402
from rig_runtime.safety import Channel, Sample, Supervisor, innovation  # noqa: E402


def per_call_us(fn, n: int = 20000, repeat: int = 7) -> float:
    return statistics.median(timeit.repeat(fn, number=n, repeat=repeat)) / n * 1e6


def main() -> None:
    cfg = config.load(config.resolve_config_path("sim-observer.yaml"))
    o = Observer(design(cfg, "rear"))
    o.step(1e-3, 1e-3, 0.01, 0.1, 0.0, True)
    chans = [Channel(n, "laser", 0.0, 1.0, 0.02) for n in ("b_f", "b_r")]
    sup = Supervisor(cfg.limits, cfg.controller.h, chans, ["rear"], hardware=None)
    for c in chans:
        c.observe(Sample(0.07, 1.0, Health(Freshness.FRESH)), 1.0, cfg.controller.h)
    for _ in range(300):
        o.step(1e-3, 1e-3, 0.01, 0.1, 0.0, True)
    res = {
        "Observer.step (lateral used)": per_call_us(lambda: o.step(1e-3, 1e-3, 0.01, 0.1, 0.0, True)),
        "Observer.step (lateral not fit)": per_call_us(lambda: o.step(1e-3, 1e-3, 0.01, 0.1, 0.0, False)),
        "Supervisor.fit(b_r, b_f)": per_call_us(lambda: sup.fit(("b_r", "b_f"), 1.0)),
        "innovation rule": per_call_us(lambda: innovation(o, cfg.limits)),
        "log_values": per_call_us(o.log_values),
    }
    for k, v in res.items():
        print(f"{k:34s} {v:6.2f} us")
    print(f"{'total per observed carrier':34s} {res['Observer.step (lateral used)'] + res['Supervisor.fit(b_r, b_f)'] + res['innovation rule'] + res['log_values']:6.2f} us")
    assert math.isfinite(o.y)

    vcfg = config.load(config.resolve_config_path("vehicle.yaml"))
    if "--linear" in sys.argv:              # the hysteresis and damping law left out (observer.yaw_model off)
        vcfg = dataclasses.replace(vcfg, observer=dataclasses.replace(vcfg.observer, yaw_model=False))
    print(f"\nvehicle.yaml, observer.yaw_model {vcfg.observer.yaw_model}")
    j = JointObserver(joint_speed_table(vcfg))
    j.select(1.0)
    args = (0.071, 0.0705, True, True, 1e-3, 1e-3, 0.01, 0.01, 0.1, 0.1, 1.0, 1.0)
    for _ in range(300):
        j.step(*args)
    lost = args[:3] + (False,) + args[4:]
    fit1 = lambda: sup.fit(("b_f",), 1.0)   # noqa: E731 (the loop checks each laser on its own)
    vres = {
        "JointObserver.step (both lasers)": per_call_us(lambda: j.step(*args)),
        "JointObserver.step (b_r lost)": per_call_us(lambda: j.step(*lost)),
        "Supervisor.fit(b_f), one laser": per_call_us(fit1),
        "innovation rule, one carrier": per_call_us(lambda: innovation(j.front, vcfg.limits)),
        "log_values, one carrier": per_call_us(j.front.log_values),
    }
    print()
    for k, v in vres.items():
        print(f"{k:34s} {v:6.2f} us")
    total = (vres["JointObserver.step (both lasers)"] + 2 * vres["Supervisor.fit(b_f), one laser"]
             + 2 * vres["innovation rule, one carrier"] + 2 * vres["log_values, one carrier"])
    print(f"{'total per cycle, vehicle (joint)':34s} {total:6.2f} us")
    print(f"{'per-carrier filters, both carriers':34s} {2 * (res['Observer.step (lateral used)'] + res['Supervisor.fit(b_r, b_f)'] + res['innovation rule'] + res['log_values']):6.2f} us")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    assert math.isfinite(j.front.y)


if __name__ == "__main__":
    main()
