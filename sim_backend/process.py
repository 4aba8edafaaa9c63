"""``rig sim``: the simulated rig served in its own process, in real time, so that an
unmodified ``rig run`` in another process drives it by configuration alone.

What is on the other end of each wire (docs/sim-process.md):

* lasers — the virtual optoNCDT 1420s of :class:`~sim_backend.rig.SimulatedRig`, each
  streaming into its pty at its output rate on the wall clock;
* CAN — an SLCAN adapter emulated on a pty (:mod:`sim_backend.slcan`) with the virtual CiA 402
  drives directly behind it (:class:`CanResponder`), by default in a child process of their
  own (:class:`ResponderProcess`): one thread reads the runtime's SYNC + RPDOs, lets the drives
  handle them and writes the TPDOs back in one write, with no other thread of the simulator
  competing for its interpreter lock; the drives' heartbeat, SYNC/RPDO watchdog and heartbeat
  consumer run on ``time.monotonic``, checked every ``drive_tick_s`` (1 ms) by the same thread;
* force–torque — the Modbus TCP servers on 127.0.0.1, on their real (free) ports.

The plant runs on one thread (:class:`RealtimeSim`): absolute deadlines ``t0 + k·h`` on
``time.monotonic`` (h = ``controller.h``), each step integrated with the currents the
virtual drives apply at its release; between plant steps the same thread wakes every
``laser_tick_s`` (1 ms) so the lasers' frames leave in small chunks, as a streaming sensor's
do. A late thread catches up (every step is integrated, none skipped) and is counted. Wheel
speeds go to the drives, applied currents come back through shared memory.

Scenario time (disturbances, fault injections) starts at the first SYNC the runtime sends
after an NMT start — ``rig run`` sends SYNC every cycle from its first one, so scenario time
leads the runtime's RUNNING time (``t_run``) by its arming time, a few cycles. The session
ends (active faults cleared, disturbances off) on NMT stop / pre-operational / reset — the
runtime's safe stop — or after 1 s without SYNC (a runtime that was killed). ``stall``
faults act on the runtime's own clock and cannot be injected from here: they are ignored.

Python API (tests, benchmarks): :func:`start_sim_process` spawns ``python -m rig_runtime sim``
and returns a :class:`SimProcess` once the simulator printed ``ready``.
"""

from __future__ import annotations

import collections
import copy
import gc
import json
import math
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import can
import numpy as np
import yaml

from drivers.canopen402 import COB_NMT, COB_SYNC, COB_TPDO1, NMT_START, NMT_STATE_NAMES
from rig_runtime import config as rig_config
from rig_runtime import schema
from rig_runtime.config import WHEELS, RigConfig
from rig_runtime.scenario import Scenario

from .slcan import SlcanAdapter

__all__ = ["RealtimeSim", "SimProcess", "start_sim_process", "serve", "generated_config", "parse_port_line"]

SESSION_SILENCE_S = 1.0        # no SYNC for this long ends a session (runtime killed)
SWITCH_INTERVAL_S = 0.0005     # interpreter switch interval in the rig sim process
FT_RATE_HZ = 100.0             # F/T registers refreshed at the FT 300's own output rate


class Histogram:
    """Counts of non-negative values (seconds) in fixed bins: O(1) to add, percentiles from the
    counts in microseconds. The status writer used to turn deques of up to 50 000 samples
    into arrays every 50 ms, holding the interpreter lock for up to 4-5 ms at a time, which
    the SLCAN responder then waited for (a TPDO late by that much).

    Percentiles are bin centres (``bin_s`` = 10 µs), clipped to the exact maximum. With
    ``window_s`` only the current and the previous window are counted ("the last
    window_s to 2·window_s"; ``add`` then needs the time ``t``)."""

    def __init__(self, bin_s: float = 1e-5, max_s: float = 0.2, window_s: float = 0.0) -> None:
        self.bin_s = bin_s
        self._inv = 1.0 / bin_s
        self._last = int(max_s / bin_s)
        self.window_s = window_s
        self.clear()

    def clear(self) -> None:
        self.counts = np.zeros(self._last + 1, dtype=np.int64)
        self.prev = None
        self.n = 0
        self.max = -math.inf
        self._prev_max = -math.inf
        self._t_window = math.nan

    def add(self, x: float, t: float = 0.0) -> None:
        if self.window_s and not t < self._t_window:
            if self._t_window == self._t_window:          # rotate: the current window becomes the previous
                self.prev, self.counts = self.counts, np.zeros_like(self.counts)
                self._prev_max, self.max = self.max, -math.inf
                self.n = 0
            self._t_window = t + self.window_s
        i = int(x * self._inv) if x > 0.0 else 0
        self.counts[i if i < self._last else self._last] += 1
        self.n += 1
        if x > self.max:
            self.max = x

    def copy(self) -> "Histogram":
        h = Histogram.__new__(Histogram)
        h.__dict__.update(self.__dict__)
        h.counts = self.counts.copy()
        return h

    def summary(self, scale: float = 1.0) -> dict[str, Any]:
        """``{"n", "p50", "p99", "p999", "max"}`` in seconds × ``scale`` (None without samples)."""
        counts, mx = self.counts, self.max
        if self.prev is not None:
            counts, mx = counts + self.prev, max(mx, self._prev_max)
        c = np.cumsum(counts)
        n = int(c[-1])
        if not n:
            return {"n": 0, "p50": None, "p99": None, "p999": None, "max": None}

        def pct(q: float) -> float:
            i = int(np.searchsorted(c, q * n, side="left"))
            return min((i + 0.5) * self.bin_s, mx) * scale

        return {"n": n, "p50": pct(0.5), "p99": pct(0.99), "p999": pct(0.999), "max": mx * scale}


class _SharedView:
    """What the plant side reads from a responder's 9 shared floats (layout: CanResponder)."""

    shared: Any

    @property
    def last_sync_t(self) -> float:
        return float(self.shared[8])

    @property
    def currents(self) -> list[float]:
        return [float(c) for c in self.shared[4:8]]


