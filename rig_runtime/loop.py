"""The control loop: one fixed period, read → geometry → safety check → controller →
safety limit → write → record, with one timestamp per cycle.

The loop owns time (a ``Clock``), never blocks on I/O (drivers drain OS buffers), freezes
and disables the garbage collector while running, times every cycle and skips missed
periods instead of catching up.
"""

from __future__ import annotations

import gc
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Protocol, Sequence

from .clock import Clock
from .config import LASER_ROLES, WHEELS, RigConfig
from .control import make_controller
from .geometry import measure
from .safety import Channel, State, Supervisor
from .stats import CycleStats


class DeviceSet(Protocol):
    """What the loop needs from the devices (``devices.py`` builds it from drivers)."""

    channels: list[Channel]      # lasers (LASER_ROLES order), wheels (WHEELS order), F/T sensors
    dist: list[float]            # latest laser distances, m, LASER_ROLES order
    omega: list[float]           # wheel speeds, rad/s, WHEELS order
    converters_ok: bool
    converters_ready: bool
    converter_cause: str
    extra_columns: Sequence[str]     # e.g. F/T wrench components
    extra_values: list[float]

    def poll(self, now: float) -> None: ...
    def write(self, currents: Sequence[float], now: float) -> None: ...
    def disable(self, now: float) -> None: ...


@dataclass
class RunResult:
    final_state: str
    faults: list
    cycles: int
    max_abs_current_A: float
    timing: dict
    t_start: float = math.nan           # when RUNNING began (scenario time origin)
    wall_time_s: float = 0.0
    arm_blockers: list = field(default_factory=list)


CARRIER_INDEX = {"front": 0, "rear": 1}


