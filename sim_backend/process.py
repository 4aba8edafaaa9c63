"""``rig sim``: the simulated rig served in its own process, in real time, so that an
unmodified ``rig run`` in another process drives it by configuration alone.

What is on the other end of each wire (docs/sim-process.md):

* lasers — the virtual optoNCDT 1420s of :class:`~sim_backend.rig.SimulatedRig`, each
  streaming into its pty at its output rate on the wall clock;
* CAN — an SLCAN adapter emulated on a pty (:mod:`sim_backend.slcan`), bridged to a python-can
  ``virtual`` bus on which the virtual CiA 402 drives run in realtime mode (their heartbeat,
  SYNC/RPDO watchdog and heartbeat consumer on ``time.monotonic``);
* force–torque — the Modbus TCP servers on 127.0.0.1, on their real (free) ports.

The plant runs on one thread (:class:`RealtimeSim`): absolute deadlines ``t0 + k·h`` on
``time.monotonic`` (h = ``controller.h``), each step integrated with the currents the
virtual drives apply at its release; between plant steps the same thread wakes every
``laser_tick_s`` (1 ms) so the lasers' frames leave in small chunks, as a streaming sensor's
do. A late thread catches up (every step is integrated, none skipped) and is counted.

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
import itertools
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

from .rig import SimulatedRig
from .slcan import SlcanAdapter

__all__ = ["RealtimeSim", "SimProcess", "start_sim_process", "serve", "generated_config", "parse_port_line"]

SESSION_SILENCE_S = 1.0        # no SYNC for this long ends a session (runtime killed)
SWITCH_INTERVAL_S = 0.0005     # interpreter switch interval in the rig sim process
FT_RATE_HZ = 100.0             # F/T registers refreshed at the FT 300's own output rate
_channels = itertools.count()


class RealtimeSim:
    """A :class:`SimulatedRig` served in real time (see the module docstring).

    ``start()`` starts the SLCAN adapter, the drives' realtime thread, the plant thread and
    (with ``status_file``) the status writer; ``close()`` stops everything. ``status()``
    is a JSON-ready snapshot: applied currents, drive states, session, plant, timing.
    """

    def __init__(self, cfg: RigConfig, scenario: Optional[Scenario] = None, seed: Optional[int] = None, *,
                 laser_tick_s: float = 0.001, status_file: str | Path | None = None,
                 status_period_s: float = 0.05, ft_rate_hz: float = FT_RATE_HZ, drive_tick_s: float = 0.001,
                 log: Callable[[str], None] | None = None) -> None:
        self.cfg = cfg
        self.h = cfg.controller.h
        self.laser_tick_s = min(laser_tick_s, self.h)
        self.drive_tick_s = drive_tick_s      # the drives' timers (watchdog, heartbeat) granularity
        self.status_file = Path(status_file) if status_file else None
        self.status_period_s = status_period_s
        self.ft_period = 1.0 / ft_rate_hz
        self._log = log or (lambda s: print(f"rig sim: {s}", file=sys.stderr, flush=True))
        chan = f"rig-sim-process-{os.getpid()}-{next(_channels)}"
        self.adapter_bus = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
        self.drive_bus = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
        self.adapter = SlcanAdapter(self.adapter_bus, on_frame=self._on_host_frame,
                                    on_host_frames=self._on_frames_to_host)
        try:
            self.sim = SimulatedRig(cfg, scenario, seed=seed, drive_bus=self.drive_bus)
        except BaseException:
            self.adapter.close()
            self.adapter_bus.shutdown()
            self.drive_bus.shutdown()
            raise
        self.drives = self.sim.drives
        # the plant's first step imports and precomputes (scipy, ~0.3 s): do it here, on a copy,
        # not on the plant thread's first deadline
        copy.deepcopy(self.sim.plant).step(self.h, 0.0, 0.0)
        self.scenario = scenario
        if scenario is not None and any(f.kind == "stall" for f in scenario.faults):
            self._log("scenario 'stall' faults act on the runtime's clock; ignored by rig sim")
        # session (scenario time) bookkeeping; the adapter's reader thread only queues events
        self._events: "queue.SimpleQueue[tuple[str, float]]" = queue.SimpleQueue()
        self._want_sync = False
        self.last_sync_t = math.nan
        self.session_active = False
        self.session_t0 = math.nan            # monotonic time scenario time 0
        self.sessions = 0
        # per-session diagnostics: how promptly the simulator answered (its side of every wire)
        self._stats_lock = threading.Lock()
        self._sync_queue = {COB_TPDO1 + d.node_id: collections.deque(maxlen=16) for d in cfg.devices.can.drives}
        self._tpdo_latency: collections.deque[float] = collections.deque(maxlen=50000)
        self.sess_sync_gap_max = 0.0
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
        self._lateness: collections.deque[float] = collections.deque(maxlen=12000)   # last 60 s
        self._work: collections.deque[float] = collections.deque(maxlen=12000)
        self.thread_error = ""
        self._closed = False

    # ------------------------------------------------------------------ ports
    @property
    def laser_ports(self) -> dict[str, str]:
        return self.sim.laser_ports

    @property
    def can_port(self) -> str:
        return self.adapter.port_name

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
        for s in d["ft"]["sensors"]:
            host, port = self.ft_endpoints[s["name"]]
            s.update(transport="tcp", host=host, port=int(port))
        return d

    # ------------------------------------------------------------------ lifetime
    def start(self) -> "RealtimeSim":
        if self._threads:
            return self
        self.adapter.start()
        self.drives.start_realtime(time.monotonic, tick_s=self.drive_tick_s)
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
        """Stop the threads, the adapter, the drives, the lasers and the F/T servers. Idempotent."""
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
        self.adapter.close()
        self.sim.close()          # drives (stop), F/T servers, lasers
        for b in (self.adapter_bus, self.drive_bus):
            try:
                b.shutdown()
            except Exception:  # noqa: BLE001
                pass

    def __enter__(self) -> "RealtimeSim":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ sessions
    def _on_host_frame(self, msg: can.Message, t: float) -> None:
        """Called by the SLCAN adapter for each frame the runtime sends (its reader thread)."""
        if msg.is_extended_id or msg.is_remote_frame:
            return
        cid = msg.arbitration_id
        if cid == COB_SYNC:
            with self._stats_lock:
                if self._want_sync:                 # a new session: its statistics start here
                    self._want_sync = False
                    self._events.put(("sync", t))
                    for q in self._sync_queue.values():
                        q.clear()
                    self._tpdo_latency.clear()
                    self.sess_sync_gap_max = 0.0
                elif self.last_sync_t == self.last_sync_t:
                    gap = t - self.last_sync_t
                    if self.sess_sync_gap_max < gap < SESSION_SILENCE_S:
                        self.sess_sync_gap_max = gap
                for q in self._sync_queue.values():
                    q.append(t)
            self.last_sync_t = t
        elif cid == COB_NMT and len(msg.data) == 2:
            if msg.data[0] == NMT_START:
                self._want_sync = True
            else:                               # stop, pre-operational, reset: a safe stop
                self._want_sync = False
                self._events.put(("end", t))

    def _on_frames_to_host(self, msgs: list, t: float) -> None:
        """Called by the SLCAN adapter with the frames it just wrote to the pty: the latency
        from each SYNC to the TPDO1 it triggered, as the runtime can first read it."""
        with self._stats_lock:
            for m in msgs:
                q = self._sync_queue.get(m.arbitration_id)
                if q is None or m.is_extended_id:
                    continue
                while q and t - q[0] > 0.1:         # a TPDO that never came (fault injection)
                    q.popleft()
                if q:
                    self._tpdo_latency.append(t - q.popleft())

    def _session_events(self, now: float) -> None:
        while True:
            try:
                kind, t = self._events.get_nowait()
            except queue.Empty:
                break
            if kind == "sync" and not self.session_active:
                self._end_faults()
                self.sess_tick_late_max = self.sess_plant_late_max = 0.0
                self.session_active = True
                self.session_t0 = t
                self.sessions += 1
                self.sim.on_running(t - self.t_wall0)
            elif kind == "end" and self.session_active:
                self._end_session()
        if self.session_active and now - self.last_sync_t > SESSION_SILENCE_S:
            self._end_session()

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
            self._session_events(now)
            stepped = False
            while sim.t + h <= ts + 1e-9:
                deadline = sim.t + h
                self._step_plant(ts - deadline, now)
                stepped = True
            if stepped:
                self._publish(sim.t)
                work = mono() - now
                self._work.append(work)
                if work > self.max_work:
                    self.max_work = work
            for vl in lasers:
                vl.emit_until(ts, wait=False)

    def _step_plant(self, lateness: float, now: float) -> None:
        sim, drives = self.sim, self.drives
        running = not math.isnan(sim.t_run0)
        tau = sim.t - sim.t_run0 if running else -1.0
        if running:
            try:
                sim._update_faults(tau)
            except Exception as e:  # noqa: BLE001 - a bad scenario must not stop the plant
                self._log(f"scenario fault injection failed: {e}")
        Ff, Fr, Mf, Mr = sim._forces(tau) if running else (0.0, 0.0, 0.0, 0.0)
        with drives._lock:
            cur = [drives.current_A(w) for w in WHEELS]
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
        self._lateness.append(lateness)
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
        def dist(values) -> dict[str, float]:
            a = np.asarray(list(values), dtype=float) * 1e6
            if not a.size:
                return {"p50": 0.0, "p99": 0.0, "max": 0.0}
            return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "max": float(a.max())}
        return {"h_s": self.h, "laser_tick_s": self.laser_tick_s, "steps": self.steps,
                "late_steps": self.late_steps, "max_lateness_us": self.max_lateness * 1e6,
                "max_work_us": self.max_work * 1e6,
                "recent_lateness_us": dist(self._lateness), "recent_work_us": dist(self._work)}

    def session_stats(self) -> dict[str, Any]:
        """How promptly the simulator served the current (or last) session, ms: SYNC -> its
        TPDO1 written to the pty, the largest gap between the runtime's SYNCs (the runtime's
        own timing), the plant thread's largest tick / plant-step lateness."""
        with self._stats_lock:
            a = np.asarray(list(self._tpdo_latency), dtype=float) * 1e3
            gap = self.sess_sync_gap_max
        lat = ({"n": int(a.size), "p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
                "max": float(a.max())} if a.size else {"n": 0, "p50": None, "p99": None, "max": None})
        return {"tpdo_latency_ms": lat, "sync_gap_max_ms": gap * 1e3,
                "tick_lateness_max_ms": self.sess_tick_late_max * 1e3,
                "plant_lateness_max_ms": self.sess_plant_late_max * 1e3}

    def status(self) -> dict[str, Any]:
        """A JSON-ready snapshot. Times ``t*`` are ``time.monotonic()`` of this machine
        (system-wide on Linux, so comparable with another process's)."""
        drives = {}
        with self.drives._lock:
            for w in WHEELS:
                d = self.drives.drives.get(w)
                if d is None:
                    continue
                drives[w] = {"current_A": d.current_A(), "state": d.state,
                             "nmt": NMT_STATE_NAMES.get(d.nmt, hex(d.nmt)), "error_code": d.error_code,
                             "watchdog_trips": d.counters["watchdog_trips"],
                             "heartbeat_events": d.counters["heartbeat_events"],
                             "counters": dict(d.counters),
                             "last_sync_t": d.wd_sync if d.wd_armed or d.counters["sync"] else None,
                             "last_rpdo_t": d.wd_rpdo if d.wd_armed or d.counters["rpdo"] else None,
                             "t_current_zero": self.t_current_zero[w],
                             "t_current_nonzero": self.t_current_nonzero[w]}
        p = self.sim.plant
        return {
            "t": time.monotonic(),
            "t_sim": self.sim.t,
            "pid": os.getpid(),
            "currents": {w: v["current_A"] for w, v in drives.items()},
            "drives": drives,
            "session": {"active": self.session_active, "count": self.sessions,
                        "t0": None if math.isnan(self.session_t0) else self.session_t0,
                        "last_sync_t": None if math.isnan(self.last_sync_t) else self.last_sync_t},
            "plant": {"y_f": p.y_f, "y_r": p.y_r, "psi_af": p.psi_af, "psi_ar": p.psi_ar},
            "timing": self.timing(),
            "session_stats": self.session_stats(),
            "slcan": {"open": self.adapter.is_open, "bitrate": self.adapter.bitrate, **self.adapter.counters},
            "error": self.thread_error,
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
          can_interface: str = "slcan", out=None) -> int:
    """Body of ``rig sim``: build, print the port lines (and write the config), ``ready``,
    serve until SIGINT/SIGTERM (or ``duration_s``), shut down cleanly; returns 0.

    ``rt_priority`` / ``cpu_affinity``: SCHED_FIFO priority and CPUs for the simulator's
    threads (set before any is started, so all inherit them), when the OS permits — reported
    on stderr either way. ``runtime_rt_priority`` / ``runtime_cpu_affinity``: written as
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
    if rt_priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
            print(f"rig sim: SCHED_FIFO priority {rt_priority}: applied", file=sys.stderr, flush=True)
        except (OSError, AttributeError) as e:
            print(f"rig sim: SCHED_FIFO priority {rt_priority}: not applied ({e})", file=sys.stderr, flush=True)
    stop = threading.Event()
    old = {}
    for s in (signal.SIGINT, signal.SIGTERM):
        old[s] = signal.signal(s, lambda *_: stop.set())
    rt = None
    try:
        rt = RealtimeSim(cfg, sc, seed=seed, status_file=status_file, status_period_s=status_period_s)
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
