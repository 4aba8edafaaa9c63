"""Cost of one controller step: the PI-PD (sim.yaml) and law decoupled (vehicle.yaml), on floats as the loop
calls it:  .venv/bin/python -m benchmarks.controller_step"""
import timeit
from rig_runtime import config
from rig_runtime.control import make_controller
from rig_runtime.lanes import LateralPair
class L:  # two lanes' y
    def __init__(s, c, y): s.carrier, s.y = c, y
pair = LateralPair([L("front", 1e-4), L("rear", -1e-4)])
for name, carrier in (("sim.yaml", None), ("vehicle.yaml", "rear")):
    cfg = config.load(config.CONFIG_DIR / name)
    c = make_controller(cfg.controller, 4.0, 0.04, carrier)
    if hasattr(c, "couple"):
        c.couple(pair)
    c.start(0.0, 0.0, 0.0)
    n = 200000
    t = min(timeit.repeat(lambda: c.step(1e-3, 2e-4, 1e-4), number=n, repeat=5)) / n
    print(f"{name:13s} {cfg.controller.law:9s} step {t*1e6:.2f} us")