class ControlLoop:
    """Runs the cycle against a device set with a clock, a supervisor and a recorder."""

    def __init__(self, cfg: RigConfig, devices: DeviceSet, clock: Clock, *,
                 reference: Callable[[float], float] = lambda t: 0.0,
                 open_loop: Optional[tuple[str, Callable[[float], float]]] = None,
                 recorder=None, on_event: Callable | None = None,
                 in_cycle: Callable[[float, float], None] | None = None,
                 on_running: Callable[[float], None] | None = None):
        self.cfg = cfg
        self.h = cfg.controller.h
        self.dev = devices
        self.clock = clock
        self.reference = reference
        self.open_loop = open_loop
        self.recorder = recorder
        self.in_cycle = in_cycle
        self.on_running = on_running
        self._events = on_event
        self.supervisor = Supervisor(cfg.limits, self.h, on_event=self._event)
        self.carriers = [CARRIER_INDEX[c] for c in cfg.controlled]
        psi_ref_max = cfg.limits.psi_max * 0.8
        self.controllers = [make_controller(cfg.controller, cfg.limits.u_max, psi_ref_max) for _ in self.carriers]
        self.stats = CycleStats()
        self.stop_requested = False
        self.t_start = math.nan
        self.max_abs_current = 0.0
        self.currents = [0.0, 0.0, 0.0, 0.0]
        self.columns = self._columns()
        self.last_measurement = None
        self.status: dict = {}

    # ------------------------------------------------------------------ recorder layout
    def _columns(self) -> list[str]:
        cols = ["t", "t_run", "lateness", "work", "state", "y_ref"]
        for r in LASER_ROLES:
            cols += [r, f"{r}_age"]
        for w in WHEELS:
            cols += [f"omega_{w}", f"omega_{w}_age"]
        cols += list(self.dev.extra_columns)
        cols += ["y_m", "psi_m", "y_f", "y_r", "psi_af", "psi_ar", "psi_f", "psi_r", "dw_f", "dw_r"]
        for c in self.cfg.controlled:
            cols += [f"{c}_{n}" for n in ("e_y", "x_I", "psi_ref", "e_psi", "de_psi", "u_unsat", "u_cmd", "u_lim")]
        cols += [f"i_{w}" for w in WHEELS]
        return cols

    def _event(self, t, kind, fault, text) -> None:
        if self.recorder is not None:
            if fault is not None:
                self.recorder.event(t, kind, fault.device, fault.check, fault.value, fault.limit, fault.message)
            else:
                self.recorder.event(t, kind, message=text)
        if self._events is not None:
            self._events(t, kind, fault, text)

    # ------------------------------------------------------------------ the cycle
    def run(self, duration_s: float, arm_timeout_s: float = 2.0, settle_after_fault_s: float = 0.1,
            status: Callable[["ControlLoop"], None] | None = None, status_period_s: float = 0.2) -> RunResult:
        """Warm up (IDLE, zero current) until every channel is fresh, arm, run for
        ``duration_s`` of RUNNING, stop (ramp, disable). Returns the summary."""
        h, clock, dev, sup = self.h, self.clock, self.dev, self.supervisor
        channels = dev.channels
        dist, omega = dev.dist, dev.omega
        geo = self.cfg.geometry
        rec = self.recorder
        ctrls = self.controllers
        carriers = self.carriers
        ref = self.reference
        ol = self.open_loop
        ol_idx = CARRIER_INDEX[ol[0]] if ol else -1
        currents = self.currents
        stats = self.stats
        in_cycle = self.in_cycle
        wall0 = time.perf_counter()
        gc.collect()            # before t0: a collection can take tens of ms
        gc.freeze()
        gc_was_enabled = gc.isenabled()
        gc.disable()
        t0 = clock.now() + h
        k = 0
        t_arm_deadline = t0 + arm_timeout_s
        t_end = math.inf
        t_fault_end = math.inf
        arm_blockers: list[str] = []
        next_status = 0.0
        u_out = [0.0, 0.0]
        try:
            while True:
                t_k = t0 + k * h
                t = clock.wait_until(t_k)
                lateness = t - t_k
                # ---- read
                dev.poll(t)
                m = measure(dist[0], dist[1], dist[2], dist[3], dist[4], dist[5],
                            omega[0], omega[1], omega[2], omega[3], geo)
                self.last_measurement = m
                ys = (m.y_f, m.y_r)
                psis = (m.psi_af, m.psi_ar)
                # ---- state machine
                st = sup.state
                if st is State.IDLE and math.isnan(self.t_start):
                    arm_blockers = sup.arm_blockers(channels, dev.converters_ready, t)
                    if stats.overrun_periods:   # warm-up still missing deadlines (first drains, imports)
                        arm_blockers.append(f"loop: {stats.overrun_periods} periods lost to deadline misses")
                    if not arm_blockers:
                        sup.arm(channels, dev.converters_ready, t)
                    elif t >= t_arm_deadline:
                        break
                elif st is State.ARMED:
                    sup.start(t)
                    self.t_start = t
                    t_end = t + duration_s
                    y_ref0 = ref(0.0)
                    for c, i in zip(ctrls, carriers):
                        c.start(y_ref0, ys[i], psis[i])
                    if self.on_running is not None:
                        self.on_running(t)
                if self.stop_requested and sup.state in (State.ARMED, State.RUNNING):
                    sup.request_stop(t, "stop requested (signal)")
                elif t >= t_end and sup.state is State.RUNNING:
                    sup.request_stop(t, "duration reached")
                # ---- safety check (main bus position: the carriers the controller uses)
                ci = carriers[-1]
                sup.check(t, channels, dev.converters_ok, dev.converter_cause, ys[ci], psis[ci],
                          stats.overrun_periods, rec.healthy if rec is not None else True,
                          rec.error if rec is not None else "")
                # ---- control
                tr = t - self.t_start if self.t_start == self.t_start else 0.0
                y_ref = ref(tr)
                running = sup.state is State.RUNNING
                u_out[0] = u_out[1] = 0.0
                for c, i in zip(ctrls, carriers):
                    if running and i != ol_idx:
                        u = c.step(y_ref, ys[i], psis[i])
                    else:
                        u = 0.0
                    u_out[i] = u
                if ol is not None and running:
                    u_out[ol_idx] = ol[1](tr)
                # ---- limit
                for i in (0, 1):
                    u_lim = sup.limit(u_out[i], t, i)
                    half = 0.5 * u_lim
                    currents[2 * i] = half
                    currents[2 * i + 1] = -half
                    for c, ci_ in zip(ctrls, carriers):
                        if ci_ == i:
                            c.limit_feedback(u_lim)
                    a = abs(u_lim)
                    if a > self.max_abs_current:
                        self.max_abs_current = a
                sup.end_cycle(t)
                # ---- write
                dev.write(currents, t)
                if sup.new_fault or (sup.state is State.IDLE and not math.isnan(self.t_start)):
                    dev.disable(t)
                    if sup.state is State.FAULT:
                        t_fault_end = t + settle_after_fault_s
                if in_cycle is not None:
                    in_cycle(t, tr)
                # ---- record
                work = clock.now() - t
                if rec is not None:
                    row = [t, tr, lateness, work, float(sup.state), y_ref]
                    for j in range(6):
                        c = channels[j]
                        row.append(c.value); row.append(t - c.t)
                    for j in range(4):
                        c = channels[6 + j]
                        row.append(c.value); row.append(t - c.t)
                    row.extend(dev.extra_values)
                    row.extend((m.y_m, m.psi_m, m.y_f, m.y_r, m.psi_af, m.psi_ar, m.psi_f, m.psi_r, m.dw_f, m.dw_r))
                    for c, i in zip(ctrls, carriers):
                        s = c.st
                        row.extend((s.e_y, s.x_I, s.psi_ref, s.e_psi, s.de_psi, s.u_unsat, u_out[i],
                                    2.0 * currents[2 * i]))
                    row.extend(currents)
                    rec.append(row)
                if status is not None and t >= next_status:
                    next_status = t + status_period_s
                    status(self)
                # ---- timing: skip missed periods, do not catch up
                t_done = clock.now()
                work = t_done - t
                missed = t_done > t_k + h
                k_next = int((t_done - t0) / h) + 1 if missed else k + 1  # next release still ahead
                stats.update(lateness, work, missed, k_next - k - 1)
                k = k_next
                st = sup.state
                if st is State.FAULT and t >= t_fault_end:
                    break
                if st is State.IDLE and (not math.isnan(self.t_start) or self.stop_requested):
                    break
        except BaseException:
            # anything unexpected inside the loop: zero current and disable before leaving
            self._safe_off()
            raise
        finally:
            gc.unfreeze()
            if gc_was_enabled:
                gc.enable()
        if sup.state is not State.FAULT and sup.state is not State.IDLE:
            self._safe_off()
        summary = stats.summary()
        return RunResult(final_state=sup.state.name, faults=[f.as_dict() for f in sup.faults],
                         cycles=summary.pop("cycles"), max_abs_current_A=self.max_abs_current,
                         timing=summary, t_start=self.t_start, wall_time_s=time.perf_counter() - wall0,
                         arm_blockers=arm_blockers if math.isnan(self.t_start) else [])

    def _safe_off(self) -> None:
        """Zero current on the wire and converters disabled; never raises."""
        t = self.clock.now()
        for i in range(4):
            self.currents[i] = 0.0
        try:
            self.dev.write(self.currents, t)
        except Exception:
            pass
        try:
            self.dev.disable(t)
        except Exception:
            pass
