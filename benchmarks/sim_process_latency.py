"""SYNC -> TPDO1 round trip through ``rig sim``'s emulated SLCAN adapter, as a runtime sees it.

Starts ``rig sim`` (SCHED_FIFO ``--sim-fifo``, default 50), opens the adapter's pty with the
project's ``rig_slcan`` interface, lets ``drivers.canopen402.DriveBus`` configure and enable
the four virtual drives, then — at SCHED_FIFO ``--fifo`` (default 80), on a sleep-then-spin
clock with period ``controller.h`` (5 ms) — writes SYNC + one RPDO1 per drive (+ the
heartbeat every 100 ms) in ONE ``os.write`` per cycle and waits in ``select`` between cycles,
stamping every TPDO1 when it becomes readable. The latency of a drive's TPDO1 is
"readable at the host" minus "SYNC written", matched in order per drive.

A child process loads the simulator as ``rig run`` does (unless ``--no-load``): each F/T
sensor read over Modbus TCP at ``ft.poll_hz`` and the six laser ptys drained every cycle.

    python benchmarks/sim_process_latency.py [--duration 60] [--fifo 80] [--sim-fifo 50]
        [--sim-tree DIR] [--sim-arg ARG ...] [--floor] [--no-load] [--workdir DIR] [--json]

``--sim-tree DIR`` runs the simulator from another source tree (PYTHONPATH=DIR), to compare
an older version against this one in alternating runs; ``--sim-arg`` passes options to ``rig
sim`` (e.g. ``--sim-arg=--can-responder --sim-arg=thread``). ``--floor`` answers the SYNCs
from a minimal one-thread echo process on a pty of its own instead: the kernel's pty
delivery both ways plus the machine's scheduling, the best any simulator could do here.
Results and their reading: docs/sim-process.md, "SYNC → TPDO1".
"""

from __future__ import annotations

import argparse
import collections
import gc
import json
import logging
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rig_runtime import config  # noqa: E402


def _fifo(prio: int | None) -> str:
    if not prio:
        return "SCHED_OTHER"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
        return f"SCHED_FIFO {prio}"
    except (OSError, AttributeError) as e:
        return f"SCHED_FIFO {prio} refused ({e})"


def load_child(cfg_path: str, fifo: int | None) -> int:
    """The runtime's other traffic towards the simulator: each F/T sensor read over Modbus TCP
    at ``ft.poll_hz`` (raw requests, independent of the F/T driver's implementation) and the
    laser ptys drained every cycle. Runs until stdin closes."""
    import socket
    import struct
    _fifo(fifo)
    cfg = config.load(cfg_path)
    socks = []
    for s in cfg.devices.ft.sensors:
        so = socket.create_connection((s.host, s.port), timeout=0.2)
        so.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        socks.append(so)
    fds = [os.open(lc.port, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY) for lc in cfg.devices.lasers]
    os.set_blocking(0, False)
    h, ft_period = cfg.controller.h, 1.0 / cfg.devices.ft.poll_hz
    tid = 0
    t_next = t_ft = time.monotonic()
    try:
        while True:
            t_next += h
            time.sleep(max(0.0, t_next - time.monotonic()))
            for fd in fds:
                try:
                    os.read(fd, 65536)
                except BlockingIOError:
                    pass
            if time.monotonic() >= t_ft:
                t_ft += ft_period
                for so in socks:                      # read holding registers 180..185, unit 9
                    tid = (tid + 1) & 0xFFFF
                    so.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 9, 3, 180, 6))
                    got = b""
                    try:
                        while len(got) < 21:
                            chunk = so.recv(64)
                            if not chunk:
                                return 1
                            got += chunk
                    except socket.timeout:
                        pass
            try:
                if os.read(0, 1) == b"":
                    break
            except BlockingIOError:
                pass
    finally:
        for so in socks:
            so.close()
        for fd in fds:
            os.close(fd)
    return 0


def echo_child(fifo: int | None) -> int:
    """``--floor``: the smallest possible SLCAN responder — one thread in its own process
    answering every SYNC line with four TPDO1 lines in one write — so the round trip is only
    the kernel's pty delivery both ways plus scheduling: the floor for ``rig sim``."""
    import tty
    master, slave = os.openpty()
    tty.setraw(slave)
    print(os.ttyname(slave), flush=True)
    _fifo(fifo)
    gc.disable()
    ep = select.epoll()
    ep.register(master, select.EPOLLIN)
    ep.register(0, select.EPOLLIN)
    reply = b"".join(b"t%03X8%s\r" % (0x180 + n, b"0" * 16) for n in (1, 2, 3, 4))
    buf = bytearray()
    while True:
        for fd, _ in ep.poll():
            if fd == 0:
                return 0
            buf += os.read(master, 65536)
            out = b""
            while (i := buf.find(b"\r")) >= 0:
                if buf[:i] == b"t0800":
                    out += reply
                elif buf[:1] in (b"C", b"S", b"O"):
                    out += b"\r"
                del buf[:i + 1]
            if out:
                os.write(master, out)


