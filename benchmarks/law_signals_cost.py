"""Cost per cycle of the control law's signals in the log row (issue 25): each controlled lane's
``signal_values()`` (the law's declared signals through the getter resolved at configure time),
against copying the six fields of the controller's record (``st``) as the row did before the law
declared its signals.  .venv/bin/python -m benchmarks.law_signals_cost"""
import timeit
from operator import attrgetter

from rig_runtime import config
from rig_runtime.control import PIPDLaw
from rig_runtime.lanes import make_lanes

RECORD = attrgetter(*PIPDLaw.SIGNALS)          # the six fields the row copied from ``st`` before
N, REPEAT = 200_000, 5

for name in ("sim.yaml", "vehicle.yaml"):
    cfg = config.load(config.CONFIG_DIR / name)
    lanes = [lane for lane in make_lanes(cfg, lambda t: 1e-3) if lane.controlled]
    for lane in lanes:
        lane.start()
    for lane in lanes:
        lane.control(0.0, True)

    def now():
        for lane in lanes:
            lane.signal_values()

    def before():
        for lane in lanes:
            RECORD(lane.controller.st)

    t_now, t_before = (min(timeit.repeat(f, number=N, repeat=REPEAT)) / N for f in (now, before))
    print(f"{name:13s} {cfg.controller.law:9s} {len(lanes)} lane(s), {len(lanes[0].signals)} signals each: "
          f"{t_now * 1e6:.3f} us per cycle (the record's 6 fields: {t_before * 1e6:.3f} us)")