class CanResponder(_SharedView):
    """The CAN side of ``rig sim``: the emulated SLCAN adapter (direct mode) with the virtual
    drives behind it, served by ONE thread — a SYNC is answered by the thread that read it,
    in one write, with no hand-over between threads. Also its share of the session
    bookkeeping: SYNC/NMT events for scenario time, SYNC → TPDO1 latency, SYNC gaps.

    Runs either inside the ``rig sim`` process (``attach(sim.drives)``; the adapter's own
    thread) or alone in a child process (:class:`ResponderProcess`, ``python -m
    sim_backend.process --can-responder``; drives of its own, the process's only thread), where
    no plant, laser, Modbus or status thread competes with it for the interpreter lock.

    ``shared``: 9 floats shared with the plant side — [0:4] wheel speeds in (WHEELS order;
    only with ``speeds_in``, else the plant sets them on the drives itself), [4:8] applied
    currents out (after every service), [8] time of the latest SYNC. ``on_event(kind, t)``:
    "sync" (the first SYNC after an NMT start: a session starts) or "end" (NMT stop /
    pre-operational / reset); default: queued for :meth:`poll_events`.
    """

    mode = "thread"

    def __init__(self, *, tick_s: float = 0.001, on_event: Optional[Callable[[str, float], None]] = None,
                 shared: Any = None, speeds_in: bool = False,
                 on_thread_start: Optional[Callable[[], None]] = None) -> None:
        self.adapter = SlcanAdapter(None, on_frame=self._on_host_frame, on_host_frames=self._on_frames_to_host,
                                    service=self._service, service_period_s=tick_s, on_thread_start=on_thread_start)
        self._events: "queue.SimpleQueue[tuple[str, float]]" = queue.SimpleQueue()
        self.on_event = on_event or (lambda kind, t: self._events.put((kind, t)))
        self.shared = shared if shared is not None else [0.0] * 8 + [math.nan]
        self.speeds_in = speeds_in
        self.drives: Any = None
        self._drive_list: list = []
        self._want_sync = False
        self._stats_lock = threading.Lock()
        self._sync_queue: dict[int, collections.deque] = {}
        self._tpdo_latency = Histogram()
        self.sync_gap_max = 0.0
        self.t_last_host_frame = -math.inf

    def attach(self, drives) -> "CanResponder":
        """Serve ``drives`` (a VirtualDriveSet on ``adapter.device_bus``, not running its own thread)."""
        self.drives = drives
        self._drive_list = [drives.drives.get(w) for w in WHEELS]
        self._sync_queue = {COB_TPDO1 + d.node_id: collections.deque(maxlen=16) for d in drives.drives.values()}
        return self

    # the interface RealtimeSim uses (ResponderProcess has the same)
    @property
    def port_name(self) -> str:
        return self.adapter.port_name

    @property
    def pid(self) -> int:
        return os.getpid()

    def start(self) -> "CanResponder":
        self.adapter.start()
        return self

    def close(self) -> None:
        self.adapter.close()

    def push_model(self, model) -> None:
        """Plant side → drives: nothing to do here, the plant sets them directly."""

    def poll_events(self) -> list[tuple[str, float]]:
        out = []
        while True:
            try:
                out.append(self._events.get_nowait())
            except queue.Empty:
                return out

    def error(self) -> str:
        return ""

    # the adapter's thread
    def _service(self, t: float) -> None:
        """The drives handle the host's frames and run their timers; currents out."""
        sh, drl = self.shared, self._drive_list
        if self.speeds_in:
            for i, d in enumerate(drl):
                if d is not None:
                    d.omega = float(sh[i])
        self.drives.service(t)
        for i, d in enumerate(drl):
            sh[4 + i] = d.current_A() if d is not None else 0.0

    def _on_host_frame(self, msg: can.Message, t: float) -> None:
        """Each frame the runtime sends (before the drives get it): sessions, SYNC statistics."""
        self.t_last_host_frame = t
        if msg.is_extended_id or msg.is_remote_frame:
            return
        cid = msg.arbitration_id
        if cid == COB_SYNC:
            with self._stats_lock:
                last = float(self.shared[8])
                if self._want_sync:                 # a new session: its statistics start here
                    self._want_sync = False
                    self.on_event("sync", t)
                    for q in self._sync_queue.values():
                        q.clear()
                    self._tpdo_latency.clear()
                    self.sync_gap_max = 0.0
                elif last == last:
                    gap = t - last
                    if self.sync_gap_max < gap < SESSION_SILENCE_S:
                        self.sync_gap_max = gap
                for q in self._sync_queue.values():
                    q.append(t)
            self.shared[8] = t
        elif cid == COB_NMT and len(msg.data) == 2:
            if msg.data[0] == NMT_START:
                self._want_sync = True
            else:                               # stop, pre-operational, reset: a safe stop
                self._want_sync = False
                self.on_event("end", t)

    def _on_frames_to_host(self, msgs: list, t: float) -> None:
        """The frames just written to the pty: the latency from each SYNC to the TPDO1 it
        triggered, as the runtime can first read it."""
        with self._stats_lock:
            for m in msgs:
                q = self._sync_queue.get(m.arbitration_id)
                if q is None or m.is_extended_id:
                    continue
                while q and t - q[0] > 0.1:         # a TPDO that never came (fault injection)
                    q.popleft()
                if q:
                    self._tpdo_latency.add(t - q.popleft())

    def snapshot(self) -> dict[str, Any]:
        """JSON-ready: drive states, adapter state, SYNC → TPDO1 latency and SYNC gap (ms)."""
        drives = {}
        with self.drives._lock:
            for w, d in zip(WHEELS, self._drive_list):
                if d is None:
                    continue
                drives[w] = {"current_A": d.current_A(), "state": d.state,
                             "nmt": NMT_STATE_NAMES.get(d.nmt, hex(d.nmt)), "error_code": d.error_code,
                             "watchdog_trips": d.counters["watchdog_trips"],
                             "heartbeat_events": d.counters["heartbeat_events"],
                             "counters": dict(d.counters),
                             "last_sync_t": d.wd_sync if d.wd_armed or d.counters["sync"] else None,
                             "last_rpdo_t": d.wd_rpdo if d.wd_armed or d.counters["rpdo"] else None}
        with self._stats_lock:
            hist = self._tpdo_latency.copy()
            gap = self.sync_gap_max
        ad = self.adapter
        return {"drives": drives, "slcan": {"open": ad.is_open, "bitrate": ad.bitrate, **ad.counters},
                "tpdo_latency_ms": hist.summary(1e3), "sync_gap_max_ms": gap * 1e3}


