"""How long the laser driver's ``poll()`` takes on a pty, by what its line discipline holds:
the wait for the kernel's flip-buffer worker that docs/sim-process.md item 6 describes.

Three cases, interleaved cycle by cycle on one pty (raw, opened by the driver via pyserial):

* ``empty``     — nothing in the line discipline and nothing on its way (the port was drained);
* ``in_flight`` — one 3-byte frame written to the master just before the poll: the kernel
  has queued its flip-buffer work but (usually) not run it, the line discipline is empty —
  the real loop's situation with a 4 kHz laser whose last frame is a few µs old;
* ``pending``   — one period's 60 bytes written and delivered (``TIOCINQ`` spun on, untimed)
  before the poll.

``--load`` runs the same beside ``--hogs`` CPU-bound processes (SCHED_OTHER) and a writer
thread streaming 3-byte frames at 4 kHz through a second pty (and reading them back), which
keeps the kworkers busy with tty work as six lasers and an SLCAN adapter do.

    python benchmarks/pty_read_wait.py [--cycles N] [--fifo PRIO] [--load] [--hogs N] [--json]

Old vs new: run it once more with ``PYTHONPATH`` at a worktree of the older commit (the script
imports ``drivers.laser`` from the first ``drivers`` package on the path). ``--fifo P`` runs
the measuring thread SCHED_FIFO P as the control loop runs. Times in µs.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import multiprocessing
import os
import sys
import termios
import threading
import time
import tty
from pathlib import Path

if not os.environ.get("PYTHONPATH"):
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(1, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

import drivers.laser as laser_mod  # noqa: E402
from drivers.laser import LaserDriver  # noqa: E402
from drivers.optoncdt import encode_value  # noqa: E402
from rig_runtime.config import LaserDevice  # noqa: E402

from _machine import StealMeter  # noqa: E402

CASES = ("empty", "in_flight", "pending")
FRAME = encode_value(32760)            # one valid 3-byte frame
PERIOD_BYTES = FRAME * 20              # a 5 ms period at 4 kHz


def _inq(fd: int, b: bytearray = bytearray(4)) -> int:
    fcntl.ioctl(fd, termios.FIONREAD, b, True)
    return int.from_bytes(b, "little", signed=True)


def _hog(stop) -> None:
    """Child process: burn CPU at SCHED_OTHER until told to stop."""
    x = 0
    while not stop.is_set():
        for _ in range(10000):
            x += 1


def _writer(stop: threading.Event) -> None:
    """Stream 3-byte frames at 4 kHz through a pty of its own and read them back."""
    m, s = os.openpty()
    tty.setraw(s)
    os.set_blocking(m, False)
    os.set_blocking(s, False)
    t = time.monotonic()
    try:
        while not stop.is_set():
            t += 250e-6
            try:
                os.write(m, FRAME)
                os.read(s, 4096)
            except (BlockingIOError, OSError):
                pass
            d = t - time.monotonic()
            if d > 0:
                time.sleep(d)
    finally:
        os.close(m)
        os.close(s)


def dist(a: list[float]) -> dict:
    x = np.asarray(a) * 1e6
    return {"n": int(x.size), "p50": round(float(np.percentile(x, 50)), 1),
            "p99": round(float(np.percentile(x, 99)), 1), "max": round(float(x.max()), 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=2000, help="timed polls per case")
    ap.add_argument("--fifo", type=int, help="SCHED_FIFO priority of the measuring thread (if permitted)")
    ap.add_argument("--load", action="store_true", help="CPU hogs + a pty writer thread beside it")
    ap.add_argument("--hogs", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--gap-ms", type=float, default=1.0, help="sleep between cycles")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    master, slave = os.openpty()
    os.set_blocking(master, False)
    drv = LaserDriver(LaserDevice(role="b_f", port="", measuring_range_mm=50.0, offset_mm=45.0),
                      port=os.ttyname(slave))
    drv.configure()
    fd = drv._ser.fd
    hogs, stop_hogs, stop_writer, writer = [], None, threading.Event(), None
    if args.load:
        ctx = multiprocessing.get_context("spawn")
        stop_hogs = ctx.Event()
        hogs = [ctx.Process(target=_hog, args=(stop_hogs,), daemon=True) for _ in range(args.hogs)]
        for p in hogs:
            p.start()
        writer = threading.Thread(target=_writer, args=(stop_writer,), daemon=True)
        writer.start()
        time.sleep(0.5)
    fifo = "not requested"
    if args.fifo:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.fifo))
            fifo = f"SCHED_FIFO {args.fifo}: applied"
        except (PermissionError, OSError) as e:
            fifo = f"SCHED_FIFO {args.fifo}: not applied ({e})"
    times = {c: [] for c in CASES}
    got_bytes = {c: 0 for c in CASES}
    undelivered = 0
    clock = time.perf_counter
    now = 0.0
    try:
        with StealMeter() as steal:
            for k in range(args.cycles * len(CASES)):
                case = CASES[k % len(CASES)]
                if case == "pending":
                    os.write(master, PERIOD_BYTES)
                    end = clock() + 1.0
                    while _inq(fd) < len(PERIOD_BYTES) and clock() < end:
                        pass
                    undelivered += _inq(fd) < len(PERIOD_BYTES)
                elif case == "in_flight":
                    os.write(master, FRAME)
                now += 0.005
                b0 = drv.counters()["bytes"]
                t0 = clock()
                drv.poll(now)
                times[case].append(clock() - t0)
                got_bytes[case] += drv.counters()["bytes"] - b0
                time.sleep(args.gap_ms / 1000.0)
                drv.poll(now + 0.001)                      # drain what arrived late (untimed)
    finally:
        stop_writer.set()
        if stop_hogs is not None:
            stop_hogs.set()
        for p in hogs:
            p.join(2.0)
        if writer is not None:
            writer.join(2.0)
        drv.close()
        os.close(master)
        os.close(slave)
    out = {"driver": str(Path(laser_mod.__file__).resolve()), "load": args.load,
           "hogs": args.hogs if args.load else 0, "fifo": fifo, "cycles_per_case": args.cycles,
           "cpu_steal_pct": steal.percent, "loadavg_1min": os.getloadavg()[0],
           "pending_not_delivered_in_1s": undelivered,
           "poll_us": {c: dist(times[c]) for c in CASES},
           "bytes_read_in_the_timed_poll": got_bytes}
    if args.json:
        print(json.dumps(out))
    else:
        print(f"driver {out['driver']}; load {args.load}; {fifo}; steal {steal.percent}; "
              f"loadavg {out['loadavg_1min']:.2f}")
        for c in CASES:
            d = out["poll_us"][c]
            print(f"  {c:10s} p50 {d['p50']:8.1f}  p99 {d['p99']:8.1f}  max {d['max']:9.1f} µs  "
                  f"(bytes read in the timed polls: {got_bytes[c]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
