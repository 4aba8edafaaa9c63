"""Where a lockstep dry-run cycle spends its time: wraps the simulated rig's and the
device set's per-cycle calls with timers and runs the single-step scenario.

Per part: the mean per cycle (what the real-time factor pays) and the median per call
(robust against other processes preempting this one). In the simulator, "virtual
drives" handles the runtime's frames (the replies wait in an outbox), "frames sent" sends
the replies; "laser frames written to the wires" samples, encodes and writes every laser's
frames (into in-process serial lines with ``sim.wires: memory``, the default, or pty
pairs with ``kernel``); over ptys the replies, the wheel speeds and the F/T work run while
the kernel delivers the laser bytes, and what is left of that wait is "wait until the
laser bytes are delivered" (nothing to wait for on a memory line), the last part of
``advance``. "advance" is the whole simulator step (the parts plus what is not timed
separately). The runtime's stages of the cycle (loop.py) are timed too: the geometry, the
measured speed, the supervisor, the observer, control (the lanes' schedule and law), the
output limit and the log row.

The two sums at the end are the acceptance of docs/performance.md ("In-memory wires"):
"wires" = the simulated devices, the drivers and the transport (``advance`` without the
plant step, plus ``devices.poll`` and ``devices.write``); "plant + runtime stages" = the
plant step plus the loop's stages. The plant step is ``SimulatedRig.step``: the plant's own
step plus what the simulation does around it each step (scenario forces and faults
switched, the roller speed of the scenario's profile, the free-spinning lifted wheels);
the plant's own step alone is shown inside it. Each sum is given from the means and, robust against
other processes preempting this one on a shared machine, from the medians (median per
call × calls per cycle); "whole cycle, median" is the median time from one release of the
lockstep clock to the next. "CPU time per cycle" is the loop thread's own CPU time
(``time.thread_time``) from one release to the next, mean and median: unlike the wall
time it does not count the time the process waits while others run on a loaded machine.

With several ``--config`` (or ``--wires``) the runs are made one after the other in one
process and shown side by side (e.g. the paper's single-carrier set-up against the vehicle,
or memory wires against kernel wires). ``--clock cpu`` times the parts with the loop thread's
CPU time (``time.thread_time``) instead of the wall clock: medians that hold on a loaded
machine, each call paying a clock read of ≈ 0.3 µs more.

    python benchmarks/lockstep_breakdown.py [--duration S] [--scenario NAME] [--clock wall|cpu]
    python benchmarks/lockstep_breakdown.py --config configs/sim.yaml --config configs/vehicle.yaml
    python benchmarks/lockstep_breakdown.py --wires memory --wires kernel
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from rig_runtime.loop import ControlLoop  # noqa: E402
from rig_runtime.scenario import load_scenario  # noqa: E402
from rig_runtime.speed import SpeedEstimate  # noqa: E402
from rig_runtime.app import dryrun  # noqa: E402

samples: dict[str, list[float]] = collections.defaultdict(list)
STAGES = ((ControlLoop, "_measure", "runtime: stage geometry (_measure)"),
          (SpeedEstimate, "update", "runtime: stage measured speed"),
          (ControlLoop, "_supervise", "runtime: stage supervisor (rules)"),
          (ControlLoop, "_estimate", "runtime: stage observer (_estimate)"),
          (ControlLoop, "_control", "runtime: stage control (schedule + law)"),
          (ControlLoop, "_limit", "runtime: stage output limit"),
          (ControlLoop, "row", "runtime: log row"))


CLOCK = {"wall": time.perf_counter, "cpu": time.thread_time}
clock = CLOCK["wall"]           # what the parts are timed with (--clock)


def timed(f, key: str):
    out = samples[key]
    pc = clock

    def call(*a, **k):
        t = pc()
        r = f(*a, **k)
        out.append(pc() - t)
        return r
    return call


def wrap(obj, name: str, key: str) -> None:
    setattr(obj, name, timed(getattr(obj, name), key))


def prepare(sim, dev, clock) -> None:
    marks, cpu_marks = samples["cycle marks"], samples["cycle cpu marks"]
    wait_until, pc, tt = clock.wait_until, time.perf_counter, time.thread_time

    def marked(t):
        marks.append(pc())
        cpu_marks.append(tt())
        return wait_until(t)
    clock.wait_until = marked
    if hasattr(clock, "_advance"):          # the clock holds the bound method already
        clock._advance = timed(clock._advance, "sim: advance (all below)")
    wrap(sim, "step", "sim:   plant step (SimulatedRig.step)")
    wrap(sim.plant, "step", "sim:     the plant alone (Plant.step)")
    wrap(sim.drives, "service", "sim:   virtual drives")
    wrap(sim.drives, "release", "sim:   virtual drives: frames sent")
    wrap(sim, "set_laser_distances", "sim:   laser distances (geometry)")
    wrap(sim._laser_group, "emit", "sim:   laser frames written to the wires")
    wrap(sim, "set_wheel_speeds", "sim:   wheel speeds")
    if sim.ft is not None:
        wrap(sim.ft, "set_wrench", "sim:   F/T registers")
        wrap(sim.ft, "answer_pending", "sim:   F/T requests answered")
    wrap(sim._laser_group, "wait", "sim:   wait until the laser bytes are delivered")
    if dev.ft is not None:
        wrap(dev.ft, "poll", "runtime:   F/T poll (inline: sends and collects)")
    wrap(dev, "poll", "runtime: devices.poll (all below)")
    for d in dev.lasers:
        wrap(d, "poll", "runtime:   laser polls")
    wrap(dev.drives, "poll", "runtime:   drive bus poll")
    wrap(dev, "write", "runtime: devices.write")


def measure(path, scenario: str, duration: float, wires=None) -> tuple[dict, dict[str, list[float]]]:
    """One run of ``scenario`` with config ``path`` (None: the default) and ``sim.wires``
    (None: the config's); its summary and timers."""
    samples.clear()
    cfg = config.load(path) if path else config.load()
    if wires is not None:
        cfg = dataclasses.replace(cfg, sim={**(cfg.sim or {}), "wires": wires})
    originals = [(cls, name, getattr(cls, name)) for cls, name, _ in STAGES]
    for cls, name, key in STAGES:
        setattr(cls, name, timed(getattr(cls, name), key))
    try:
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as d:
            s, _ = dryrun.run_lockstep(cfg, load_scenario(scenario), Path(d) / "x.h5",
                                       duration_s=duration, prepare=prepare)
        s["wall_all"] = time.perf_counter() - t0
    finally:
        for cls, name, f in originals:
            setattr(cls, name, f)
    marks = samples.pop("cycle marks", [])
    cpu = samples.pop("cycle cpu marks", [])
    s["cycle_p50_us"] = statistics.median(b - a for a, b in zip(marks, marks[1:])) * 1e6 if len(marks) > 2 else 0.0
    # the loop thread's CPU time per cycle (time.thread_time: not counting the time this
    # process waits preempted by others — the figure that holds on a loaded machine)
    s["cycle_cpu_p50_us"] = statistics.median(b - a for a, b in zip(cpu, cpu[1:])) * 1e6 if len(cpu) > 2 else 0.0
    s["cycle_cpu_mean_us"] = (cpu[-1] - cpu[0]) / (len(cpu) - 1) * 1e6 if len(cpu) > 2 else 0.0
    return s, {k: list(v) for k, v in samples.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--scenario", default="single-step")
    ap.add_argument("--config", action="append", help="a config (repeat: side by side; default: the shipped one)")
    ap.add_argument("--wires", action="append", choices=("memory", "kernel"),
                    help="sim.wires (repeat: side by side; default: the config's)")
    ap.add_argument("--clock", choices=tuple(CLOCK), default="wall",
                    help="time the parts on the wall clock (default) or the loop thread's CPU time")
    args = ap.parse_args()
    global clock
    clock = CLOCK[args.clock]
    runs = [(f"{p or 'default'}" + (f" ({w})" if w else ""), *measure(p, args.scenario, args.duration, w))
            for p in (args.config or [None]) for w in (args.wires or [None])]
    if len(runs) == 1:
        _, s, smp = runs[0]
        n = s["cycles"]
        print(f"{n} cycles, {s['wall_all'] / n * 1e6:.0f} us per cycle in all (incl. set-up), "
              f"{s['wall_time_s'] / n * 1e6:.0f} us in the loop, whole cycle median {s['cycle_p50_us']:.1f} us; "
              f"CPU time per cycle mean {s['cycle_cpu_mean_us']:.1f} us, median {s['cycle_cpu_p50_us']:.1f} us")
        print(f"  {'':46s} {'mean us/cycle':>14s} {'p50 us/call':>12s} {'calls/cycle':>12s}")
        for k, v in smp.items():
            if v:
                print(f"  {k:46s} {sum(v) / n * 1e6:14.1f} {statistics.median(v) * 1e6:12.1f} {len(v) / n:12.2f}")
        (wires, plant_rt), (wires50, plant_rt50) = sums(s, smp), sums(s, smp, p50=True)
        print(f"  {'= wires (devices + drivers + transport)':46s} {wires:14.1f} {wires50:12.1f}")
        print(f"  {'= plant step + runtime stages':46s} {plant_rt:14.1f} {plant_rt50:12.1f}")
        return 0
    print(f"us ({args.clock} clock): mean per cycle / median per call ({args.scenario}, {args.duration:g} s); config: " +
          ", ".join(f"[{i}] {name}" for i, (name, _, _) in enumerate(runs)))
    print(f"  {'':46s} " + " ".join(f"{f'[{i}] mean':>9s} {'p50':>7s}" for i in range(len(runs))))
    print(f"  {'in the loop (whole cycle)':46s} " +
          " ".join(f"{s['wall_time_s'] / s['cycles'] * 1e6:9.1f} {s['cycle_p50_us']:7.1f}" for _, s, _ in runs))
    print(f"  {'CPU time per cycle (thread_time)':46s} " +
          " ".join(f"{s['cycle_cpu_mean_us']:9.1f} {s['cycle_cpu_p50_us']:7.1f}" for _, s, _ in runs))
    keys = list(dict.fromkeys(k for _, _, smp in runs for k in smp))
    for k in keys:
        cells = []
        for _, s, smp in runs:
            v = smp.get(k, [])
            cells.append(f"{sum(v) / s['cycles'] * 1e6:9.1f} {statistics.median(v) * 1e6 if v else 0.0:7.1f}")
        print(f"  {k:46s} " + " ".join(cells))
    for i, label in enumerate(("= wires (devices + drivers + transport)", "= plant step + runtime stages")):
        print(f"  {label:46s} " + " ".join(f"{sums(s, smp)[i]:9.1f} {sums(s, smp, p50=True)[i]:7.1f}"
                                           for _, s, smp in runs))
    return 0


def sums(s: dict, smp: dict[str, list[float]], p50: bool = False) -> tuple[float, float]:
    """(wires, plant step + runtime stages), us per cycle (see the module docstring): from
    the means, or (``p50``) from median per call × calls per cycle."""
    n = s["cycles"]

    def tot(k: str) -> float:
        v = smp.get(k, ())
        if not v:
            return 0.0
        return statistics.median(v) * len(v) / n * 1e6 if p50 else sum(v) / n * 1e6
    plant = tot("sim:   plant step (SimulatedRig.step)")
    wires = (tot("sim: advance (all below)") - plant + tot("runtime: devices.poll (all below)")
             + tot("runtime: devices.write"))
    return wires, plant + sum(tot(key) for _, _, key in STAGES)


if __name__ == "__main__":
    sys.exit(main())
