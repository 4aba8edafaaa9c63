"""Cost of the inline F/T poller in lockstep: four simulated sensors, stepped as the
lockstep dry run steps them — ``VirtualFTServer.set_wrench`` when the sensors' 100 Hz
refresh is due and ``answer_pending()`` (the simulator's ``advance``), then the driver's
``poll(t)`` — at h = 5 ms and ``poll_hz`` (default 100, a round every 2nd poll, as
configs/sim.yaml). Over in-process wires (``--stream memory``, the default, as a lockstep
dry run with ``sim.wires: memory``) or loopback TCP (``--stream tcp``). Per call, by what
the call did: the median and p99 of the wall time, and the median of the thread's CPU time
(``time.thread_time``, what holds on a loaded machine); then the mean per 5 ms cycle of
all the calls, wall and CPU time.

    python benchmarks/ft_inline_cost.py [--polls N] [--stream memory|tcp] [--poll-hz HZ]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from drivers.ft300 import FTSensorSet, Wrench  # noqa: E402
from rig_runtime.config import FTBus, FTSensor  # noqa: E402
from sim_backend.virtual_ft import VirtualFTServer  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--polls", type=int, default=8000)
    ap.add_argument("--stream", choices=("memory", "tcp"), default="memory")
    ap.add_argument("--poll-hz", type=float, default=100.0)
    args = ap.parse_args()
    names = ["ft_fl", "ft_fr", "ft_rl", "ft_rr"]
    h, refresh = 0.005, 0.01
    parts: dict[str, list[tuple[float, float]]] = {k: [] for k in (
        "poll: collects the replies", "poll: sends the requests", "poll: nothing due",
        "set_wrench x4 (100 Hz refresh)", "answer_pending: requests", "answer_pending: nothing pending")}
    pc, tt = time.perf_counter, time.thread_time
    with VirtualFTServer(names, stream=args.stream) as srv:
        cfg = FTBus(poller="inline", poll_hz=args.poll_hz, sensors=tuple(FTSensor(name=n) for n in names))
        with FTSensorSet(cfg, srv.endpoints) as drv:
            srv.answer_pending()
            links = drv.poller.core.links
            next_refresh = 0.0
            for k in range(1, args.polls + 1):
                t = k * h
                if t >= next_refresh - 1e-12:
                    next_refresh = t + refresh
                    w0, c0 = pc(), tt()
                    for i, n in enumerate(names):
                        srv.set_wrench(n, Wrench(fx=0.01 * (k % 100), fy=-1.0 - i, mz=0.001 * k % 1.0))
                    parts["set_wrench x4 (100 Hz refresh)"].append((pc() - w0, tt() - c0))
                w0, c0 = pc(), tt()
                n = srv.answer_pending()
                w1, c1 = pc(), tt()
                parts["answer_pending: requests" if n else "answer_pending: nothing pending"].append((w1 - w0, c1 - c0))
                pending = any(link.pending is not None for link in links)
                w0, c0 = pc(), tt()
                drv.poll(t)
                w1, c1 = pc(), tt()
                sent = any(link.pending is not None for link in links)
                key = ("poll: collects the replies" if pending else
                       "poll: sends the requests" if sent else "poll: nothing due")
                parts[key].append((w1 - w0, c1 - c0))
    total = cpu_total = 0.0
    print(f"{args.stream}, poll_hz {args.poll_hz:g}, {args.polls} polls at h = 5 ms")
    for name, v in parts.items():
        if v:
            wall = sorted(w for w, _ in v)
            cpu = statistics.median(c for _, c in v)
            total += sum(w for w, _ in v)
            cpu_total += sum(c for _, c in v)
            print(f"{name:34s} n={len(v):6d}  median {wall[len(wall) // 2] * 1e6:6.1f} µs  "
                  f"p99 {wall[int(len(wall) * 0.99)] * 1e6:6.1f} µs  CPU median {cpu * 1e6:6.1f} µs")
    print(f"{'all of the above, mean per cycle':34s} {total / args.polls * 1e6:6.1f} µs  "
          f"CPU {cpu_total / args.polls * 1e6:6.1f} µs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
