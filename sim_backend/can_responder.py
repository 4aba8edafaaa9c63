"""The CAN side of ``rig sim``: the emulated SLCAN adapter with the virtual CiA 402 drives
directly behind it, served by ONE thread — a SYNC is answered by the thread that read it,
in one write, with no hand-over between threads (docs/sim-process.md, "Inside the
simulator").

:class:`CanResponder` runs on a thread of the ``rig sim`` process; :class:`ResponderProcess`
runs it alone in a child process of its own (``python -m sim_backend.can_responder``), where
no plant, laser, Modbus or status thread competes with it for the interpreter lock. Both
offer the plant side the same interface: applied currents, time of the latest SYNC,
session events, a status snapshot.

Sessions: a session starts when every virtual drive has reached OPERATION ENABLED (the
runtime enables the power stages at its ARM) and ends on an NMT stop / pre-operational /
reset (the runtime's safe stop) or after ``SESSION_SILENCE_S`` without SYNC (a runtime
that was killed). The plant side starts and ends scenario time with them.
"""

from __future__ import annotations

import collections
import gc
import json
import math
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from typing import Any, Callable, Optional, Sequence

import can
import numpy as np

from drivers.cia402 import COB_NMT, COB_SYNC, COB_TPDO1, NMT_START
from rig_runtime.clock import set_sched_fifo
from rig_runtime.config import WHEELS
from rig_runtime.stats import Histogram

from .child_process import die_with_parent
from .slcan import SlcanAdapter

__all__ = ["CanResponder", "ResponderProcess", "SESSION_SILENCE_S", "SHARED_FLOATS", "json_default"]

SESSION_SILENCE_S = 1.0        # no SYNC for this long ends a session (runtime killed)
SHARED_FLOATS = 9
TPDO_LATENCY_BINS = {"bin_s": 1e-5, "max_s": 0.2}     # SYNC -> TPDO1: 10 µs bins up to 0.2 s


def json_default(o: Any) -> Any:
    """``json.dumps(default=…)`` for numpy scalars (and anything else, as text)."""
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


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
    bookkeeping: session events for scenario time (every drive enabled; NMT stop, SYNC
    silence), SYNC → TPDO1 latency, SYNC gaps.

    Runs either inside the ``rig sim`` process (``attach(sim.drives)``; the adapter's own
    thread) or alone in a child process (:class:`ResponderProcess`, ``python -m
    sim_backend.can_responder --can-responder``; drives of its own, the process's only
    thread), where no plant, laser, Modbus or status thread competes with it for the
    interpreter lock.

    ``shared``: 9 floats shared with the plant side — [0:4] wheel speeds in (WHEELS order;
    only with ``speeds_in``, else the plant sets them on the drives itself), [4:8] applied
    currents out (after every service), [8] time of the latest SYNC. ``on_event(kind, t)``:
    "start" (every drive reached OPERATION ENABLED: a session starts) or "end" (NMT stop /
    pre-operational / reset, or no SYNC for ``SESSION_SILENCE_S``); default: queued for
    :meth:`poll_events`.
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
        self.in_session = False
        self._t_session = math.nan
        self._enabled = False               # every drive OPERATION ENABLED at the latest service
        self._stats_lock = threading.Lock()
        self._sync_queue: dict[int, collections.deque] = {}
        self._tpdo_latency = Histogram(**TPDO_LATENCY_BINS)
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
        self._sessions(t)

    def _sessions(self, t: float) -> None:
        """A session starts when every drive reaches OPERATION ENABLED (the runtime's ARM);
        it ends after SESSION_SILENCE_S without SYNC (a killed runtime; NMT: _on_host_frame)."""
        enabled = self.drives.operation_enabled()
        if enabled and not self._enabled and not self.in_session:
            self.in_session = True
            self._t_session = t
            with self._stats_lock:          # the session's statistics start here
                for q in self._sync_queue.values():
                    q.clear()
                self._tpdo_latency.clear()
                self.sync_gap_max = 0.0
            self.on_event("start", t)
        self._enabled = enabled
        if self.in_session:
            last = float(self.shared[8])
            if t - (last if last > self._t_session else self._t_session) > SESSION_SILENCE_S:
                self._end_session(t)

    def _end_session(self, t: float) -> None:
        if self.in_session:
            self.in_session = False
            self.on_event("end", t)

    def _on_host_frame(self, msg: can.Message, t: float) -> None:
        """Each frame the runtime sends (before the drives get it): NMT ends a session,
        SYNC statistics."""
        self.t_last_host_frame = t
        if msg.is_extended_id or msg.is_remote_frame:
            return
        cid = msg.arbitration_id
        if cid == COB_SYNC:
            with self._stats_lock:
                last = float(self.shared[8])
                if last == last:
                    gap = t - last
                    if self.sync_gap_max < gap < SESSION_SILENCE_S:
                        self.sync_gap_max = gap
                for q in self._sync_queue.values():
                    q.append(t)
            self.shared[8] = t
        elif cid == COB_NMT and len(msg.data) == 2 and msg.data[0] != NMT_START:
            self._end_session(t)                # stop, pre-operational, reset: a safe stop

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
        drives = self.drives.status()
        with self._stats_lock:
            hist = self._tpdo_latency.copy()
            gap = self.sync_gap_max
        ad = self.adapter
        return {"drives": drives, "slcan": {"open": ad.is_open, "bitrate": ad.bitrate, **ad.counters},
                "tpdo_latency_ms": hist.summary(1e3), "sync_gap_max_ms": gap * 1e3}


class ResponderProcess(_SharedView):
    """A :class:`CanResponder` in a child process (``python -m sim_backend.can_responder
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
            cmd = [python or sys.executable, "-m", "sim_backend.can_responder", "--can-responder",
                   *(str(f) for f in fds), repr(float(tick_s)), str(rt_priority or 0)]
            self.proc = subprocess.Popen(cmd, pass_fds=fds, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                         preexec_fn=die_with_parent)
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
    if prio and (err := set_sched_fifo(prio)):
        print(f"rig sim: CAN responder SCHED_FIFO {prio}: not applied ({err})", file=sys.stderr, flush=True)
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
            snap = json.dumps({"id": pending[-1], "snapshot": resp.snapshot()}, default=json_default)
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



if __name__ == "__main__":          # the CAN responder process of ResponderProcess
    if sys.argv[1:2] != ["--can-responder"]:
        sys.exit("usage: python -m sim_backend.can_responder --can-responder <memfd> <ev fd> <cmd fd> <tick_s> <prio>")
    sys.exit(_responder_main(sys.argv[2:]))
