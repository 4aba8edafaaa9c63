"""The runtime's own per-cycle cost in a lockstep run, stage by stage, without the simulated
wires: the median per cycle of each stage of loop.py (geometry, measured speed, supervisor,
observer, control, output limit, log row) and of ``devices.poll``'s own work (the poll minus
the drivers' polls inside it: filing the readings under their names; what timing each driver's
poll adds is measured on an empty call and taken off). Each call is timed in
the loop thread's CPU time (``time.thread_time``: the time other processes of a shared machine
take is not counted) and the median of many cycles is shown (robust against the rest).

Measures this tree, or the one given with ``--tree``; ``--base DIR`` measures another tree (a
checkout of an older commit) side by side, the two alternating run by run, each run in a fresh
process, and gives the ratio base / this. ``--repeat`` runs of each, the median of each stage's
per-run medians:

    python benchmarks/runtime_stage_cost.py [--config configs/vehicle.yaml] [--duration S] [--repeat N]
    python benchmarks/runtime_stage_cost.py --base /tmp/before [--config ...]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent


def _tree() -> Path:
    """The tree whose code is measured: ``--tree DIR`` (before the imports below), else this one."""
    if "--tree" in sys.argv:
        return Path(sys.argv[sys.argv.index("--tree") + 1]).resolve()
    return HERE


sys.path.insert(0, str(_tree()))

from rig_runtime import config  # noqa: E402
from rig_runtime.loop import ControlLoop  # noqa: E402
from rig_runtime.speed import SpeedEstimate  # noqa: E402
from rig_runtime.scenario import load_scenario  # noqa: E402
from rig_runtime.app import dryrun  # noqa: E402

STAGES = ((ControlLoop, "_measure", "geometry (_measure)"),
          (SpeedEstimate, "update", "measured speed"),
          (ControlLoop, "_supervise", "supervisor"),
          (ControlLoop, "_estimate", "observer (_estimate)"),
          (ControlLoop, "_control", "control"),
          (ControlLoop, "_limit", "output limit"),
          (ControlLoop, "row", "log row"))
POLL_OWN = "devices.poll: own work (minus the drivers)"


def one_run(path: str, scenario: str, duration: float) -> dict[str, float]:
    pc = time.thread_time
    samples: dict[str, list[float]] = collections.defaultdict(list)
    inner = [0.0]
    calls = [0]                         # the drivers' polls timed inside this devices.poll

    def timed(f, key):
        out = samples[key]

        def call(*a, **k):
            t = pc()
            r = f(*a, **k)
            out.append(pc() - t)
            return r
        return call

    def child(f):
        def call(*a, **k):
            t = pc()
            r = f(*a, **k)
            inner[0] += pc() - t
            calls[0] += 1
            return r
        return call

    # what timing a driver's poll adds to the devices.poll around it (the wrapper and its two
    # clock reads, outside the interval it subtracts): measured on an empty call, taken off
    def nop(now):
        return None
    wrapped, bare = child(nop), []
    for f, out in ((wrapped, []), (nop, bare)):
        for _ in range(20000):
            inner[0] = 0.0
            t = pc()
            f(0.0)
            out.append(pc() - t - inner[0])
        if f is wrapped:
            with_timer = out
    per_child = max(0.0, statistics.median(with_timer) - statistics.median(bare))

    def prepare(sim, dev, clock):
        for d in dev.lasers:
            d.poll = child(d.poll)
        dev.drives.poll = child(dev.drives.poll)
        if dev.ft is not None:
            dev.ft.poll = child(dev.ft.poll)
        outer = dev.poll
        own = samples[POLL_OWN]

        def poll(now):
            inner[0] = 0.0
            calls[0] = 0
            t = pc()
            r = outer(now)
            own.append(pc() - t - inner[0] - calls[0] * per_child)
            return r
        dev.poll = poll

    cfg = config.load(path)
    originals = [(cls, name, getattr(cls, name)) for cls, name, _ in STAGES]
    for cls, name, key in STAGES:
        setattr(cls, name, timed(getattr(cls, name), key))
    try:
        with tempfile.TemporaryDirectory() as d:
            dryrun.run_lockstep(cfg, load_scenario(scenario), Path(d) / "x.h5", duration_s=duration, prepare=prepare)
    finally:
        for cls, name, f in originals:
            setattr(cls, name, f)
    return {k: statistics.median(v) * 1e6 for k, v in samples.items() if v}


def _in_process(tree: Path, a) -> dict[str, float]:
    """One run of the benchmark on ``tree``'s code in a fresh interpreter."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--tree", str(tree), "--json", "--repeat", "1",
           "--config", str(Path(a.config).resolve()), "--scenario", a.scenario, "--duration", str(a.duration)]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)})
    if p.returncode != 0:
        raise SystemExit(f"{tree}: the run failed (exit {p.returncode}):\n{p.stderr}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(config.CONFIG_DIR / "sim.yaml"))
    ap.add_argument("--scenario", default="single-step")
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--tree", help="the tree whose code is measured (default: this one)")
    ap.add_argument("--base", help="another tree measured side by side (runs alternate, fresh processes)")
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.base is None:
        runs = [one_run(a.config, a.scenario, a.duration) for _ in range(a.repeat)]
        if a.json:
            print(json.dumps(runs[0]))
            return 0
        bases = None
    else:
        runs, bases = [], []
        for _ in range(a.repeat):
            bases.append(_in_process(Path(a.base).resolve(), a))
            runs.append(_in_process(_tree(), a))
    keys = [k for _, _, k in STAGES] + [POLL_OWN]
    print(f"median µs of CPU time per call ({a.scenario}, {a.duration:g} s, {Path(a.config).name}, "
          f"median of {a.repeat} runs)")
    if bases is not None:
        print(f"  {'':46s} {'base':>7s} {'this':>7s} {'base/this':>9s}   (base: {a.base})")
    total = total_b = 0.0
    for k in keys:
        v = statistics.median(r.get(k, 0.0) for r in runs)
        total += v
        if bases is None:
            print(f"  {k:46s} {v:7.2f}")
        else:
            b = statistics.median(r.get(k, 0.0) for r in bases)
            total_b += b
            print(f"  {k:46s} {b:7.2f} {v:7.2f} {b / v if v else float('nan'):8.2f}x")
    if bases is None:
        print(f"  {'sum':46s} {total:7.2f}")
    else:
        print(f"  {'sum':46s} {total_b:7.2f} {total:7.2f} {total_b / total:8.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
