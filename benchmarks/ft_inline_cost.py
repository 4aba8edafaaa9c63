"""Cost of the inline F/T poller in lockstep: four simulated sensors on 127.0.0.1, stepped
as the lockstep dry run steps them — ``VirtualFTServer.answer_pending()`` (the simulator's
``advance``), then the driver's ``poll(t)`` — at h = 5 ms, ``poll_hz`` 50 (a round every
4th poll). Wall-clock cost per call, by what the call did.

    python benchmarks/ft_inline_cost.py [--polls N]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from drivers.ft300 import FTSensorSet  # noqa: E402
from rig_runtime.config import FTBus, FTSensor  # noqa: E402
from sim_backend.virtual_ft import VirtualFTServer  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--polls", type=int, default=8000)
    args = ap.parse_args()
    names = ["ft_fl", "ft_fr", "ft_rl", "ft_rr"]
    h = 0.005
    parts: dict[str, list[float]] = {k: [] for k in (
        "poll: collects the replies", "poll: sends the requests", "poll: nothing due",
        "answer_pending: 4 requests", "answer_pending: nothing pending")}
    pc = time.perf_counter
    with VirtualFTServer(names) as srv:
        cfg = FTBus(poller="inline", poll_hz=50.0, sensors=tuple(FTSensor(name=n) for n in names))
        with FTSensorSet(cfg, srv.endpoints) as drv:
            srv.answer_pending()
            links = drv.poller.core.links
            for k in range(1, args.polls + 1):
                t0 = pc()
                n = srv.answer_pending()
                t1 = pc()
                parts["answer_pending: 4 requests" if n else "answer_pending: nothing pending"].append(t1 - t0)
                pending = any(link.pending is not None for link in links)
                t0 = pc()
                drv.poll(k * h)
                t1 = pc()
                sent = any(link.pending is not None for link in links)
                key = ("poll: collects the replies" if pending else
                       "poll: sends the requests" if sent else "poll: nothing due")
                parts[key].append(t1 - t0)
    for name, v in parts.items():
        v.sort()
        if v:
            print(f"{name:32s} n={len(v):6d}  median {v[len(v) // 2] * 1e6:6.1f} µs  "
                  f"p99 {v[int(len(v) * 0.99)] * 1e6:6.1f} µs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
