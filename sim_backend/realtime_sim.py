"""``rig sim``'s simulated rig in real time: the plant on one thread, absolute deadlines
``t0 + k·h`` on ``time.monotonic`` (h = ``controller.h``), each step integrated with the
currents the virtual drives apply at its release; between plant steps the same thread
wakes every ``laser_tick_s`` (1 ms) so the lasers' frames leave in small chunks, as a
streaming sensor's do. A late thread catches up (every step is integrated, none skipped)
and is counted.

A pause — the process stopped (SIGSTOP/SIGCONT, a debugger, a suspended terminal) or not
scheduled for longer than ``pause_s`` — is noted (one line on stderr, and in the status: the
count, the longest, the last with the lateness it caused) and serving goes on: the plant
catches up at most ``max_catchup_s`` of the lost time step by step; the rest it skips (the
plant stood still while the simulator did; simulated time then lags the wall clock by the
skipped total, also in the status). The runtime on the other side sees its sensors go stale
and faults, as it would with a real rig whose sensors stop; the next ``rig run`` connects
as usual. The CAN side is a :mod:`~sim_backend.can_responder` (in a child process by
default); wheel speeds go to it, applied currents and session events come back.

Scenario time runs from the responder's session start (every drive reached OPERATION
ENABLED) to its end (NMT stop / pre-operational / reset, or 1 s without SYNC); ``stall``
faults act on the runtime's own clock and cannot be injected from here: they are ignored.
The plant steps with :meth:`SimulatedRig.step`, the one plant step lockstep uses too.
"""

from __future__ import annotations

import copy
import json
import math
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional

import can

from rig_runtime.clock import set_sched_fifo
from rig_runtime.config import WHEELS, RigConfig
from rig_runtime.scenario import Scenario
from rig_runtime.stats import Histogram

from .can_responder import CanResponder, ResponderProcess, json_default
from .rig import SimulatedRig

__all__ = ["RealtimeSim", "FT_RATE_HZ"]

FT_RATE_HZ = 100.0             # F/T registers refreshed at the FT 300's own output rate
TIMING_BINS = {"bin_s": 1e-5, "max_s": 0.2, "window_s": 30.0}   # 10 µs bins, the last 30-60 s
PAUSE_S = 0.1                  # a plant thread this late was paused (stopped or not scheduled)
MAX_CATCHUP_S = 1.0            # of a pause's lost time, at most this much is integrated step by step


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
                 log: Callable[[str], None] | None = None, pause_s: float = PAUSE_S,
                 max_catchup_s: float = MAX_CATCHUP_S) -> None:
        if can_responder not in ("thread", "process"):
            raise ValueError(f"can_responder is 'thread' or 'process', not {can_responder!r}")
        self.cfg = cfg
        self.h = cfg.controller.h
        self.laser_tick_s = min(laser_tick_s, self.h)
        self.drive_tick_s = drive_tick_s      # the drives' timers (watchdog, heartbeat) granularity
        self.status_file = Path(status_file) if status_file else None
        self.status_period_s = status_period_s
        self.pause_s = max(pause_s, 2.0 * self.h)
        self.max_catchup_s = max_catchup_s
        self.ft_period = 1.0 / ft_rate_hz
        self._log = log or (lambda s: print(f"rig sim: {s}", file=sys.stderr, flush=True))
        self._null_bus: Optional[_NullBus] = None
        if can_responder == "process":
            self.can: Any = ResponderProcess(tick_s=drive_tick_s, rt_priority=responder_rt_priority)
            self._null_bus = drive_bus = _NullBus()
        else:
            def prio() -> None:
                if responder_rt_priority and (err := set_sched_fifo(responder_rt_priority)):
                    self._log(f"CAN responder SCHED_FIFO {responder_rt_priority}: not applied ({err})")
            self.can = CanResponder(tick_s=drive_tick_s, on_thread_start=prio)
            drive_bus = self.can.adapter.device_bus
        try:
            self.sim = SimulatedRig(cfg, scenario, seed=seed, drive_bus=drive_bus)
            if can_responder == "process":
                self.can.configure(self.sim.wired_can(), self.sim.seed)
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
        self._lateness = Histogram(**TIMING_BINS)
        self._work = Histogram(**TIMING_BINS)
        self.pauses = 0                     # see the module docstring
        self.pause_longest_s = 0.0
        self.pause_skipped_s = 0.0          # simulated time behind the wall clock by this much
        self.last_pause: Optional[dict[str, Any]] = None
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

    @property
    def laser_rates_hz(self) -> dict[str, float]:
        """The rate each virtual laser really streams at (its configured output rate, or sim.laser_rate_hz)."""
        return {r: float(v.rate_hz) for r, v in self.sim.lasers.items()}

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
    def _session_events(self) -> bool:
        """The responder's session events start and end scenario time; whether there were any."""
        events = self.can.poll_events()
        for kind, t in events:
            if kind == "start" and not self.session_active:
                self.sess_tick_late_max = self.sess_plant_late_max = 0.0
                self.session_active = True
                self.session_t0 = t
                self.sessions += 1
                self.sim.start_scenario(t - self.t_wall0)
                self.sim.power_observed(True)
            elif kind == "end" and self.session_active:
                self.session_active = False
                self.sim.end_scenario()
                self.sim.power_observed(False)
        return bool(events)

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
            if late > self.pause_s:
                t0 = self._paused(late, now)                # skips what is not caught up
                ts = now - t0
            if late > self.sess_tick_late_max:
                self.sess_tick_late_max = late
            if ts - k * tick > tick:                        # overslept: next tick from now
                k = int(ts / tick)
            changed = self._session_events()
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

    def _paused(self, late: float, now: float) -> float:
        """The plant thread was away ``late`` s (a pause, see the module docstring): note it,
        skip what is beyond ``max_catchup_s``; the (new) wall time of simulated time 0."""
        skip = max(0.0, late - self.max_catchup_s)
        if skip > 0.0:
            self.t_wall0 += skip
            self.pause_skipped_s += skip
        self.pauses += 1
        self.pause_longest_s = max(self.pause_longest_s, late)
        self.last_pause = {"t_resumed": now, "duration_s": late, "skipped_s": skip,
                           "caught_up_s": late - skip, "t_sim": self.sim.t}
        self._log(f"paused {late:.3f} s (stopped or not scheduled) at simulated t={self.sim.t:.3f} s; "
                  + (f"caught up {late - skip:.3f} s, skipped {skip:.3f} s" if skip else f"caught up {late:.3f} s")
                  + "; serving again")
        return self.t_wall0

    def _step_plant(self, lateness: float, now: float) -> None:
        cur = self.can.currents                 # what the drives apply now (after their last service)
        for w, c in zip(WHEELS, cur):
            prev = self._applied[w]
            if prev != 0.0 and c == 0.0:
                self.t_current_zero[w] = now
            elif prev == 0.0 and c != 0.0:
                self.t_current_nonzero[w] = now
            self._applied[w] = c
        self.sim.step(self.h, cur)
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
                "recent_lateness_us": dist(self._lateness), "recent_work_us": dist(self._work),
                "pauses": {"count": self.pauses, "longest_s": self.pause_longest_s,
                           "skipped_s": self.pause_skipped_s, "last": self.last_pause}}

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
            "plant": {"y_f": p.y_f, "y_r": p.y_r, "psi_af": p.psi_af, "psi_ar": p.psi_ar, "v": p.v},
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
        tmp.write_text(json.dumps(self.status(), default=json_default))
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

