"""Real-time loop timing: the machine's floor (a bare sleep-then-spin loop) and the full
runtime cycle against the simulated devices, in one process and one run.

The simulated rig is served by ``rig sim`` in a separate process (lasers on ptys, an SLCAN
adapter on a pty, Modbus TCP on 127.0.0.1), started first so that every part sees the same
background load. Then, in this process: the bare loop for ``--bare-duration`` seconds; the
runtime (``rig run``'s devices, loop and supervisor on the real-time clock, holding
y_ref = 0) with recording and telemetry off (no log, no sidecar) and with both on (the HDF5
log through the recording sidecar, UDP telemetry of every cycle to a receiver in another
process), in the order off, on, on, off, ``--duration`` / 2 seconds each. Resident memory of this process is sampled after one minute of the last
part and at its end; its thread count while the loop runs.

    python benchmarks/loop_timing.py [--duration S] [--bare-duration S] [--json] [--fifo PRIO] [--cpu N]

Goals (``docs/performance.md``): the runtime's lateness p99.9 within 1.2x the bare loop's;
cycle-work p50 with recording and telemetry on within 1.1x of it with them off.

With ``--fifo P`` this process runs SCHED_FIFO P and the simulator SCHED_FIFO P − 30 (when
the OS permits; reported either way).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):    # as the `rig` command does:
    os.environ.setdefault(_var, "1")                                        # one thread in the loop's process

from rig_runtime import config  # noqa: E402
from rig_runtime.clock import RealtimeClock, apply_realtime  # noqa: E402
from rig_runtime.devices import RigDevices  # noqa: E402
from rig_runtime.app.bare_loop import bare_loop as run_bare_loop  # noqa: E402
from rig_runtime.app.runner import execute  # noqa: E402
from rig_runtime.stats import CycleStats  # noqa: E402
from sim_backend.launcher import start_sim_process  # noqa: E402


DRAIN = """
import signal, socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", 0))
print(s.getsockname()[1], flush=True)
n = 0
signal.signal(signal.SIGTERM, lambda *a: (print(n, flush=True), sys.exit(0)))
while True:
    s.recv(4096)
    n += 1