class _NullBus(can.BusABC):
    """A bus that drops what is sent and never receives: the plant side's copy of the drives
    when the real ones run in the responder process (it only carries speeds and faults)."""

    def __init__(self) -> None:
        self.channel_info = "null"
        super().__init__(channel="null")

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        pass

    def _recv_internal(self, timeout: Optional[float]):
        return None, False


SHARED_FLOATS = 9


class ResponderProcess(_SharedView):
    """A :class:`CanResponder` in a child process (``python -m sim_backend.process
    --can-responder``), as the plant side sees it: the same interface as CanResponder.

    Wheel speeds in, applied currents and the latest SYNC time out go through 9 shared
    float64s (a memfd; each value is written whole, no lock needed); session events come on
    one socket pair, status requests / replies and fault changes on another (SOCK_SEQPACKET:
    one message each). The child gets SIGTERM when the thread that started it ends
    (``PR_SET_PDEATHSIG``) and exits when its command socket closes."""

    mode = "process"

    def __init__(self, *, tick_s: float = 0.001, rt_priority: Optional[int] = None,
                 python: Optional[str] = None) -> None:
        import mmap
        import socket
        fd = os.memfd_create("rig-sim-can", 0)
        try:
            os.ftruncate(fd, 8 * SHARED_FLOATS)
            self._mm = mmap.mmap(fd, 8 * SHARED_FLOATS)
            self.shared = np.ndarray((SHARED_FLOATS,), dtype=np.float64, buffer=self._mm)
            self.shared[:] = 0.0
            self.shared[8] = math.nan
            self._ev, ev_child = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            self._cmd, cmd_child = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            fds = (fd, ev_child.fileno(), cmd_child.fileno())
            cmd = [python or sys.executable, "-m", "sim_backend.process", "--can-responder",
                   *(str(f) for f in fds), repr(float(tick_s)), str(rt_priority or 0)]
            self.proc = subprocess.Popen(cmd, pass_fds=fds, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                         preexec_fn=_die_with_parent)
        finally:
            os.close(fd)
        ev_child.close()
        cmd_child.close()
        self._ev.setblocking(False)
        self._lock = threading.Lock()
        self._req = 0
        self._last_snapshot: dict[str, Any] = {}
        self._faults_sent: Optional[dict] = None
        self._error = ""
        self.port_name = ""
        self.pid = self.proc.pid

    def configure(self, can_cfg, seed: int, timeout_s: float = 30.0) -> None:
        """Send the drives' configuration; returns once the child serves the pty."""
        import pickle
        import socket
        self._cmd.sendall(pickle.dumps({"can": can_cfg, "seed": seed}))
        self._cmd.settimeout(timeout_s)
        try:
            reply = json.loads(self._cmd.recv(1 << 16) or b'{"op": "error", "message": "exited"}')
        except (socket.timeout, ValueError) as e:
            self.close()
            raise RuntimeError(f"CAN responder process did not start: {e}") from None
        if reply.get("op") != "ready":
            self.close()
            raise RuntimeError(f"CAN responder process failed: {reply.get('message')}")
        self.port_name = reply["port"]
        self._cmd.settimeout(None)
        self.snapshot(timeout_s=timeout_s)          # the status has drives from the start

    def start(self) -> "ResponderProcess":
        return self

    def push_model(self, model) -> None:
        """Wheel speeds (shared memory) and injected faults (a message, when they changed)
        from the plant side's copy of the drives to the real ones."""
        sh = self.shared
        for i, w in enumerate(WHEELS):
            d = model.drives.get(w)
            if d is not None:
                sh[i] = d.omega
        faults = {w: d.faults for w, d in model.drives.items()}
        if faults != self._faults_sent:
            self._faults_sent = {w: dict(f) for w, f in faults.items()}
            self._send({"op": "faults", "faults": self._faults_sent})

    def _send(self, msg: dict) -> None:
        import socket
        try:                            # never block the plant thread on a child that does not read
            self._cmd.send(json.dumps(msg).encode(), socket.MSG_DONTWAIT)
        except OSError as e:
            self._error = self._error or f"CAN responder process: {e}"

    def poll_events(self) -> list[tuple[str, float]]:
        out = []
        while True:
            try:
                data = self._ev.recv(4096)
            except BlockingIOError:
                return out
            except OSError as e:
                self._error = self._error or f"CAN responder process: {e}"
                return out
            if not data:
                if not self._error:
                    self.proc.poll()
                    self._error = f"CAN responder process exited ({self.proc.returncode})"
                return out
            kind, t = json.loads(data)
            out.append((kind, t))

    def error(self) -> str:
        if not self._error and self.proc.poll() is not None:
            self._error = f"CAN responder process exited ({self.proc.returncode})"
        return self._error

    def snapshot(self, timeout_s: float = 0.5) -> dict[str, Any]:
        """The child's snapshot (it answers after its next SYNC, or at once without traffic);
        the previous one if it does not answer within ``timeout_s``."""
        import select
        with self._lock:
            self._req += 1
            self._send({"op": "status", "id": self._req})
            deadline = time.monotonic() + timeout_s
            while True:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([self._cmd], [], [], left)[0]:
                    return self._last_snapshot
                try:
                    data = self._cmd.recv(1 << 20)
                except OSError:
                    return self._last_snapshot
                if not data:
                    return self._last_snapshot
                reply = json.loads(data)
                if reply.get("id") == self._req:
                    self._last_snapshot = reply["snapshot"]
                    return self._last_snapshot

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the child (its pty goes with it). Idempotent."""
        if self.proc.poll() is None:
            self._send({"op": "stop"})
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        for s in (self._ev, self._cmd):
            s.close()


def _responder_main(argv: Sequence[str]) -> int:
    """Child process of :class:`ResponderProcess`: ``<memfd> <event socket> <command socket>
    <tick_s> <SCHED_FIFO priority or 0>``. Serves the pty in this process's only thread."""
    import mmap
    import pickle
    import socket

    from .virtual_drive import VirtualDriveSet
    shm_fd, ev_fd, cmd_fd = (int(a) for a in argv[:3])
    tick_s, prio = float(argv[3]), int(argv[4])
    signal.signal(signal.SIGINT, signal.SIG_IGN)        # Ctrl-C reaches the group: the parent stops us
    for name in ("can", "canopen"):
        import logging
        logging.getLogger(name).setLevel(logging.CRITICAL)
    if prio:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
        except OSError as e:
            print(f"rig sim: CAN responder SCHED_FIFO {prio}: not applied ({e})", file=sys.stderr, flush=True)
    mm = mmap.mmap(shm_fd, 8 * SHARED_FLOATS)
    shared = np.ndarray((SHARED_FLOATS,), dtype=np.float64, buffer=mm)
    ev = socket.socket(fileno=ev_fd)
    cmd = socket.socket(fileno=cmd_fd)
    init = pickle.loads(cmd.recv(1 << 20) or pickle.dumps(None))
    if init is None:
        return 0
    try:
        def on_event(kind: str, t: float) -> None:
            try:                        # never wait for the parent here
                ev.send(json.dumps([kind, t]).encode(), socket.MSG_DONTWAIT)
            except BlockingIOError:
                pass

        resp = CanResponder(tick_s=tick_s, shared=shared, speeds_in=True, on_event=on_event)
        resp.attach(VirtualDriveSet(init["can"], resp.adapter.device_bus, seed=init["seed"]))
    except Exception as e:  # noqa: BLE001 - reported to the parent, which raises it
        cmd.sendall(json.dumps({"op": "error", "message": f"{type(e).__name__}: {e}"}).encode())
        return 1
    pending: list[int] = []

    def on_command(t: float) -> None:
        while True:
            try:
                data = cmd.recv(1 << 20, socket.MSG_DONTWAIT)
            except BlockingIOError:
                return
            except OSError:
                data = b""
            if not data:
                resp.adapter.stop()
                return
            msg = json.loads(data)
            op = msg.get("op")
            if op == "faults":
                for w, f in msg["faults"].items():
                    d = resp.drives.drives.get(w)
                    if d is not None:
                        d.faults = dict(f)
            elif op == "status":
                pending.append(msg["id"])
            elif op == "stop":
                resp.adapter.stop()
                return

    def after_write(t: float, host_frames: bool) -> None:
        # answer status requests right after a SYNC was answered (the next one is ~h away),
        # or at once when the runtime sends nothing
        if pending and (host_frames or t - resp.t_last_host_frame > 0.02):
            snap = json.dumps({"id": pending[-1], "snapshot": resp.snapshot()}, default=_json_default)
            pending.clear()
            try:
                cmd.send(snap.encode(), socket.MSG_DONTWAIT)
            except BlockingIOError:
                pass
            except OSError:
                resp.adapter.stop()

    resp.adapter.after_write = after_write
    resp.adapter.watch(cmd.fileno(), on_command)
    cmd.sendall(json.dumps({"op": "ready", "port": resp.port_name}).encode())
    gc.collect()
    gc.freeze()
    try:
        resp.adapter.run()
    finally:
        resp.adapter.close()
    return 0


