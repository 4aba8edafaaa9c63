"""Real-time loop timing: the machine's floor (a bare sleep-then-spin loop) and the full
runtime cycle against the simulated devices, in one process and one run.

The simulated rig is served by ``rig sim`` in a separate process (lasers on ptys, an SLCAN
adapter on a pty, Modbus TCP on 127.0.0.1), started first so that both parts see the same
background load. Then, in this process: the bare loop for ``--duration`` seconds, then the
runtime (``rig run``'s devices, loop, supervisor and recorder on the real-time clock,
holding y_ref = 0) for ``--duration`` seconds. Resident memory of this process is sampled
after one minute of the runtime part and at its end.

    python benchmarks/loop_timing.py [--duration S] [--bare-duration S] [--json] [--fifo PRIO] [--cpu N]

With ``--fifo P`` this process runs SCHED_FIFO P and the simulator SCHED_FIFO P − 30 (when
the OS permits; reported either way).
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from rig_runtime.clock import RealtimeClock, apply_realtime  # noqa: E402
from rig_runtime.devices import RigDevices  # noqa: E402
from rig_runtime.app.runner import execute  # noqa: E402
from rig_runtime.stats import CycleStats  # noqa: E402
from sim_backend.launcher import start_sim_process  # noqa: E402


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


def bare_loop(clock: RealtimeClock, h: float, duration: float) -> dict:
    stats = CycleStats()
    n = int(duration / h)
    gc.collect(); gc.freeze(); gc.disable()
    t0 = clock.now() + h
    k = 0
    while k < n:
        t_k = t0 + k * h
        t = clock.wait_until(t_k)
        t_done = clock.now()
        missed = t_done > t_k + h
        k_next = int((t_done - t0) / h) + 1 if missed else k + 1
        stats.update(t - t_k, t_done - t, missed, k_next - k - 1)
        k = k_next
    gc.enable(); gc.unfreeze()
    s = stats.summary()
    s.pop("skipped_periods")
    return s


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of the runtime part (default 60)")
    ap.add_argument("--bare-duration", type=float, help="seconds of the bare loop (default: --duration)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--fifo", type=int, help="SCHED_FIFO priority for this process (if permitted)")
    ap.add_argument("--cpu", type=int, help="pin this process to one CPU (the simulator gets the others)")
    args = ap.parse_args()
    for name in ("pymodbus", "can", "canopen"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    sim_args = ["--rt-priority", str(max(1, args.fifo - 30))] if args.fifo else []
    if args.cpu is not None:
        others = sorted(set(os.sched_getaffinity(0)) - {args.cpu})
        if others:
            sim_args += ["--cpu-affinity", ",".join(map(str, others))]
    with tempfile.TemporaryDirectory() as d, start_sim_process(seed=0, workdir=Path(d) / "sim", extra_args=sim_args) as sp:
        cfg = config.load(sp.config_path)
        cfg = dataclasses.replace(cfg, realtime=dataclasses.replace(
            cfg.realtime, sched_fifo_priority=args.fifo,
            cpu_affinity=(args.cpu,) if args.cpu is not None else None))
        rt = apply_realtime(cfg.realtime)
        h = cfg.controller.h
        clock = RealtimeClock(cfg.realtime.spin_us * 1e-6)
        bare = bare_loop(clock, h, args.bare_duration or args.duration)
        rss = {}
        t_first = [None]

        def sample(loop) -> None:
            now = time.monotonic()
            if t_first[0] is None:
                t_first[0] = now
            if "after_1min" not in rss and now - t_first[0] >= 60.0:
                rss["after_1min"] = rss_mb()

        import rig_runtime.app.runner as runner
        orig = runner.StatusLine
        runner.StatusLine = lambda: sample  # sample memory from the loop's status hook (every 0.2 s)
        try:
            summary, code, _ = execute(cfg, RigDevices(cfg), clock, scenario=None, duration_s=args.duration,
                                       log_path=Path(d) / "timing.h5", status=True,
                                       extra_attrs={"mode": "benchmark loop_timing"})
        finally:
            runner.StatusLine = orig
        rss["end"] = rss_mb()
        try:        # the simulator's side of the SYNC -> TPDO path, to tell whose fault a gap was
            sim_stats = sp.status().get("session_stats", {})
        except (OSError, ValueError):
            sim_stats = {}
        t = summary["timing"]
        runtime = {"release_lateness_us": t["release_lateness_us"], "cycle_work_us": t["cycle_work_us"],
                   "deadline_misses": t["deadline_misses"], "final_state": summary["final_state"],
                   "faults": summary["faults"], "cycles": summary["cycles"]}
    out = {"bare": bare, "runtime": runtime,
           "ratio": {"lateness_p99": runtime["release_lateness_us"]["p99"] / max(bare["release_lateness_us"]["p99"], 1e-9),
                     "lateness_p999": runtime["release_lateness_us"]["p999"] / max(bare["release_lateness_us"]["p999"], 1e-9)},
           "rss_mb": rss, "duration_s": args.duration, "bare_duration_s": args.bare_duration or args.duration,
           "realtime": rt, "sim_session_stats": sim_stats}
    if args.json:
        print(json.dumps(out))
    else:
        for name in ("bare", "runtime"):
            r = out[name]
            la, wk = r["release_lateness_us"], r["cycle_work_us"]
            print(f"{name:8s} lateness p50/p99/p99.9/max {la['p50']:.1f}/{la['p99']:.1f}/{la['p999']:.1f}/{la['max']:.1f} us   "
                  f"work p50/p99/p99.9/max {wk['p50']:.1f}/{wk['p99']:.1f}/{wk['p999']:.1f}/{wk['max']:.1f} us   "
                  f"misses {r['deadline_misses']}")
        print(f"ratio runtime/bare lateness: p99 {out['ratio']['lateness_p99']:.2f}, p99.9 {out['ratio']['lateness_p999']:.2f}")
        print(f"runtime final state {runtime['final_state']}, faults {runtime['faults']}")
        print(f"resident memory: {rss}")
        print("realtime: " + "; ".join(rt))
    return 0


if __name__ == "__main__":
    sys.exit(main())