"""


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


def bare_loop(clock: RealtimeClock, h: float, duration: float) -> dict:
    s = run_bare_loop(clock, h, duration).summary()
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
        rss: dict = {}
        threads: set = set()
        t_first = [None]

        def sample(loop) -> None:
            now = time.monotonic()
            threads.add(len(os.listdir("/proc/self/task")))
            if t_first[0] is None:
                t_first[0] = now
            if "after_1min" not in rss and now - t_first[0] >= 60.0:
                rss["after_1min"] = rss_mb()

        import rig_runtime.app.runner as runner
        from rig_runtime.app.live import outputs_for

        class Publisher(runner.StatusPublisher):
            def __call__(self, loop) -> None:
                super().__call__(loop)
                sample(loop)

        def runtime_part(log_path, outputs, duration) -> dict:
            orig = runner.StatusLine, runner.StatusPublisher
            runner.StatusLine = lambda: sample  # sample from the loop's status hook (every 0.2 s)
            runner.StatusPublisher = Publisher
            try:
                summary, code, _ = execute(cfg, RigDevices(cfg), clock, scenario=None, duration_s=duration,
                                           log_path=log_path, status=True, outputs=outputs,
                                           extra_attrs={"mode": "benchmark loop_timing"})
            finally:
                runner.StatusLine, runner.StatusPublisher = orig
            t = summary["timing"]
            return {"release_lateness_us": t["release_lateness_us"], "cycle_work_us": t["cycle_work_us"],
                    "deadline_misses": t["deadline_misses"], "final_state": summary["final_state"],
                    "faults": summary["faults"], "cycles": summary["cycles"], "recorder": summary["recorder"]}

        # A-B-B-A, half the duration each: a drift of the machine over the run (other tenants,
        # thermal, the simulator's state) weighs on both kinds alike
        receiver = subprocess.Popen([sys.executable, "-c", DRAIN], stdout=subprocess.PIPE, text=True)
        port = int(receiver.stdout.readline())
        parts: dict[str, list] = {"off": [], "on": []}
        thread_counts: dict[str, set] = {"off": set(), "on": set()}
        half = args.duration / 2
        try:
            for n, kind in enumerate(("off", "on", "on", "off")):
                threads.clear()
                if kind == "off":
                    r = runtime_part(None, [], half)
                else:
                    r = runtime_part(Path(d) / f"timing-{n}.h5", outputs_for(telemetry=f"udp://127.0.0.1:{port}"), half)
                parts[kind].append(r)
                thread_counts[kind] |= threads
        finally:
            receiver.terminate()
            datagrams = int(receiver.communicate(timeout=10)[0] or 0)
        rss["end"] = rss_mb()
        try:        # the simulator's side of the SYNC -> TPDO path, to tell whose fault a gap was
            sim_stats = sp.status().get("session_stats", {})
        except (OSError, ValueError):
            sim_stats = {}

    def ratio(a, b):
        return a / max(b, 1e-9)

    def worst(kind, q):             # the worse of the two parts of a kind
        return max(r["release_lateness_us"][q] for r in parts[kind])

    def mean_work(kind, q):
        return sum(r["cycle_work_us"][q] for r in parts[kind]) / len(parts[kind])
    bare_p999 = bare["release_lateness_us"]["p999"]
    out = {"bare": bare, "runtime_off": parts["off"], "runtime_on": parts["on"],
           "ratio": {"lateness_p999_off_vs_bare": ratio(worst("off", "p999"), bare_p999),
                     "lateness_p999_on_vs_bare": ratio(worst("on", "p999"), bare_p999),
                     "work_p50_on_vs_off": ratio(mean_work("on", "p50"), mean_work("off", "p50"))},
           "threads_in_loop_process": {k: sorted(v) for k, v in thread_counts.items()},
           "telemetry_datagrams_received": datagrams,
           "rss_mb": rss, "duration_s": args.duration, "bare_duration_s": args.bare_duration or args.duration,
           "realtime": rt, "sim_session_stats": sim_stats}
    if args.json:
        print(json.dumps(out))
    else:
        rows = [("bare", bare)] + [(f"{k} ({n + 1}/2)", r) for k in ("off", "on") for n, r in enumerate(parts[k])]
        for name, r in rows:
            la, wk = r["release_lateness_us"], r["cycle_work_us"]
            print(f"{name:12s} lateness p50/p99/p99.9/max {la['p50']:.1f}/{la['p99']:.1f}/{la['p999']:.1f}/{la['max']:.1f} us   "
                  f"work p50/p99/p99.9/max {wk['p50']:.1f}/{wk['p99']:.1f}/{wk['p999']:.1f}/{wk['max']:.1f} us   "
                  f"misses {r['deadline_misses']}")
        r = out["ratio"]
        print(f"lateness p99.9 runtime (worse part)/bare: off {r['lateness_p999_off_vs_bare']:.2f}, "
              f"on {r['lateness_p999_on_vs_bare']:.2f} (goal <= 1.2)   work p50 on/off (mean of the parts): "
              f"{r['work_p50_on_vs_off']:.2f} (goal <= 1.1)")
        for k in ("off", "on"):
            for n, x in enumerate(parts[k]):
                print(f"{k} ({n + 1}/2): final state {x['final_state']}, faults {x['faults']}, recorder {x['recorder']}")
        print(f"threads in the loop's process: {out['threads_in_loop_process']}; "
              f"telemetry datagrams received: {datagrams}")
        print(f"resident memory: {rss}")
        print("realtime: " + "; ".join(rt))
    return 0


if __name__ == "__main__":
    sys.exit(main())