class RealtimeSim:
    """A :class:`SimulatedRig` served in real time (see the module docstring).

    ``start()`` starts the CAN responder, the plant thread and (with ``status_file``) the
    status writer; ``close()`` stops everything. ``status()`` is a JSON-ready snapshot:
    applied currents, drive states, session, plant, timing. ``can_responder``: "process"
    (the SLCAN adapter and the drives in a child process of their own) or "thread" (in this
    process, on the adapter's thread); ``responder_rt_priority``: its SCHED_FIFO priority.
    """

    def __init__(self, cfg: RigConfig, scenario: Optional[Scenario] = None, seed: Optional[int] = None, *,
                 laser_tick_s: float = 0.001, status_file: str | Path | None = None,
                 status_period_s: float = 0.05, ft_rate_hz: float = FT_RATE_HZ, drive_tick_s: float = 0.001,
                 can_responder: str = "process", responder_rt_priority: Optional[int] = None,
                 log: Callable[[str], None] | None = None) -> None:
        from .rig import SimulatedRig         # plant, lasers, F/T servers: not in the responder process
        if can_responder not in ("thread", "process"):
            raise ValueError(f"can_responder is 'thread' or 'process', not {can_responder!r}")
        self.cfg = cfg
        self.h = cfg.controller.h
        self.laser_tick_s = min(laser_tick_s, self.h)
        self.drive_tick_s = drive_tick_s      # the drives' timers (watchdog, heartbeat) granularity
        self.status_file = Path(status_file) if status_file else None
        self.status_period_s = status_period_s
        self.ft_period = 1.0 / ft_rate_hz
        self._log = log or (lambda s: print(f"rig sim: {s}", file=sys.stderr, flush=True))
        self._null_bus: Optional[_NullBus] = None
        if can_responder == "process":
            self.can: Any = ResponderProcess(tick_s=drive_tick_s, rt_priority=responder_rt_priority)
            self._null_bus = drive_bus = _NullBus()
        else:
            def prio() -> None:
                if responder_rt_priority:
                    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(responder_rt_priority))
            self.can = CanResponder(tick_s=drive_tick_s, on_thread_start=prio)
            drive_bus = self.can.adapter.device_bus
        try:
            self.sim = SimulatedRig(cfg, scenario, seed=seed, drive_bus=drive_bus)
            if can_responder == "process":
                self.can.configure(cfg.devices.can, self.sim.seed)
            else:
                self.can.attach(self.sim.drives)
        except BaseException:
            self.can.close()
            if getattr(self, "sim", None) is not None:
                self.sim.close()
            raise
        # with the responder process these are the plant side's copies: they carry the wheel
        # speeds and the scenario's faults (push_model); the real ones answer the runtime
        self.drives = self.sim.drives
        # the plant's first step imports and precomputes (scipy, ~0.3 s): do it here, on a copy,
        # not on the plant thread's first deadline
        copy.deepcopy(self.sim.plant).step(self.h, 0.0, 0.0)
        self.scenario = scenario
        if scenario is not None and any(f.kind == "stall" for f in scenario.faults):
            self._log("scenario 'stall' faults act on the runtime's clock; ignored by rig sim")
        self.session_active = False
        self.session_t0 = math.nan            # monotonic time scenario time 0
        self.sessions = 0
        self.sess_tick_late_max = 0.0
        self.sess_plant_late_max = 0.0
        # plant thread state
        self.t_wall0 = math.nan
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._next_ft = 0.0
        self._applied = {w: 0.0 for w in WHEELS}
        self.t_current_zero: dict[str, Optional[float]] = {w: None for w in WHEELS}
        self.t_current_nonzero: dict[str, Optional[float]] = {w: None for w in WHEELS}
        self.steps = 0
        self.late_steps = 0                 # released more than one period after their deadline
        self.max_lateness = 0.0
        self.max_work = 0.0
        self._lateness = Histogram(window_s=30.0)      # the last 30-60 s
        self._work = Histogram(window_s=30.0)
        self.thread_error = ""
        self._closed = False

    # ------------------------------------------------------------------ ports
    @property
    def laser_ports(self) -> dict[str, str]:
        return self.sim.laser_ports

    @property
    def can_port(self) -> str:
        return self.can.port_name

    @property
    def last_sync_t(self) -> float:
        return self.can.last_sync_t

    @property
    def ft_endpoints(self) -> dict[str, tuple[str, int]]:
        return self.sim.ft_endpoints

    def port_lines(self) -> list[str]:
        """One machine-readable line per port: ``laser <role> <path>``, ``can slcan <path>``,
        ``ft <name> <host>:<port>``."""
        lines = [f"laser {r} {p}" for r, p in self.laser_ports.items()]
        lines.append(f"can slcan {self.can_port}")
        lines += [f"ft {n} {h}:{p}" for n, (h, p) in self.ft_endpoints.items()]
        return lines

    def devices_section(self) -> dict[str, Any]:
        """The ``devices:`` section a ``rig run`` needs to reach this simulator."""
        d = schema.to_dict(self.cfg.devices)
        for lc in d["lasers"]:
            vl = self.sim.lasers[lc["role"]]
            lc["port"] = vl.port_name
            lc["output_rate_hz"] = float(vl.rate_hz)
        can_d = d["can"]
        can_d["interface"] = "slcan"
        can_d["channel"] = self.can_port
        can_d["eds"] = str(rig_config.resolve_config_path(can_d["eds"]).resolve())
        d["ft"]["poller"] = "process"       # the runtime polls as on the rig (sim.yaml's dry run: inline)
        for s in d["ft"]["sensors"]:
            host, port = self.ft_endpoints[s["name"]]
            s.update(transport="tcp", host=host, port=int(port))
        return d

    # ------------------------------------------------------------------ lifetime
    def start(self) -> "RealtimeSim":
        if self._threads:
            return self
        self.can.start()
        self.t_wall0 = time.monotonic() - self.sim.t
        th = threading.Thread(target=self._plant_loop, name="rig-sim plant", daemon=True)
        th.start()
        self._threads.append(th)
        if self.status_file is not None:
            th = threading.Thread(target=self._status_loop, name="rig-sim status", daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def close(self) -> None:
        """Stop the threads, the CAN responder, the lasers and the F/T servers. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        for th in self._threads:
            th.join(5.0)
        if self.status_file is not None:
            try:
                self.write_status()
            except OSError:
                pass
        self.can.close()          # the adapter's pty and the drives that answer on it
        self.sim.close()          # the plant side's drives, F/T servers, lasers
        if self._null_bus is not None:
            self._null_bus.shutdown()

    def __enter__(self) -> "RealtimeSim":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ sessions
    def _session_events(self, now: float) -> bool:
        events = self.can.poll_events()
        for kind, t in events:
            if kind == "sync" and not self.session_active:
                self._end_faults()
                self.sess_tick_late_max = self.sess_plant_late_max = 0.0
                self.session_active = True
                self.session_t0 = t
                self.sessions += 1
                self.sim.on_running(t - self.t_wall0)
            elif kind == "end" and self.session_active:
                self._end_session()
        if self.session_active and now - self.can.last_sync_t > SESSION_SILENCE_S:
            self._end_session()
            return True
        return bool(events)

    def _end_session(self) -> None:
        self._end_faults()
        self.session_active = False
        self.sim.t_run0 = math.nan

    def _end_faults(self) -> None:
        sim = self.sim
        for i in list(getattr(sim, "_active_faults", ())):
            try:
                sim._inject(sim._events[i][3], False)
            except Exception as e:  # noqa: BLE001
                self._log(f"clearing scenario fault failed: {e}")
        if hasattr(sim, "_active_faults"):
            sim._active_faults.clear()

    # ------------------------------------------------------------------ plant thread
    def _plant_loop(self) -> None:
        try:
            self._plant_loop_inner()
        except BaseException as e:  # noqa: BLE001 - reported in the status and on stderr
            self.thread_error = f"{type(e).__name__}: {e}"
            self._log(f"plant thread stopped: {self.thread_error}")

    def _plant_loop_inner(self) -> None:
        sim, h, tick = self.sim, self.h, self.laser_tick_s
        mono, sleep = time.monotonic, time.sleep
        lasers = list(sim.lasers.values())
        t0 = self.t_wall0
        k = 0
        while not self._stop.is_set():
            k += 1
            t_rel = t0 + k * tick
            dt = t_rel - mono()
            if dt > 0:
                sleep(dt)
            now = mono()
            ts = now - t0                                   # simulated time = wall time since start
            late = ts - k * tick
            if late > self.sess_tick_late_max:
                self.sess_tick_late_max = late
            if ts - k * tick > tick:                        # overslept: next tick from now
                k = int(ts / tick)
            changed = self._session_events(now)
            stepped = False
            while sim.t + h <= ts + 1e-9:
                deadline = sim.t + h
                self._step_plant(ts - deadline, now)
                stepped = True
            if stepped:
                self._publish(sim.t)
                work = mono() - now
                self._work.add(work, now)
                if work > self.max_work:
                    self.max_work = work
            if stepped or changed:
                self.can.push_model(self.drives)            # speeds, faults -> the responder process
            for vl in lasers:
                vl.emit_until(ts, wait=False)

    def _step_plant(self, lateness: float, now: float) -> None:
        sim = self.sim
        running = not math.isnan(sim.t_run0)
        tau = sim.t - sim.t_run0 if running else -1.0
        if running:
            try:
                sim._update_faults(tau)
            except Exception as e:  # noqa: BLE001 - a bad scenario must not stop the plant
                self._log(f"scenario fault injection failed: {e}")
        Ff, Fr, Mf, Mr = sim._forces(tau) if running else (0.0, 0.0, 0.0, 0.0)
        cur = self.can.currents                 # what the drives apply now (after their last service)
        for w, c in zip(WHEELS, cur):
            prev = self._applied[w]
            if prev != 0.0 and c == 0.0:
                self.t_current_zero[w] = now
            elif prev == 0.0 and c != 0.0:
                self.t_current_nonzero[w] = now
            self._applied[w] = c
        sim.plant.step(self.h, cur[0] - cur[1], cur[2] - cur[3], Ff, Fr, Mf, Mr)
        sim.t += self.h
        self.steps += 1
        self._lateness.add(lateness, now)
        if lateness > self.max_lateness:
            self.max_lateness = lateness
        if lateness > self.sess_plant_late_max:
            self.sess_plant_late_max = lateness
        if lateness > self.h:
            self.late_steps += 1

    def _publish(self, t: float) -> None:
        """Physical values -> virtual devices (the lasers emit on the ticks, not here)."""
        sim = self.sim
        sim.set_laser_distances()
        sim.set_wheel_speeds()
        if sim.ft is not None and t >= self._next_ft - 1e-12:
            self._next_ft = t + self.ft_period
            sim.set_wrenches()

    # ------------------------------------------------------------------ status
    def timing(self) -> dict[str, Any]:
        """Plant-thread timing: release lateness of the plant steps and work per release, µs."""
        def dist(hist: Histogram) -> dict[str, float]:
            d = hist.summary(1e6)
            return {k: d[k] or 0.0 for k in ("p50", "p99", "max")}
        return {"h_s": self.h, "laser_tick_s": self.laser_tick_s, "steps": self.steps,
                "late_steps": self.late_steps, "max_lateness_us": self.max_lateness * 1e6,
                "max_work_us": self.max_work * 1e6,
                "recent_lateness_us": dist(self._lateness), "recent_work_us": dist(self._work)}

    def session_stats(self, snap: Optional[dict] = None) -> dict[str, Any]:
        """How promptly the simulator served the current (or last) session, ms: SYNC -> its
        TPDO1 written to the pty, the largest gap between the runtime's SYNCs (the runtime's
        own timing), the plant thread's largest tick / plant-step lateness."""
        snap = snap if snap is not None else self.can.snapshot()
        lat = snap.get("tpdo_latency_ms") or {"n": 0, "p50": None, "p99": None, "p999": None, "max": None}
        return {"tpdo_latency_ms": lat, "sync_gap_max_ms": snap.get("sync_gap_max_ms", 0.0),
                "tick_lateness_max_ms": self.sess_tick_late_max * 1e3,
                "plant_lateness_max_ms": self.sess_plant_late_max * 1e3}

    def status(self) -> dict[str, Any]:
        """A JSON-ready snapshot. Times ``t*`` are ``time.monotonic()`` of this machine
        (system-wide on Linux, so comparable with another process's)."""
        snap = self.can.snapshot()
        drives = {}
        for w, d in (snap.get("drives") or {}).items():
            drives[w] = {**d, "t_current_zero": self.t_current_zero.get(w),
                         "t_current_nonzero": self.t_current_nonzero.get(w)}
        p = self.sim.plant
        last_sync = self.can.last_sync_t
        return {
            "t": time.monotonic(),
            "t_sim": self.sim.t,
            "pid": os.getpid(),
            "currents": {w: v["current_A"] for w, v in drives.items()},
            "drives": drives,
            "session": {"active": self.session_active, "count": self.sessions,
                        "t0": None if math.isnan(self.session_t0) else self.session_t0,
                        "last_sync_t": None if math.isnan(last_sync) else last_sync},
            "plant": {"y_f": p.y_f, "y_r": p.y_r, "psi_af": p.psi_af, "psi_ar": p.psi_ar},
            "timing": self.timing(),
            "session_stats": self.session_stats(snap),
            "slcan": snap.get("slcan", {}),
            "can_responder": {"mode": self.can.mode, "pid": self.can.pid},
            "error": self.thread_error or self.can.error(),
        }

    def write_status(self) -> None:
        """Rewrite the status file atomically (write a temporary file, then rename)."""
        assert self.status_file is not None
        tmp = self.status_file.with_name(self.status_file.name + ".tmp")
        tmp.write_text(json.dumps(self.status(), default=_json_default))
        os.replace(tmp, self.status_file)

    def _status_loop(self) -> None:
        said = ""
        while not self._stop.wait(self.status_period_s):
            try:
                self.write_status()
            except Exception as e:  # noqa: BLE001 - keep serving; say so once per cause
                msg = f"status file: {type(e).__name__}: {e}"
                if msg != said:
                    said = msg
                    self._log(msg)


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


