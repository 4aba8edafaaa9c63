"""What the pre-run stability gate costs the real-time loop's process: resident and locked
memory under ``mlockall`` (as ``rig run`` applies it) and start-up time, with the gate's
analysis (numpy + scipy.linalg) imported and run in the process, and without it.

Each sample is a fresh interpreter that does what ``rig run`` does before its loop starts,
in its order: the thread settings of ``rig_runtime.app.entry``, ``import
rig_runtime.app.cli`` (every module the ``rig`` command loads at start-up), the config, the
stability gate and the plan's slowest eigenvalues (``preflight.check_run``), the driver
classes (``RigDevices``), the recorder and live-view modules, then
``apply_realtime`` with ``mlockall: true`` — and reads ``VmRSS``/``VmLck`` from
``/proc/self/status``. "without": ``rig_runtime.analysis`` is replaced by an empty module
before anything is imported (so neither it nor scipy is loaded, and the gate does not run):
the process as it would be if the gate ran in another process. The two kinds alternate,
and after each pair the gate runs in a process of its own (wall time: what a run would
wait for it there).

    python benchmarks/gate_cost.py [--runs 7] [--config configs/sim.yaml] [--json]

Results: docs/performance.md, "The stability gate in the loop's process".
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

_CHILD = r"""
import os, sys, time
t0 = time.perf_counter()
for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(v, "1")
with_gate = sys.argv[1] == "with"
if not with_gate:
    import types
    sys.modules["rig_runtime.analysis"] = types.ModuleType("rig_runtime.analysis")   # no analysis, no scipy
import dataclasses
import rig_runtime.app.cli                      # what `rig` imports at start-up
from rig_runtime import config
from rig_runtime.app import live, runner       # noqa: F401 - the run's modules
from rig_runtime import recorder, registry     # noqa: F401
from rig_runtime.clock import apply_realtime
cfg = config.load(sys.argv[2])
t_imports = time.perf_counter() - t0
if with_gate:
    from rig_runtime import analysis
    analysis.stability_gate(cfg)                # preflight.check_run, and again in runner.execute
    {D: float(max(analysis.sampled_loop(cfg, D).real)) for D in (cfg.plant.D_min, cfg.plant.D_max)}
    analysis.stability_gate(cfg)
registry.driver_class("laser", cfg.devices.lasers[0].driver)    # the driver modules RigDevices imports
registry.driver_class("can", cfg.devices.can.driver)
registry.driver_class("ft", cfg.devices.ft.driver)
t_ready = time.perf_counter() - t0
t1 = time.perf_counter()
report = apply_realtime(dataclasses.replace(cfg.realtime, mlockall=True, sched_fifo_priority=None,
                                            cpu_affinity=None))
t_lock = time.perf_counter() - t1
status = dict(l.split(":", 1) for l in open("/proc/self/status").read().splitlines() if ":" in l)
kb = lambda k: int(status[k].split()[0])
mods = sorted(m for m in ("scipy", "numpy", "h5py", "matplotlib") if m in sys.modules)
print(json.dumps({"rss_kb": kb("VmRSS"), "lck_kb": kb("VmLck"), "imports_s": t_imports, "ready_s": t_ready,
                  "mlockall_s": t_lock,
                  "mlockall": [r for r in report if r.startswith("mlockall")], "loaded": mods}))
"""


_GATE_CHILD = r"""
import os, sys
for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(v, "1")
from rig_runtime import analysis, tuning
cfg = tuning.config_from_json(sys.stdin.read())
analysis.stability_gate(cfg)
print({D: float(max(analysis.sampled_loop(cfg, D).real)) for D in (cfg.plant.D_min, cfg.plant.D_max)})
"""


def gate_process(cfg: str) -> float:
    """Wall time of the gate in a process of its own, as a run would start it: a fresh
    interpreter, the config as JSON on stdin, the gate and the plan's eigenvalues."""
    from rig_runtime import config, schema
    text = json.dumps(schema.to_dict(config.load(cfg)))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", _GATE_CHILD], cwd=ROOT, input=text, capture_output=True, text=True,
                   env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True)
    return time.perf_counter() - t0


def sample(kind: str, cfg: str) -> dict:
    code = "import json\n" + _CHILD
    r = subprocess.run([sys.executable, "-c", code, kind, cfg], cwd=ROOT, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--config", default=str(ROOT / "configs" / "sim.yaml"))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    out: dict[str, list[dict]] = {"with": [], "without": []}
    elsewhere = []
    for _ in range(a.runs):
        for kind in ("with", "without"):
            out[kind].append(sample(kind, a.config))
        elsewhere.append(gate_process(a.config))
    res = {}
    for kind, rows in out.items():
        res[kind] = {k: statistics.median(r[k] for r in rows) for k in ("rss_kb", "lck_kb", "imports_s", "ready_s", "mlockall_s")}
        res[kind]["min_ready_s"] = min(r["ready_s"] for r in rows)
        res[kind]["mlockall"] = rows[0]["mlockall"]
        res[kind]["loaded"] = rows[0]["loaded"]
    res["gate_process_s"] = statistics.median(elsewhere)
    if a.json:
        print(json.dumps(res))
        return
    print(f"{a.runs} fresh interpreters each, alternating; medians")
    for kind in ("with", "without"):
        r = res[kind]
        print(f"{kind:>8} gate: VmRSS {r['rss_kb'] / 1024:6.1f} MiB  VmLck {r['lck_kb'] / 1024:6.1f} MiB  "
              f"imports {r['imports_s'] * 1e3:6.0f} ms  ready {r['ready_s'] * 1e3:6.0f} ms (min {r['min_ready_s'] * 1e3:.0f})  "
              f"mlockall {r['mlockall_s'] * 1e3:5.0f} ms"
              f"  {r['mlockall']}  loaded {r['loaded']}")
    w, wo = res["with"], res["without"]
    print(f"   cost: VmRSS +{(w['rss_kb'] - wo['rss_kb']) / 1024:.1f} MiB, VmLck +{(w['lck_kb'] - wo['lck_kb']) / 1024:.1f} MiB, "
          f"start-up +{(w['ready_s'] - wo['ready_s']) * 1e3:.0f} ms, mlockall +{(w['mlockall_s'] - wo['mlockall_s']) * 1e3:.0f} ms")
    print(f"   the gate in a process of its own instead: {res['gate_process_s'] * 1e3:.0f} ms wall (median)")


if __name__ == "__main__":
    main()
