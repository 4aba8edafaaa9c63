"""What a lockstep dry run costs besides its cycles, run after run in one process (a warm
worker: a campaign's, a test session's): the wall time of ``--runs`` dry runs of
``--duration`` s, and inside each the time spent designing the observers
(``observer_design.designs``), parsing the drives' EDS (``canopen.import_od``) and in the
loop's garbage collection before its first cycle (``gc.collect`` called by loop.py).

Runs the code on ``sys.path``: run it from a tree (``cd TREE && python
benchmarks/fixed_cost_per_run.py``) to measure that tree. The last line: the median wall
and CPU time (this process) of the runs after the first (a warm worker's run).

``--shell N``: instead, ``python -m rig_runtime dry-run --config CONFIG --duration D`` started
N times from this tree (a fresh interpreter each; after one untimed start that writes the
bytecode caches and fills a temporary disk cache, ``RIG_CACHE_DIR``: a config seen before):
median wall and CPU (user + system of the child) per start. ``--no-disk-cache``: every start
computes the gate and the designs and composes the YAML (``RIG_CACHE_DIR=""``; a config
never seen, or a tree without the disk cache).

    python benchmarks/fixed_cost_per_run.py [--config configs/vehicle.yaml] [--runs 4] [--duration 0.1]
    python benchmarks/fixed_cost_per_run.py --config configs/sim.yaml --shell 5
"""

from __future__ import annotations

import argparse
import gc
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import canopen  # noqa: E402

from rig_runtime import config  # noqa: E402
from rig_runtime import loop  # noqa: E402
from rig_runtime.app import dryrun, runner  # noqa: E402
from rig_runtime.scenario import load_scenario  # noqa: E402

spent = {"design": 0.0, "eds": 0.0, "eds_calls": 0, "gc": 0.0}


class _TimedGC:
    """The gc module as loop.py sees it, its ``collect`` timed."""

    def __getattr__(self, name):
        return getattr(gc, name)

    def collect(self, *a):
        t = time.perf_counter()
        try:
            return gc.collect(*a)
        finally:
            spent["gc"] += time.perf_counter() - t


def _timed(f, key, count=None):
    def call(*a, **k):
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            spent[key] += time.perf_counter() - t
            if count:
                spent[count] += 1
    return call


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(config.CONFIG_DIR / "vehicle.yaml"))
    ap.add_argument("--scenario", default="single-step")
    ap.add_argument("--duration", type=float, default=0.1)
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--shell", type=int, default=0, metavar="N")
    ap.add_argument("--no-disk-cache", action="store_true")
    a = ap.parse_args()
    if a.shell:
        return shell(a)
    canopen.import_od = _timed(canopen.import_od, "eds", "eds_calls")
    runner.observer_designs = _timed(runner.observer_designs, "design")
    loop.gc = _TimedGC()
    cfg = config.load(a.config)
    print(f"{Path(a.config).name}, {a.scenario}, {a.duration:g} s per run, one process")
    print(f"  {'run':>4s} {'wall s':>8s} {'observer design s':>18s} {'EDS parse s':>12s} {'EDS parses':>11s} "
          f"{'loop gc.collect s':>18s}")
    walls, cpus = [], []
    for i in range(a.runs):
        for k in spent:
            spent[k] = 0
        t, c = time.perf_counter(), time.process_time()
        with tempfile.TemporaryDirectory() as d:
            dryrun.run_lockstep(cfg, load_scenario(a.scenario), Path(d) / "x.h5", duration_s=a.duration)
        wall, cpu = time.perf_counter() - t, time.process_time() - c
        walls.append(wall)
        cpus.append(cpu)
        print(f"  {i + 1:4d} {wall:8.3f} {spent['design']:18.3f} {spent['eds']:12.4f} {spent['eds_calls']:11d} "
              f"{spent['gc']:18.3f}")
    if a.runs > 1:
        print(f"warm runs (2..{a.runs}): median wall {statistics.median(walls[1:]):.3f} s, "
              f"median CPU {statistics.median(cpus[1:]):.3f} s; load average {os.getloadavg()[0]:.1f}")
    return 0


def shell(a) -> int:
    """``rig dry-run`` from the shell, ``a.shell`` times (one untimed start first)."""
    root = Path(__file__).resolve().parent.parent
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    cmd = [sys.executable, "-m", "rig_runtime", "dry-run", "--config", a.config, "--scenario", a.scenario,
           "--duration", str(a.duration)]
    with tempfile.TemporaryDirectory() as d:
        env["RIG_CACHE_DIR"] = "" if a.no_disk_cache else str(Path(d) / "cache")
        cmd += ["--log", str(Path(d) / "warm.h5")]
        subprocess.run(cmd, cwd=root, env=env, check=True, stdout=subprocess.DEVNULL)
        walls, cpus = [], []
        for i in range(a.shell):
            cmd[-1] = str(Path(d) / f"x{i}.h5")
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t = time.perf_counter()
            subprocess.run(cmd, cwd=root, env=env, check=True, stdout=subprocess.DEVNULL)
            walls.append(time.perf_counter() - t)
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpus.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
    print(f"rig dry-run --duration {a.duration:g} ({Path(a.config).name}) from the shell, {a.shell} starts, "
          f"disk cache {'off' if a.no_disk_cache else 'warm'}: "
          f"median wall {statistics.median(walls):.3f} s (min {min(walls):.3f}), median CPU "
          f"{statistics.median(cpus):.3f} s; load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