# --------------------------------------------------------------------------- the config for rig run
GENERATED_HEADER = """\
# Generated by `rig sim` (pid {pid}) from {source}.
# `rig run --config <this file>` drives the simulated rig served by that process; the ports
# below exist only while it runs. Template and documentation: configs/sim-process.yaml.
"""


def generated_config(source: str | Path, devices: dict[str, Any], header: str = "",
                     overrides: Optional[dict[str, dict[str, Any]]] = None) -> str:
    """YAML text of a complete rig config: ``source``'s includes (absolute paths) and its
    own sections, with ``devices`` replaced and ``overrides`` merged into their sections."""
    src = Path(source).resolve()
    raw = rig_config._read_yaml(src)
    inc = raw.pop("include", [])
    if isinstance(inc, str):
        inc = [inc]
    out: dict[str, Any] = {}
    if inc:
        out["include"] = [str((src.parent / i).resolve()) for i in inc]
    for k, v in raw.items():
        if k != "devices":
            out[k] = v
    for k, v in (overrides or {}).items():
        out[k] = {**(out.get(k) or {}), **v}
    out["devices"] = devices
    return header + yaml.safe_dump(out, sort_keys=False, default_flow_style=None, width=120)


# --------------------------------------------------------------------------- rig sim
def serve(config_path: str | Path | None = None, scenario: str | Path | None = None, seed: Optional[int] = None,
          write_config: str | Path | None = None, status_file: str | Path | None = None,
          status_period_s: float = 0.05, duration_s: Optional[float] = None,
          rt_priority: Optional[int] = None, cpu_affinity: Optional[Sequence[int]] = None,
          runtime_rt_priority: Optional[int] = None, runtime_cpu_affinity: Optional[Sequence[int]] = None,
          can_interface: str = "slcan", can_responder: str = "process", out=None) -> int:
    """Body of ``rig sim``: build, print the port lines (and write the config), ``ready``,
    serve until SIGINT/SIGTERM (or ``duration_s``), shut down cleanly; returns 0.

    ``rt_priority`` / ``cpu_affinity``: SCHED_FIFO priority of the CAN responder (the plant
    side's threads get one less) and CPUs for the simulator (set before any thread or process is
    started, so all inherit them), when the OS permits — reported on stderr either way.
    ``can_responder``: "process" (the SLCAN adapter and the drives in a child process of their
    own) or "thread" (in this process; see :class:`RealtimeSim`). ``runtime_rt_priority`` / ``runtime_cpu_affinity``: written as
    ``realtime.sched_fifo_priority`` / ``realtime.cpu_affinity`` into the generated config,
    for the ``rig run`` that uses it (docs/sim-process.md has measurements). ``can_interface``:
    the python-can interface the generated config names for the adapter's pty — ``slcan``
    (python-can's own client) or ``rig_slcan`` (drivers/slcan_bus.py, which reads whole
    buffers instead of single bytes)."""
    from rig_runtime.scenario import load_scenario
    out = out or sys.stdout
    # a thread waking for its deadline waits for the interpreter lock up to the switch
    # interval (5 ms by default): measured p99 release lateness 2.7 ms -> 0.35 ms at 0.5 ms
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    for name in ("can", "canopen", "pymodbus"):
        import logging
        logging.getLogger(name).setLevel(logging.CRITICAL)
    src = Path(config_path) if config_path else rig_config.DEFAULT_CONFIG
    cfg = rig_config.load(src)
    sc = load_scenario(scenario) if scenario else None
    if cpu_affinity:
        try:
            os.sched_setaffinity(0, set(cpu_affinity))
            print(f"rig sim: cpu affinity {sorted(cpu_affinity)}: applied", file=sys.stderr, flush=True)
        except (OSError, AttributeError, ValueError) as e:
            print(f"rig sim: cpu affinity {sorted(cpu_affinity)}: not applied ({e})", file=sys.stderr, flush=True)
    plant_prio = None
    if rt_priority is not None:
        # the CAN responder (the latency-critical part) at rt_priority, every thread of the
        # plant side (plant, F/T server, status) one below, all SCHED_FIFO: a plant-side thread
        # holding the interpreter lock is then never preempted by ordinary load
        plant_prio = max(1, rt_priority - 1)
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(plant_prio))
            print(f"rig sim: SCHED_FIFO priority {rt_priority} (CAN responder), {plant_prio} (plant side): "
                  f"applied", file=sys.stderr, flush=True)
        except (OSError, AttributeError) as e:
            print(f"rig sim: SCHED_FIFO priority {rt_priority}: not applied ({e})", file=sys.stderr, flush=True)
            rt_priority = None
    stop = threading.Event()
    old = {}
    for s in (signal.SIGINT, signal.SIGTERM):
        old[s] = signal.signal(s, lambda *_: stop.set())
    rt = None
    try:
        rt = RealtimeSim(cfg, sc, seed=seed, status_file=status_file, status_period_s=status_period_s,
                         can_responder=can_responder, responder_rt_priority=rt_priority)
        lines = rt.port_lines()         # the ports exist from construction on
        if write_config:
            wc = Path(write_config)
            wc.parent.mkdir(parents=True, exist_ok=True)
            rt_over: dict[str, Any] = {}
            if runtime_rt_priority is not None:
                rt_over["sched_fifo_priority"] = int(runtime_rt_priority)
            if runtime_cpu_affinity:
                rt_over["cpu_affinity"] = [int(c) for c in runtime_cpu_affinity]
            extra = {"realtime": rt_over} if rt_over else {}
            devices = rt.devices_section()
            devices["can"]["interface"] = can_interface
            text = generated_config(src, devices,
                                    GENERATED_HEADER.format(pid=os.getpid(), source=src.resolve()), extra)
            tmp = wc.with_name(wc.name + ".tmp")
            tmp.write_text(text)
            os.replace(tmp, wc)
        gc.collect()                    # collections while serving then skip the start-up objects
        gc.freeze()
        rt.start()
        if status_file:
            rt.write_status()
            lines.append(f"status {Path(status_file).resolve()}")
        if write_config:
            lines.append(f"config {Path(write_config).resolve()}")
        lines.append("ready")
        try:
            out.write("\n".join(lines) + "\n")
            out.flush()
        except (BrokenPipeError, OSError):
            pass
        t_end = time.monotonic() + duration_s if duration_s is not None else math.inf
        while not stop.wait(min(0.2, max(0.0, t_end - time.monotonic()))):
            if time.monotonic() >= t_end:
                break
        tm = rt.timing()
        print(f"rig sim: stopping; plant steps {tm['steps']}, late {tm['late_steps']}, release lateness "
              f"p50/p99/max {tm['recent_lateness_us']['p50']:.0f}/{tm['recent_lateness_us']['p99']:.0f}/"
              f"{tm['max_lateness_us']:.0f} us, sessions {rt.sessions}", file=sys.stderr, flush=True)
    finally:
        if rt is not None:
            rt.close()
        for s, hnd in old.items():
            signal.signal(s, hnd)
    return 0


