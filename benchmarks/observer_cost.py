"""Cost of the observer's per-cycle work (docs/performance.md): the lane stage's filter
step (``Observer.step``, one carrier), the supervisor's fitness check of the two lateral
lasers (``Supervisor.fit``: ARM_RULES on two channels) and the innovation rule; median of
repeated timings per call, µs.

    python benchmarks/observer_cost.py
"""

from __future__ import annotations

import math
import statistics
import sys
import timeit
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from rig_runtime.app.observer_design import design  # noqa: E402
from rig_runtime.hardware import Freshness, Health  # noqa: E402
from rig_runtime.observer import Observer  # noqa: E402
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


if __name__ == "__main__":
    main()
