"""False alarms of the observer's innovation rule (docs/observer.md): every shipped scenario
that injects no fault (no ``faults``, no ``expect_fault``), each over N seeds, in lockstep
dry runs with the rule on, each on the shipped config it is for (``vehicle-*``: vehicle.yaml;
``ident-front-*``: sim-ident-front.yaml, which has no observer — skipped; the rest: sim.yaml)
unless ``--config`` names one for all. Per run: the final state, any fault or DEGRADED
interval, and the largest window statistic of each measurement over RUNNING, against
``limits.innovation_chi2``; then one line per scenario.

    python benchmarks/observer_false_alarms.py [--seeds N] [--first K] [--cap S] [--full NAME ...] [--only NAME ...]
        [--config FILE]

``--first K``: seeds K..N-1 only (two processes can share the seeds of a sweep).

``--cap S`` shortens each run to its first S seconds of scenario time (the long
identification scenarios take minutes of wall time each), except the scenarios named by
``--full`` (default: robustness, whose disturbances come up to 55 s). The shortened runs
are what was measured: say so where the numbers are quoted.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from rig_runtime.app.dryrun import run_lockstep  # noqa: E402
from rig_runtime.scenario import SCENARIO_DIR, load_scenario  # noqa: E402

MEASUREMENTS = ("lat", "psi", "dw")


def fault_free() -> list[str]:
    """The shipped scenarios that inject no fault, by name."""
    out = []
    for p in sorted(SCENARIO_DIR.glob("*.yaml")):
        sc = load_scenario(p.stem)
        if not sc.faults and sc.expect_fault is None:
            out.append(p.stem)
    return out


def largest_T(log: Path) -> dict[str, float]:
    """The largest statistic per measurement over RUNNING, over every observed carrier."""
    with h5py.File(log, "r") as f:
        cyc = f["cycles"]
        cols = [c.decode() if isinstance(c, bytes) else c for c in cyc.attrs["columns"]]
        running = cyc["state"][:] == 2.0
        out = {}
        for m in MEASUREMENTS:
            vals = [cyc[c][:][running] for c in cols if c.endswith(f"_obs_T_{m}")]
            out[m] = max((float(np.nanmax(v)) for v in vals if v.size), default=math.nan)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=10, help="seeds 0..N-1 per scenario")
    ap.add_argument("--cap", type=float, default=None, help="scenario seconds per run (default: the whole scenario)")
    ap.add_argument("--full", nargs="*", default=["robustness"], help="scenarios run whole despite --cap")
    ap.add_argument("--only", nargs="*", default=None, help="these scenarios only")
    ap.add_argument("--config", default=None, help="one config for every scenario (default: the shipped one for each)")
    ap.add_argument("--first", type=int, default=0, help="the first seed")
    a = ap.parse_args()
    names = a.only or fault_free()
    configs = {}

    def config_for(name: str):
        f = a.config or ("vehicle.yaml" if name.startswith("vehicle-") else
                         "sim-ident-front.yaml" if name.startswith("ident-front-") else "sim.yaml")
        if f not in configs:
            configs[f] = config.load(config.resolve_config_path(f))
        return f, configs[f]

    for name in names:                        # every config read before the first run
        config_for(name)
    print(f"seeds {a.first}..{a.seeds - 1}; cap {a.cap} s (whole: {', '.join(a.full)})", flush=True)
    rows = []
    thr = math.nan
    for name in names:
        fname, cfg = config_for(name)
        if cfg.observer is None:
            print(f"  {name}: {fname} has no observer — skipped", flush=True)
            continue
        thr = cfg.limits.innovation_chi2
        if thr is None:
            sys.exit(f"{fname}: limits.innovation_chi2 is off; the rule must be on for this measurement")
        sc = load_scenario(name)
        dur = sc.duration_s if (a.cap is None or name in a.full) else min(sc.duration_s, a.cap)
        alarms, worst = 0, dict.fromkeys(MEASUREMENTS, math.nan)    # nan: no observed carrier
        w0 = time.perf_counter()
        for seed in range(a.first, a.seeds):
            with tempfile.TemporaryDirectory() as d:
                log = Path(d) / "run.h5"
                summary, code = run_lockstep(cfg, sc, log, seed=seed, duration_s=dur)
                T = largest_T(log)
            faults = summary["faults"]
            if faults or summary["final_state"] != "IDLE" or summary.get("degraded"):
                alarms += 1             # (with observe a lateral finding DEGRADES: an alarm all the same)
            for m in MEASUREMENTS:
                if math.isfinite(T[m]):
                    worst[m] = T[m] if math.isnan(worst[m]) else max(worst[m], T[m])
            print(f"  {name} [{fname}] seed {seed} ({dur:g} s, {time.perf_counter() - w0:.0f} s wall so far): "
                  f"{summary['final_state']} {'DEGRADED ' if summary.get('degraded') else ''}"
                  f"{[(round(f['t'] - summary['run_started_t'], 3), f['device'], f['check']) for f in faults]} "
                  + " ".join(f"T_{m} {T[m]:.2f}" for m in MEASUREMENTS), flush=True)
        rows.append((name, dur, a.seeds - a.first, alarms, worst, time.perf_counter() - w0))
    print(f"\n| scenario | s per run | seeds | alarms | largest T lat / psi / dw (threshold {thr:g}) |")
    print("| --- | --- | --- | --- | --- |")
    for name, dur, n, alarms, worst, _ in rows:
        print(f"| {name} | {dur:g} | {n} | {alarms} | "
              + (" / ".join(f"{worst[m]:.2f}" for m in MEASUREMENTS) if not math.isnan(worst["lat"])
               else "no observer (carrier lifted)") + " |")
    print(f"\nwall time {sum(r[5] for r in rows):.0f} s")


if __name__ == "__main__":
    main()