def parse_port_line(line: str, ports: dict[str, Any]) -> None:
    """Fold one line of ``rig sim``'s output into ``ports``
    (``{"laser": {role: path}, "can": {"interface", "channel"}, "ft": {name: (host, port)}, …}``)."""
    parts = line.split()
    if len(parts) == 3 and parts[0] == "laser":
        ports.setdefault("laser", {})[parts[1]] = parts[2]
    elif len(parts) == 3 and parts[0] == "can":
        ports["can"] = {"interface": parts[1], "channel": parts[2]}
    elif len(parts) == 3 and parts[0] == "ft":
        host, _, port = parts[2].rpartition(":")
        ports.setdefault("ft", {})[parts[1]] = (host, int(port))
    elif len(parts) == 2 and parts[0] in ("config", "status"):
        ports[parts[0]] = parts[1]


# --------------------------------------------------------------------------- Python API
@dataclass
class SimProcess:
    """A running ``rig sim`` subprocess (from :func:`start_sim_process`)."""

    proc: subprocess.Popen
    workdir: Path
    config_path: Path
    status_path: Path
    stderr_path: Path
    ports: dict[str, Any] = field(default_factory=dict)
    lines: list[str] = field(default_factory=list)

    def status(self, timeout_s: float = 2.0) -> dict[str, Any]:
        """The latest status snapshot (rewritten every ``--status-period``, 50 ms)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return json.loads(self.status_path.read_text())
            except (OSError, ValueError):
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.01)

    def wait_status(self, pred: Callable[[dict], bool], timeout_s: float = 10.0, period_s: float = 0.02) -> dict:
        """Poll the status until ``pred(status)``; TimeoutError with the last snapshot otherwise."""
        deadline = time.monotonic() + timeout_s
        st: dict = {}
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"rig sim exited with {self.proc.returncode}: {self.stderr()[-2000:]}")
            st = self.status()
            if pred(st):
                return st
            time.sleep(period_s)
        raise TimeoutError(f"status condition not met within {timeout_s} s; last status: {st}")

    def stderr(self) -> str:
        try:
            return self.stderr_path.read_text(errors="replace")
        except OSError:
            return ""

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 10.0) -> int:
        """Signal the simulator and wait; kills it after ``timeout_s``. Returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        return self.proc.returncode

    def __enter__(self) -> "SimProcess":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the parent goes (Linux; ignored elsewhere)."""
    try:
        import ctypes
        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    except Exception:  # noqa: BLE001 - best effort
        pass


def start_sim_process(config: str | Path | None = None, scenario: str | Path | None = None, seed: Optional[int] = 0,
                      extra_args: Sequence[str] = (), *, workdir: str | Path | None = None,
                      timeout_s: float = 60.0, python: str | None = None,
                      env: Optional[dict[str, str]] = None, die_with_parent: bool = True) -> SimProcess:
    """Spawn ``python -m rig_runtime sim --write-config … --status-file …`` and wait for ``ready``.

    The generated config, the status file and the simulator's stderr go to ``workdir``
    (a new temporary directory if None). Stop it with ``.stop()`` (or use it as a context
    manager). ``die_with_parent``: the simulator gets SIGTERM when the thread that started it
    ends (Linux ``PR_SET_PDEATHSIG``), so a crashed test or benchmark leaves no simulator
    behind (with SCHED_FIFO, one would keep a CPU busy)."""
    wd = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="rig-sim-"))
    wd.mkdir(parents=True, exist_ok=True)
    cfg_path, status_path, err_path = wd / "sim-process.yaml", wd / "sim-status.json", wd / "sim.stderr"
    cmd = [python or sys.executable, "-m", "rig_runtime", "sim", "--write-config", str(cfg_path),
           "--status-file", str(status_path)]
    if config is not None:
        cmd += ["--config", str(config)]
    if scenario is not None:
        cmd += ["--scenario", str(scenario)]
    if seed is not None:
        cmd += ["--seed", str(seed)]
    cmd += list(extra_args)
    err = open(err_path, "wb")
    try:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, stdin=subprocess.DEVNULL,
                                env=env, text=True, bufsize=1,
                                preexec_fn=_die_with_parent if die_with_parent else None)
    finally:
        err.close()
    sp = SimProcess(proc, wd, cfg_path, status_path, err_path)
    lines: "queue.SimpleQueue[Optional[str]]" = queue.SimpleQueue()

    def reader() -> None:                    # keeps draining stdout after ready
        assert proc.stdout is not None
        for line in proc.stdout:
            line = line.rstrip("\n")
            sp.lines.append(line)
            lines.put(line)
        lines.put(None)

    threading.Thread(target=reader, name="rig sim stdout", daemon=True).start()
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            line = lines.get(timeout=max(0.01, deadline - time.monotonic()))
        except queue.Empty:
            sp.stop(signal.SIGKILL)
            raise TimeoutError(f"rig sim not ready within {timeout_s} s: {sp.stderr()[-2000:]}") from None
        if line is None:
            proc.wait(5.0)
            raise RuntimeError(f"rig sim exited with {proc.returncode} before ready: {sp.stderr()[-2000:]}")
        if line == "ready":
            return sp
        parse_port_line(line, sp.ports)


if __name__ == "__main__":          # the CAN responder process of ResponderProcess
    if sys.argv[1:2] != ["--can-responder"]:
        sys.exit("usage: python -m sim_backend.process --can-responder <memfd> <ev fd> <cmd fd> <tick_s> <prio>")
    sys.exit(_responder_main(sys.argv[2:]))
