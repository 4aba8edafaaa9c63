"""The running gear's filter replayed (docs/observer.md, "Cost, third session"): the calls a
lockstep run made of ``JointObserver`` (step, select, reset) are recorded once and fed to the
filter of this tree and of another tree (``--base``): every logged value of both carriers'
views, their leads and window means compared cycle by cycle (the change is bit-identical or
says where it is not), and the step's CPU time in a tight loop (median per call; each timing
includes one clock read, ~0.2 µs).

    python benchmarks/observer_replay.py [--base DIR] [--scenario vehicle-steps] [--duration S]
        [--fault drift:s_fl:0.1 | dropout:b_r:6] [--repeat N]

``--fault KIND:DEVICE:VALUE`` injects one fault at 4 s (a drift in mm/s, a dropout in s).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent


def record(scenario: str, duration: float, fault: str | None, out: Path) -> None:
    """This tree's lockstep run on vehicle.yaml; the joint filter's calls pickled to ``out``."""
    sys.path.insert(0, str(HERE))
    import dataclasses

    from rig_runtime import config
    from rig_runtime.app import dryrun
    from rig_runtime.observer import JointObserver
    from rig_runtime.scenario import FaultInjection, load_scenario

    calls: list = []
    step, select, reset = JointObserver.step, JointObserver.select, JointObserver.reset
    JointObserver.step = lambda self, *a: (calls.append(("step", a)), step(self, *a))[1]
    JointObserver.select = lambda self, v: (calls.append(("select", v)), select(self, v))[1]
    JointObserver.reset = lambda self: (calls.append(("reset",)), reset(self))[1]
    sc = load_scenario(scenario)
    if fault:
        kind, dev, val = fault.split(":")
        fi = (FaultInjection(kind=kind, t=4.0, device=dev, rate_mm_s=float(val)) if kind == "drift" else
              FaultInjection(kind=kind, t=4.0, device=dev, duration_s=float(val)))
        sc = dataclasses.replace(sc, faults=(fi,), expect_fault=None)
    cfg = config.load(config.resolve_config_path("vehicle.yaml"))
    with tempfile.TemporaryDirectory() as d:
        dryrun.run_lockstep(cfg, sc, Path(d) / "x.h5", duration_s=duration)
    out.write_bytes(pickle.dumps(calls))


def replay(tree: str, calls_file: Path, values_file: Path, repeat: int) -> dict:
    """The recorded calls into ``tree``'s filter: the values per cycle (pickled to
    ``values_file``) and the step's median CPU time per call (µs) over ``repeat`` passes."""
    sys.path.insert(0, tree)
    import time

    from rig_runtime import config
    from rig_runtime.app.observer_design import joint_speed_table
    from rig_runtime.observer import JointObserver

    calls = pickle.loads(calls_file.read_bytes())
    table = joint_speed_table(config.load(config.resolve_config_path("vehicle.yaml")))

    def run(keep: bool) -> tuple[list, list]:
        j = JointObserver(table)
        f, r = j.front, j.rear
        rows, dt, clock = [], [], time.thread_time_ns
        for c in calls:
            if c[0] == "step":
                t = clock()
                j.step(*c[1])
                dt.append(clock() - t)
                if keep:
                    row = f.log_values() + r.log_values() + (f.window_full, f.lead, r.lead, f.outage)
                    if f.window_full:
                        row += (f.mean_lat, f.mean_dw, r.mean_lat, r.mean_dw)
                    rows.append(row)
            elif c[0] == "select":
                j.select(c[1])
            else:
                j.reset()
        return rows, dt

    rows, _ = run(True)
    values_file.write_bytes(pickle.dumps(rows))
    meds = [statistics.median(run(False)[1]) / 1e3 for _ in range(repeat)]
    return {"step_us": statistics.median(meds), "runs": meds, "cycles": len(rows)}


def _same(u, v) -> bool:
    return u == v or (isinstance(u, float) and isinstance(v, float) and math.isnan(u) and math.isnan(v))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", help="another tree whose filter gets the same calls")
    ap.add_argument("--scenario", default="vehicle-steps")
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument("--fault", default=None)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--record", help=argparse.SUPPRESS)
    ap.add_argument("--replay", nargs=3, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.record:
        record(a.scenario, a.duration, a.fault, Path(a.record))
        return 0
    if a.replay:
        tree, calls, values = a.replay
        print(json.dumps(replay(tree, Path(calls), Path(values), a.repeat)))
        return 0
    me = [sys.executable, str(Path(__file__).resolve())]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    with tempfile.TemporaryDirectory() as d:
        calls = Path(d) / "calls.pickle"
        subprocess.run(me + ["--record", str(calls), "--scenario", a.scenario, "--duration", str(a.duration)]
                       + (["--fault", a.fault] if a.fault else []), check=True, env=env)
        trees = [str(HERE)] + ([str(Path(a.base).resolve())] if a.base else [])
        res, values = {}, {}
        for k, t in enumerate(trees):
            values[t] = Path(d) / f"values{k}.pickle"
            out = subprocess.run(me + ["--repeat", str(a.repeat), "--replay", t, str(calls), str(values[t])],
                                 capture_output=True, text=True, check=True, env=env)
            res[t] = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{a.scenario}{' with ' + a.fault if a.fault else ''}, {a.duration:g} s on vehicle.yaml; "
              f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        for t in trees:
            r = res[t]
            print(f"  {t}: step {r['step_us']:.2f} µs CPU per call in a tight loop "
                  f"({' '.join(f'{v:.2f}' for v in r['runs'])}), {r['cycles']} cycles")
        if a.base:
            x, y = (pickle.loads(values[t].read_bytes()) for t in trees)
            diff = [k for k, (p, q) in enumerate(zip(x, y)) if len(p) != len(q) or not all(map(_same, p, q))]
            rel = max((abs(u - v) / max(abs(u), abs(v)) for k in diff for u, v in zip(x[k], y[k])
                       if isinstance(u, float) and isinstance(v, float) and not _same(u, v)), default=0.0)
            same_leads = all(p[24:27] == q[24:27] for p, q in zip(x, y))
            print(f"  values: {len(x) - len(diff)} of {len(x)} cycles bit-identical; elsewhere at most "
                  f"{rel:.1e} relative; leads and window flags {'the same' if same_leads else 'DIFFER'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
