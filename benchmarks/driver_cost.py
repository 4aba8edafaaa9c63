"""What one cycle's ``poll()`` + ``write()`` costs for all devices together, against the
virtual devices: six lasers at 4 kHz on ptys, four CiA 402 drives on a python-can bus
(``LockstepBus``, the in-process bus of the lockstep dry run; ``--can virtual`` uses
python-can's ``virtual`` bus instead, which deep-copies every frame for every receiver),
the F/T hand-off (four sensors polled over Modbus TCP by the driver's poll process; the
simulated sensors' server runs in a process of its own, as with ``rig sim``, so that no
simulator thread competes with the measured calls for the interpreter lock).

The virtual devices produce one period's worth of frames between cycles (not timed), so
every timed poll drains what a real 5 ms period brings (20 frames per laser, 4 TPDOs,
heartbeats). Baseline, same run: the bare transport floor — one non-blocking ``os.read``
per pty and the same CAN frames sent and received with no codec or driver logic.

    python benchmarks/driver_cost.py [--cycles N] [--can lockstep|virtual] [--fifo PRIO] [--json]

``--fifo P`` runs the measuring thread SCHED_FIFO P, as the control loop runs on the rig
(when the OS permits; reported either way). ``cpu_steal_pct``: CPU time the hypervisor
took away during the measured cycles, in % of their wall time (summed over CPUs).
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import logging
import multiprocessing
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import can  # noqa: E402
import numpy as np  # noqa: E402

from rig_runtime import config  # noqa: E402
from rig_runtime.config import WHEELS  # noqa: E402
from drivers.canopen402 import DriveBus  # noqa: E402
from drivers.ft300 import FTSensorSet, Wrench  # noqa: E402
from drivers.laser import LaserDriver  # noqa: E402
from sim_backend.lockstep_bus import LockstepBus  # noqa: E402
from sim_backend.virtual_drive import VirtualDriveSet  # noqa: E402
from sim_backend.virtual_ft import VirtualFTServer  # noqa: E402
from sim_backend.virtual_laser import LaserGroup, VirtualLaser  # noqa: E402

from _machine import StealMeter  # noqa: E402


def dist(a) -> dict:
    a = np.asarray(a) * 1e6
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def _serve_ft(names, conn) -> None:
    """Child process: the simulated F/T sensors' Modbus TCP server until told to stop."""
    srv = VirtualFTServer(names).start()
    for n in names:
        srv.set_wrench(n, Wrench(1.0, 2.0, 3.0, 0.1, 0.2, 0.3))
    conn.send(dict(srv.endpoints))
    try:
        conn.recv()
    except EOFError:
        pass
    srv.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=4000)
    ap.add_argument("--can", choices=("lockstep", "virtual"), default="lockstep",
                    help="python-can bus between the drives and the driver (default lockstep)")
    ap.add_argument("--fifo", type=int, help="SCHED_FIFO priority of the measuring thread (if permitted)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    cfg = config.load()
    h = cfg.controller.h
    lasers, drivers = [], []
    for i, lc in enumerate(cfg.devices.lasers):
        vl = VirtualLaser(lc, noise_std_m=1e-6, seed=i, output_rate_hz=4000.0)
        lasers.append(vl)
        drivers.append(LaserDriver(lc, port=vl.port_name))
    group = LaserGroup(lasers)
    chan = f"bench-{os.getpid()}"
    new_bus = (lambda: LockstepBus(channel=chan)) if args.can == "lockstep" else \
        (lambda: can.Bus(interface="virtual", channel=chan))
    sim_bus = new_bus()
    vdrives = VirtualDriveSet(cfg.devices.can, sim_bus)
    drv_can = new_bus()
    drive_bus = DriveBus(cfg.devices.can, bus=drv_can, period_s=h)
    names = [s.name for s in cfg.devices.ft.sensors]
    ctx = multiprocessing.get_context("spawn")
    parent_end, child_end = ctx.Pipe()
    ft_srv = ctx.Process(target=_serve_ft, args=(names, child_end), name="ft-server", daemon=True)
    ft_srv.start()
    ft = FTSensorSet(dataclasses.replace(cfg.devices.ft, poller="process"), endpoints=parent_end.recv())
    try:
        for d in drivers:
            d.configure()
        with vdrives.serving(0.0):
            drive_bus.configure()
        drive_bus.activate(0.0)     # the warm-up cycles below walk the drives to OPERATION ENABLED
        ft.configure()
        fifo = "not requested"
        if args.fifo:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.fifo))
                fifo = f"SCHED_FIFO {args.fifo}: applied"
            except (OSError, AttributeError) as e:
                fifo = f"SCHED_FIFO {args.fifo}: not applied ({e})"
        currents = [0.1, -0.1, 0.5, -0.5]
        t = 0.0
        cyc, base = [], []
        fds = [os.open(vl.port_name, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY) for vl in lasers[:1]]
        gc.collect(); gc.freeze(); gc.disable()
        steal = StealMeter().__enter__()
        for k in range(args.cycles + 200):
            t += h
            for w in WHEELS:
                vdrives.set_wheel_speed(w, 13.3)
            vdrives.service(t - h)          # answers last cycle's SYNC with TPDOs
            group.emit(t)                   # one period of laser frames
            group.wait()
            t0 = time.perf_counter()
            for d in drivers:
                d.poll(t)
            drive_bus.poll(t)
            ft.poll(time.monotonic())   # the poll process stamps samples on the monotonic clock
            drive_bus.write(currents, t)
            t1 = time.perf_counter()
            if k >= 200:
                cyc.append(t1 - t0)
        steal.__exit__()
        gc.enable(); gc.unfreeze()
        # baseline: the transport floor with the same traffic, no codec/driver logic
        raw_fds = [d._ser.fileno() for d in drivers]
        msgs = [can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)] + [
            can.Message(arbitration_id=0x200 + i, data=b"\x0f\x00\x10\x00", is_extended_id=False) for i in range(1, 5)]
        rx = drive_bus._bus if hasattr(drive_bus, "_bus") else None
        for k in range(args.cycles + 200):
            t += h
            vdrives.service(t - h)
            group.emit(t)
            group.wait()
            t0 = time.perf_counter()
            for fd in raw_fds:
                try:
                    os.read(fd, 4096)
                except BlockingIOError:
                    pass
            if rx is not None:
                while rx.recv(0) is not None:
                    pass
                for m in msgs:
                    rx.send(m)
            t1 = time.perf_counter()
            if k >= 200:
                base.append(t1 - t0)
        for fd in fds:
            os.close(fd)
    finally:
        ft.close()
        parent_end.send("stop")
        ft_srv.join(5.0)
        drive_bus.close(); vdrives.close(); sim_bus.shutdown(); drv_can.shutdown()
        for d in drivers:
            d.close()
        for vl in lasers:
            vl.close()
    out = {"cycle_us": dist(cyc), "baseline_us": dist(base),
           "ratio_p50": float(np.percentile(cyc, 50) / np.percentile(base, 50)),
           "ratio_p99": float(np.percentile(cyc, 99) / np.percentile(base, 99)),
           "cycles": args.cycles, "can": args.can, "fifo": fifo, "cpu_steal_pct": steal.percent, "lasers_hz": 4000, "drives": 4, "ft_sensors": len(names)}
    if args.json:
        print(json.dumps(out))
    else:
        c, b = out["cycle_us"], out["baseline_us"]
        print(f"poll()+write(), all devices: p50 {c['p50']:.1f} us, p99 {c['p99']:.1f} us, max {c['max']:.1f} us")
        print(f"transport floor (same run):  p50 {b['p50']:.1f} us, p99 {b['p99']:.1f} us -> "
              f"ratio p50 {out['ratio_p50']:.2f}, p99 {out['ratio_p99']:.2f}")
        print(f"measuring thread: {out['fifo']}; CPU time stolen by the hypervisor meanwhile: "
              f"{'n/a' if steal.percent is None else f'{steal.percent:.1f} %'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
