"""The vehicle's plant (issue 18): integrator accuracy with per-carrier values and a speed
reversal against the stiff reference, and the cost of a time-varying speed.

- accuracy: configs/vehicle-plant.yaml's plant (both carriers in contact, the front's own
  values), both carriers driven by steps, a lateral-force pulse, side wind and a yaw-moment
  pulse, over ``--seconds``; the speed constant +1 m/s, or ramping +1 -> -1 m/s through 0
  over the middle half (held per step, ZOH); error = max |x - x_ref| / range(x_ref) against
  ``solve_ivp(Radau, rtol=1e-10, atol=1e-12)`` restarted wherever an input or v changes.
- cost: ``Plant.set_speed`` with a new v every call (the paper's set-up, rear only; both
  carriers with unequal a_f, a_r), and ``Plant.step`` per 5 ms step at a constant speed vs
  with ``set_speed`` before every step (a ramp), best of ``--repeat``.

    python benchmarks/vehicle_plant.py [--seconds T] [--repeat N] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

from rig_runtime import config  # noqa: E402
from sim_backend.plant import STATE_NAMES, Plant  # noqa: E402
from tests.plant_reference import Scenario, reference, simulate  # noqa: E402

H = 0.005
NAMES = ("y_f", "y_r", "psi_af", "psi_ar", "psi_rate_f", "psi_rate_r")


def vehicle_plant():
    """The plant part of configs/vehicle-plant.yaml (read as its own section)."""
    sections = config.load_sections(config.CONFIG_DIR / "vehicle-plant.yaml")
    from rig_runtime import schema
    import typing
    hints = typing.get_type_hints(config.RigConfig)
    return schema._convert(hints["plant"], sections["plant"][0], "plant", sections["plant"][1])


def inputs(n: int) -> np.ndarray:
    t = np.arange(n) * H
    T = n * H
    U = np.zeros((n, 6))
    U[:, 0] = 0.5 * (t >= 0.1 * T) - 1.0 * (t >= 0.55 * T) + 0.3 * (t >= 0.8 * T)
    U[:, 1] = -0.6 * (t >= 0.05 * T) + 1.0 * (t >= 0.4 * T) - 0.2 * (t >= 0.9 * T)
    U[(t >= 0.3 * T) & (t < 0.3 * T + 0.05), 3] = 200.0
    U[(t >= 0.6 * T) & (t < 0.6 * T + 0.02), 4] = 2.0
    U[t >= 0.7 * T, 2] = 50.0
    return U


def accuracy(P, seconds: float, reversal: bool) -> dict:
    n = int(round(seconds / H))
    t = np.arange(n) * H
    V = np.interp(t, [0.0, 0.25 * seconds, 0.75 * seconds, seconds], [1.0, 1.0, -1.0, -1.0]) if reversal else None
    sc = Scenario("vehicle", P, H, inputs(n), speed=V)
    t0 = time.perf_counter()
    x = simulate(sc)
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    xr = reference(sc)
    t_ref = time.perf_counter() - t0
    idx = {k: STATE_NAMES.index(k) for k in NAMES}
    err = {k: float(np.max(np.abs(x[:, i] - xr[:, i])) / np.ptp(xr[:, i])) for k, i in idx.items()}
    rng = {k: float(np.ptp(xr[:, i])) for k, i in idx.items()}
    return {"reversal": reversal, "steps": n, "err_rel": err, "range": rng,
            "us_per_step": t_sim / n * 1e6, "reference_s": t_ref}


def best(fn, repeat: int, number: int) -> float:
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn(number)
        out.append((time.perf_counter() - t0) / number)
    return min(out) * 1e6


def cost(P_paper, P_vehicle, repeat: int) -> dict:
    res = {}
    for name, P in (("paper", P_paper), ("vehicle", P_vehicle)):
        pl = Plant(P)
        pl.step(H, 0.0, 0.0)
        vs = np.linspace(1.0, -1.0, 1001).tolist()

        def set_speed(m, pl=pl, vs=vs):
            s = pl.set_speed
            for k in range(m):
                s(vs[k % 1001])
        res[f"set_speed_us_{name}"] = best(set_speed, repeat, 20000)
        U = inputs(4000)[:, :].tolist()

        def steps(m, P=P, U=U):
            p = Plant(P)
            st = p.step
            for k in range(m):
                st(H, *U[k % 4000])
        res[f"step_us_{name}"] = best(steps, repeat, 4000)

        def ramp(m, P=P, U=U, vs=vs):
            p = Plant(P)
            st, s = p.step, p.set_speed
            for k in range(m):
                s(vs[k % 1001])
                st(H, *U[k % 4000])
        res[f"step_with_set_speed_us_{name}"] = best(ramp, repeat, 4000)
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    Pv = vehicle_plant()
    out = {"accuracy": [accuracy(Pv, args.seconds, rev) for rev in (False, True)],
           "accuracy_linear": [accuracy(replace(Pv, bouc_wen=None), args.seconds, rev) for rev in (False, True)],
           "cost": cost(config.load().plant, Pv, args.repeat)}
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        for key in ("accuracy", "accuracy_linear"):
            for a in out[key]:
                errs = ", ".join(f"{k} {v:.1e}" for k, v in a["err_rel"].items())
                print(f"{key} {'reversal' if a['reversal'] else 'v = +1  '}: {errs}; "
                      f"{a['us_per_step']:.1f} µs/step, reference {a['reference_s']:.0f} s")
        for k, v in out["cost"].items():
            print(f"{k}: {v:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
