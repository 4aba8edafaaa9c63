"""Issue 25's acceptance on lockstep runs of a vehicle config: reference steps on the front, the
rear and both together, at speeds of both signs, seeds; each figure against its demand.

    .venv/bin/python -m benchmarks.vehicle_acceptance [--config configs/vehicle.yaml]
        [--speeds -1.5,-1,-0.5,0.5,1,1.5] [--steps 0.5,3] [--seeds 0] [--json OUT]

Each run: the carriers settle from the simulated rig's start (offsets put them ~1 mm off) for
6 s, then a step of A mm on the stepped carrier(s), back to 0 15 s later, 36 s in all, the speed
constant. Figures per step (rig_runtime.app.metrics.step_info: 10–90 % rise, overshoot, 2 %
settling up to the next change, steady-state error), the held carrier's largest move from where
it was at the step as a fraction of the step, the largest |u_cmd| of either carrier from the
first step on (the limiter never clips: ≤ 3 A).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import h5py
import numpy as np

from rig_runtime import config
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.app.metrics import step_info
from rig_runtime.scenario import load_scenario

DEMAND = {"rise_time_s": 3.0, "overshoot_pct": 10.0, "settling_time_s": 8.0, "sse_pct": 2.0,
          "held_pct": 10.0, "peak_u_A": 3.0}
T_STEP, T_BACK, T_END = 6.0, 21.0, 36.0


def scenario_text(v: float, stepped: tuple[str, ...], a_mm: float) -> str:
    ref = {c: (f"[{{t: 0, y_mm: 0}}, {{t: {T_STEP}, y_mm: {a_mm}}}, {{t: {T_BACK}, y_mm: 0}}]"
               if c in stepped else "[{t: 0, y_mm: 0}]") for c in ("front", "rear")}
    return (f"name: accept\ndescription: acceptance step\nduration_s: {T_END}\nspeed: [{{t: 0, v: {v}}}]\n"
            f"reference:\n  front: {ref['front']}\n  rear: {ref['rear']}\n")


def run_case(cfg, v, stepped, a_mm, seed, tmp: Path) -> dict:
    sc = tmp / "accept.yaml"
    sc.write_text(scenario_text(v, stepped, a_mm))
    log = tmp / f"run-{v:+g}-{'+'.join(stepped)}-{a_mm:g}-{seed}.h5"
    summary, code = run_lockstep(cfg, load_scenario(sc), log, seed=seed)
    with h5py.File(log) as f:
        c = {k: f["cycles"][k][()] for k in ("t_run", "y_f", "y_r", "front_u_cmd", "rear_u_cmd", "state")}
    log.unlink()
    run = c["state"] > 0
    t = c["t_run"]
    out = {"v": v, "stepped": "+".join(stepped), "step_mm": a_mm, "seed": seed, "exit": code,
           "faults": summary.get("faults", []), "worst": {}}
    a = a_mm * 1e-3
    figs = []
    for car, y in (("front", c["y_f"]), ("rear", c["y_r"])):
        if car in stepped:
            for rec in step_info(t, y, [(T_STEP, 0.0, a), (T_BACK, a, 0.0)], T_END):
                rec = dict(rec, carrier=car)
                rec["sse_pct"] = (abs(rec["steady_state_error_mm"]) / a_mm * 100.0
                                  if rec["steady_state_error_mm"] is not None else None)
                figs.append(rec)
        else:
            for t0, t1 in ((T_STEP, T_BACK), (T_BACK, T_END)):
                sel = (t >= t0) & (t < t1)
                y0 = y[np.argmax(t >= t0)]
                out["held_pct"] = max(out.get("held_pct", 0.0), float(np.max(np.abs(y[sel] - y0))) / a * 100.0)
    out["steps"] = figs
    after = t >= T_STEP
    out["peak_u_A"] = float(max(np.max(np.abs(c["front_u_cmd"][after])), np.max(np.abs(c["rear_u_cmd"][after]))))
    w = out["worst"]
    for k in ("rise_time_s", "overshoot_pct", "settling_time_s", "sse_pct"):
        vals = [r[k] for r in figs]
        w[k] = None if any(x is None for x in vals) else max(vals)
    w["held_pct"] = out.get("held_pct")
    w["peak_u_A"] = out["peak_u_A"]
    out["ok"] = all(w[k] is not None and w[k] <= DEMAND[k] for k in DEMAND if k in w and (k != "held_pct" or w[k] is not None))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(config.CONFIG_DIR / "vehicle.yaml"))
    ap.add_argument("--speeds", default="-1.5,-1,-0.5,0.5,1,1.5")
    ap.add_argument("--steps", default="0.5,3")
    ap.add_argument("--cases", default="front,rear,front+rear")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    cfg = config.load(a.config)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for seed in (int(s) for s in a.seeds.split(",")):
            for v in (float(s) for s in a.speeds.split(",")):
                for case in a.cases.split(","):
                    for mm in (float(s) for s in a.steps.split(",")):
                        r = run_case(cfg, v, tuple(case.split("+")), mm, seed, Path(d))
                        rows.append(r)
                        w = r["worst"]
                        f = lambda x, p=2: "—" if x is None else f"{x:.{p}f}"
                        print(f"v={v:+.1f} {r['stepped']:11s} {mm:3.1f} mm seed {seed}: rise {f(w['rise_time_s'])} s  "
                              f"overshoot {f(w['overshoot_pct'], 1)} %  settling {f(w['settling_time_s'])} s  "
                              f"sse {f(w['sse_pct'], 1)} %  held {f(w['held_pct'], 1)} %  peak|u| {f(w['peak_u_A'])} A  "
                              f"{'ok' if r['ok'] else 'FAIL'}{' FAULT' if r['faults'] else ''}", flush=True)
    n_ok = sum(r["ok"] for r in rows)
    print(f"{n_ok}/{len(rows)} runs meet every demand {DEMAND}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