def _dist(a: np.ndarray) -> dict:
    if not a.size:
        return {"n": 0}
    return {"n": int(a.size), "p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
            "p999": float(np.percentile(a, 99.9)), "max": float(a.max())}


def measure(cfg, duration: float, fifo: int | None, channel: str | None = None) -> dict:
    """Open the drives through rig_slcan, then the timed SYNC/RPDO loop; latencies in ms."""
    import can

    from drivers.canopen402 import DriveBus
    from drivers.cia402 import (COB_TPDO1, NMT_OPERATIONAL, RUNTIME_NODE_ID, heartbeat_frame,
                                    nmt_frame, rpdo1_frame, sync_frame)
    from drivers.slcan_codec import encode_frame

    cc = cfg.devices.can
    h = cfg.controller.h
    bus = can.Bus(interface="rig_slcan", channel=channel or cc.channel, bitrate=cc.bitrate)
    if channel is None:
        db = DriveBus(cc, bus=bus, period_s=h)
        db.configure()                               # SDO configuration, NMT start (no power)
        db.activate(time.monotonic())                # the cyclic RPDOs walk the drives to OPERATION ENABLED
        deadline = time.monotonic() + 2.0
        while not db.enabled and time.monotonic() < deadline:
            now = time.monotonic()
            db.poll(now)
            db.write([0.0] * len(cc.drives), now)
            time.sleep(h)
    fd = bus._fd

    def line(cob_data) -> bytes:
        cob, data = cob_data
        return encode_frame(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    nodes = {COB_TPDO1 + d.node_id: d.wheel for d in cc.drives}
    frames = line(sync_frame()) + b"".join(line(rpdo1_frame(d.node_id, 0x0F, 0)) for d in cc.drives)
    hb = line(heartbeat_frame(RUNTIME_NODE_ID, NMT_OPERATIONAL))
    pending = {w: collections.deque() for w in nodes.values()}
    lat = {w: [] for w in nodes.values()}
    missing_at_next_sync = {w: 0 for w in nodes.values()}
    buf = bytearray()
    mono = time.monotonic

    def drain(t: float) -> None:
        try:
            chunk = os.read(fd, 65536)
        except BlockingIOError:
            return
        buf.extend(chunk)
        while True:
            i = buf.find(b"\r")
            if i < 0:
                return
            ln = bytes(buf[:i])
            del buf[:i + 1]
            if ln[:1] == b"t" and len(ln) >= 4:
                w = nodes.get(int(ln[1:4], 16))
                if w is not None and pending[w]:
                    lat[w].append(t - pending[w].popleft())

    os.set_blocking(fd, False)
    drain(mono())
    buf.clear()
    rt = _fifo(fifo)
    gc.collect(); gc.freeze(); gc.disable()
    spin = 200e-6
    n = int(duration / h)
    t0 = mono() + h
    hb_next = t0
    k = skipped = 0
    sync_t = []
    try:
        while k < n:
            t_k = t0 + k * h
            while True:
                rem = t_k - spin - mono()
                if rem <= 0:
                    break
                if select.select([fd], [], [], rem)[0]:
                    drain(mono())
            while mono() < t_k:
                pass
            drain(mono())
            for w, q in pending.items():
                if q:
                    missing_at_next_sync[w] += 1
            out = frames
            if t_k >= hb_next:
                out = frames + hb
                hb_next += 0.1
            os.write(fd, out)
            t_w = mono()
            sync_t.append(t_w - t_k)
            for q in pending.values():
                q.append(t_w)
            late = mono() - t_k
            k_next = k + 1 if late < h else int((mono() - t0) / h) + 1
            skipped += k_next - k - 1
            k = k_next
        end = mono() + 0.1
        while mono() < end:
            if select.select([fd], [], [], 0.01)[0]:
                drain(mono())
    finally:
        gc.enable(); gc.unfreeze()
        if fifo:
            try:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            except OSError:
                pass
        try:
            os.write(fd, line(nmt_frame(0x80, 0)))         # pre-operational: the session ends
        except OSError:
            pass
        time.sleep(0.05)
        bus.shutdown()
    per = {}
    allv = []
    for w, v in lat.items():
        a = np.asarray(v) * 1e3
        allv.append(a)
        per[w] = {**_dist(a), "lost": len(pending[w]), "missing_at_next_sync": missing_at_next_sync[w]}
    a = np.concatenate(allv)
    gaps = {f">{x}ms": int((a > x).sum()) for x in (2, 3, 5, 10, 20)}
    return {"cycles": n, "skipped_periods": skipped, "client": rt,
            "latency_ms": _dist(a), "gaps": gaps, "per_drive": per,
            "client_release_lateness_ms": _dist(np.asarray(sync_t) * 1e3)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--fifo", type=int, default=80, help="SCHED_FIFO of this client (0: none)")
    ap.add_argument("--sim-fifo", type=int, default=50, help="rig sim --rt-priority (0: none)")
    ap.add_argument("--sim-tree", help="run rig sim from this source tree (PYTHONPATH)")
    ap.add_argument("--sim-arg", action="append", default=[], help="extra argument for rig sim (repeatable)")
    ap.add_argument("--no-load", action="store_true", help="no F/T polling / laser draining child")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--workdir", help="keep the simulator's files (config, status, stderr) here")
    ap.add_argument("--floor", action="store_true",
                    help="also answer SYNCs from a minimal one-thread responder process (the pty floor)")
    ap.add_argument("--load-child", help=argparse.SUPPRESS)
    ap.add_argument("--echo-child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.load_child:
        return load_child(args.load_child, args.fifo or None)
    if args.echo_child:
        return echo_child(args.sim_fifo or None)
    for name in ("pymodbus", "can", "canopen"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    from sim_backend.launcher import start_sim_process
    env = None
    if args.sim_tree:
        env = {**os.environ, "PYTHONPATH": str(Path(args.sim_tree).resolve())}
    sim_args = (["--rt-priority", str(args.sim_fifo)] if args.sim_fifo else []) + args.sim_arg
    load = None
    with tempfile.TemporaryDirectory() as d:
        cwd = os.getcwd()
        if args.sim_tree:
            os.chdir(args.sim_tree)             # python -m rig_runtime resolves from the cwd first
        try:
            sp = start_sim_process(seed=0, workdir=Path(args.workdir or Path(d) / "sim").resolve(),
                                   extra_args=sim_args, env=env)
        finally:
            os.chdir(cwd)
        with sp:
            cfg = config.load(sp.config_path)
            if not args.no_load:
                load = subprocess.Popen([sys.executable, __file__, "--load-child", str(sp.config_path),
                                         "--fifo", str(args.fifo)], stdin=subprocess.PIPE)
                time.sleep(0.5)
            echo = channel = None
            if args.floor:
                echo = subprocess.Popen([sys.executable, __file__, "--echo-child", "--sim-fifo", str(args.sim_fifo)],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
                channel = echo.stdout.readline().strip()
            try:
                res = measure(cfg, args.duration, args.fifo or None, channel)
            finally:
                if echo is not None:
                    echo.stdin.close()
                    echo.wait(5)
                if load is not None:
                    load.stdin.close()
                    try:
                        load.wait(5)
                    except subprocess.TimeoutExpired:
                        load.send_signal(signal.SIGKILL)
                        load.wait()
            try:
                st = sp.status()
                res["sim"] = {"session_stats": st["session_stats"], "timing": st["timing"],
                              "error": st["error"]}
            except (OSError, ValueError) as e:
                res["sim"] = {"error": str(e)}
        res["sim_tree"] = "floor (one-thread echo process)" if args.floor else args.sim_tree or str(ROOT)
        res["sim_args"] = sim_args
        res["loadavg"] = os.getloadavg()
    if args.json:
        print(json.dumps(res))
    else:
        la = res["latency_ms"]
        print(f"sim {res['sim_tree']} {' '.join(sim_args)}  load {res['loadavg'][0]:.2f}")
        print(f"SYNC->TPDO ms  n {la['n']}  p50 {la['p50']:.3f}  p99 {la['p99']:.3f}  p99.9 {la['p999']:.3f}  "
              f"max {la['max']:.3f}   gaps {res['gaps']}")
        for w, p in res["per_drive"].items():
            print(f"  {w}: p50 {p['p50']:.3f} p99 {p['p99']:.3f} max {p['max']:.3f} lost {p['lost']} "
                  f"missing at next SYNC {p['missing_at_next_sync']}")
        cl = res["client_release_lateness_ms"]
        print(f"client release lateness ms p99 {cl['p99']:.3f} max {cl['max']:.3f}; skipped periods "
              f"{res['skipped_periods']}; {res['client']}")
        print(f"sim: {res['sim']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
