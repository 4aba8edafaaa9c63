"""Throughput of ``rig campaign``: the same N runs one after another in one process (the
campaign's own task function, no Dask) and on a Dask LocalCluster of W worker processes,
measured in one session. Reports runs per minute and seconds of simulated time per wall
second for both, and the speed-up.

    python benchmarks/campaign_speed.py [--runs 64] [--workers 2] [--duration 4] [--json]

The runs: the single-step scenario (``--duration`` s of RUNNING each), plant.delta0 ±30 % and
K_P_y 2-4 rad/m on a Sobol' design. ``cpu_steal_pct``: CPU time the hypervisor took during
each phase, in % of its wall time (summed over CPUs); ``loadavg``: the machine's 1-min load
before each phase (other processes share the cores).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks._machine import StealMeter  # noqa: E402


def _spec(path: Path, runs: int, duration: float) -> Path:
    path.write_text(f"""name: speed
base: {{config: sim.yaml, scenario: single-step, duration_s: {duration}}}
parameters:
  plant.delta0: {{pct: 30}}
  controller.pipd.K_P_y: {{uniform: [2.0, 4.0]}}
design: {{method: lhs, n: {runs}, seed: 1}}
pass: {{no_fault: true}}
keep_logs: none
""")
    return path


def serial(spec_path: Path, out: Path) -> tuple[float, float, float]:
    """Every run one after another through the campaign's task function; (wall s, simulated s,
    CPU s of this process: what the runs cost whatever else loads the machine)."""
    from rig_runtime.app.campaign import prepare
    from rig_runtime.app.campaign.spec import load_spec
    from rig_runtime.app.campaign.task import Job, run_sample
    spec = load_spec(spec_path)
    store = prepare.create(spec, out)
    hw = (out / "configs" / "hardware.yaml").read_text()
    sim = 0.0
    t0, c0 = time.perf_counter(), time.process_time()
    for i in store.sample_ids():
        s = store.sample(i)
        row = run_sample(Job(run_id=i, config_text=Path(s["config"]).read_text(), hardware_text=hw,
                             scenario_text=Path(s["scenario"]).read_text(), seed=s["seed"],
                             duration_s=spec.duration_s, settle_s=0.0, criteria=spec.criteria,
                             no_fault=spec.no_fault, keep_logs="none", audit_path=None))
        assert row["status"] in ("pass", "fail"), row
        sim += row["sim_s"]
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    store.close()
    return wall, sim, cpu


def parallel(spec_path: Path, out: Path, workers: int) -> tuple[float, float]:
    """``rig campaign run --workers W`` as a process, from the command to its exit (the
    cluster's start-up and shutdown included); (wall s, simulated s)."""
    import sqlite3
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "rig_runtime", "campaign", "run", str(spec_path), "--out", str(out),
                    "--workers", str(workers)], check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    db = sqlite3.connect(out / "campaign.sqlite")
    n, sim = db.execute("SELECT COUNT(*), SUM(sim_s) FROM results WHERE status IN ('pass', 'fail')").fetchone()
    db.close()
    return wall, sim, n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=64)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--duration", type=float, default=4.0)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(v, "1")
    res: dict = {"runs": a.runs, "workers": a.workers, "duration_s": a.duration, "cpus": os.cpu_count()}
    with tempfile.TemporaryDirectory(prefix="rig-campaign-bench-") as tmp:
        d = Path(tmp)
        spec = _spec(d / "speed.yaml", a.runs, a.duration)
        res["loadavg_serial"] = os.getloadavg()[0]
        with StealMeter() as m:
            wall, sim, cpu = serial(spec, d / "serial")
        res["serial"] = {"wall_s": wall, "sim_s": sim, "runs_per_min": 60 * a.runs / wall, "sim_s_per_wall_s": sim / wall,
                         "cpu_s": cpu, "sim_s_per_cpu_s": sim / cpu, "cpu_steal_pct": m.percent}
        res["loadavg_parallel"] = os.getloadavg()[0]
        with StealMeter() as m:
            wall, sim, n = parallel(spec, d / "par", a.workers)
        assert n == a.runs, n
        res["parallel"] = {"wall_s": wall, "sim_s": sim, "runs_per_min": 60 * a.runs / wall,
                           "sim_s_per_wall_s": sim / wall, "cpu_steal_pct": m.percent}
    res["speedup"] = res["parallel"]["runs_per_min"] / res["serial"]["runs_per_min"]
    if a.json:
        print(json.dumps(res))
    else:
        for k in ("serial", "parallel"):
            r = res[k]
            print(f"{k:<9} {r['wall_s']:7.1f} s wall  {r['runs_per_min']:6.1f} runs/min  "
                  f"{r['sim_s_per_wall_s']:6.2f} simulated s per wall s  (steal {r['cpu_steal_pct']})"
                  + (f"  {r['sim_s_per_cpu_s']:6.2f} simulated s per CPU s" if "cpu_s" in r else ""))
        print(f"speed-up {res['speedup']:.2f}x with {a.workers} workers; load average before: "
              f"{res['loadavg_serial']:.1f} / {res['loadavg_parallel']:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
