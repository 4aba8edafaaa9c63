"""The control loop: one fixed period, read → geometry → supervisor → controller → limit
→ write → record, with one timestamp per cycle.

The loop owns time (a ``Clock``), never blocks on I/O (drivers drain OS buffers), freezes
and disables the garbage collector while running, times every cycle and skips missed
periods instead of catching up. It asks the supervisor what to do (the supervisor owns
every state transition and switches the power stages) and does it.

Operator commands (``rig ctl``) arrive through an optional :class:`~rig_runtime.mailbox.Mailbox`
(``loop.mailbox``), looked at once at the start of every cycle: ``stop`` is the same request
as a stop signal; ``set`` applies an already checked gain change (``tuning.check``) to every
controller before this cycle's step and records an operator event; ``reset-fault`` resets a
latched fault when the run holds on faults (``run(hold_on_fault=True)``) and arms again.
"""

from __future__ import annotations

import gc
import math
import time
from dataclasses import dataclass, field
from operator import attrgetter
from typing import Callable, Iterable, Optional, Protocol, Sequence

from .clock import Clock
from .config import LASER_ROLES, WHEELS, RigConfig
from .control import make_controller
from .gains import TuningError, admissible
from .geometry import Measurement, measure
from .mailbox import Command
from .safety import Channel, State, Supervisor
from .stats import CycleStats


class DeviceSet(Protocol):
    """What the loop needs from the devices (``devices.RigDevices``)."""

    extra_columns: Sequence[str]     # e.g. F/T wrench components

    def channels(self) -> list[Channel]: ...
    def activate(self, now: float) -> None: ...
    def poll(self, now: float): ...          # -> devices.CycleInput
    def write(self, currents: Sequence[float], now: float) -> None: ...
    def deactivate(self, now: float) -> None: ...
    def resume(self, now: float) -> None: ...


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
CYCLE_FIELDS = ("t", "t_run", "lateness", "work", "state", "y_ref")
MEASUREMENT_FIELDS = Measurement._fields
CONTROLLER_FIELDS = ("e_y", "x_I", "psi_ref", "e_psi", "de_psi", "u_unsat")


class Cycle:
    """The values of the cycle being recorded (one object, updated in place)."""

    __slots__ = CYCLE_FIELDS + ("m", "extra", "u_out", "currents")

    def __init__(self) -> None:
        for f in CYCLE_FIELDS:
            setattr(self, f, math.nan)
        self.m: Measurement | None = None
        self.extra: tuple[float, ...] = ()
        self.u_out = [0.0, 0.0]          # controller output per carrier index
        self.currents = [0.0, 0.0, 0.0, 0.0]


Getter = Callable[[Cycle], Iterable[float]]


def row_spec(channels: Sequence[Channel], extra_columns: Sequence[str], controlled: Sequence[str],
             controllers: Sequence) -> list[tuple[tuple[str, ...], Getter]]:
    """The log's columns: (names, getter) groups, each group's names made from the same
    field list its getter reads, so the header and a row cannot disagree."""
    spec: list[tuple[tuple[str, ...], Getter]] = [(CYCLE_FIELDS, attrgetter(*CYCLE_FIELDS))]
    for c in channels[:len(LASER_ROLES) + len(WHEELS)]:
        name = c.name if c.kind == "laser" else f"omega_{c.name}"
        spec.append(((name, f"{name}_age"), lambda cy, c=c: (c.value, cy.t - c.t)))
    spec.append((tuple(extra_columns), attrgetter("extra")))
    spec.append((MEASUREMENT_FIELDS, attrgetter("m")))
    for carrier, ctrl in zip(controlled, controllers):
        i = CARRIER_INDEX[carrier]
        st = attrgetter(*CONTROLLER_FIELDS)
        spec.append((tuple(f"{carrier}_{f}" for f in CONTROLLER_FIELDS) + (f"{carrier}_u_cmd", f"{carrier}_u_lim"),
                     lambda cy, ctrl=ctrl, i=i, st=st: (*st(ctrl.st), cy.u_out[i], 2.0 * cy.currents[2 * i])))
    spec.append((tuple(f"i_{w}" for w in WHEELS), attrgetter("currents")))
    return spec


class ControlLoop:
    """Runs the cycle against a device set with a clock, a supervisor and a recorder."""

    def __init__(self, cfg: RigConfig, devices: DeviceSet, clock: Clock, *,
                 reference: Callable[[float], float] = lambda t: 0.0,
                 open_loop: Optional[tuple[str, Callable[[float], float]]] = None,
                 recorder=None, on_event: Callable | None = None):
        self.cfg = cfg
        self.h = cfg.controller.h
        self.dev = devices
        self.clock = clock
        self.reference = reference
        self.open_loop = open_loop
        self.recorder = recorder
        self._events = on_event
        self.channels = devices.channels()
        self.supervisor = Supervisor(cfg.limits, self.h, self.channels, cfg.controlled, devices,
                                     on_event=self._event)
        self.carriers = [CARRIER_INDEX[c] for c in cfg.controlled]
        psi_ref_max = cfg.limits.psi_max * 0.8
        self.controllers = [make_controller(cfg.controller, cfg.limits.u_max, psi_ref_max) for _ in self.carriers]
        self.stats = CycleStats()
        self.stop_requested = False
        self.stop_reason = "stop requested (signal)"
        self.mailbox = None             # a mailbox.Mailbox: operator commands (rig ctl), taken once per cycle
        self.t_start = math.nan
        self.max_abs_current = 0.0
        self.cycle = Cycle()
        self.spec = row_spec(self.channels, devices.extra_columns, cfg.controlled, self.controllers)
        self.columns = [n for names, _ in self.spec for n in names]

    @property
    def currents(self) -> list[float]:
        return self.cycle.currents

    @property
    def last_measurement(self) -> Measurement | None:
        return self.cycle.m

    def _event(self, t, kind, fault, text) -> None:
        if self.recorder is not None:
            if fault is not None:
                self.recorder.event(t, kind, fault.device, fault.check, fault.value, fault.limit, fault.message)
            else:
                self.recorder.event(t, kind, message=text)
        if self._events is not None:
            self._events(t, kind, fault, text)

    def gains(self) -> dict[str, float]:
        """The controller gains in force (every controlled carrier has the same)."""
        return self.controllers[0].gains() if self.controllers else {}

    def _operator(self, cmd: Command, t: float, hold_on_fault: bool, arm_timeout_s: float) -> bool:
        """Carry out one operator command at the start of a cycle and answer it; True if it
        reset a latched fault (the run then arms and starts afresh)."""
        mb, sup = self.mailbox, self.supervisor
        kind = cmd.kind
        if kind == "stop":
            if not self.stop_requested:
                self.stop_reason = "stop requested (rig ctl)"
            self.stop_requested = True
            mb.answer(cmd.seq, True, f"stop requested in {sup.state.name}")
        elif kind == "set":
            # the server ran tuning.check (bounds and the stability gate) before posting; the
            # loop repeats its cheap part, so nothing outside the bounds is applied whoever
            # wrote into the mailbox
            name = cmd.name
            ctrls = self.controllers
            try:
                new = admissible(self.cfg, name, cmd.value)
            except TuningError as e:
                mb.answer(cmd.seq, False, str(e))
                return False
            if not ctrls:
                mb.answer(cmd.seq, False, "no carrier is controlled: no gain to change")
                return False
            old = ctrls[0].gains()[name]    # admissible: a gain of the law every controller runs
            for c in ctrls:
                c.set_gain(name, new)
            text = f"{name} {old:g} -> {new:g}"
            if self.recorder is not None:
                self.recorder.event(t, "operator", "controller", name, new, old, text)
            if self._events is not None:
                self._events(t, "operator", None, text)
            mb.answer(cmd.seq, True, text)
        elif kind == "reset-fault":
            if sup.state is not State.FAULT:
                mb.answer(cmd.seq, False, f"no latched fault (state {sup.state.name})")
            elif not hold_on_fault:
                mb.answer(cmd.seq, False, "no latched fault to reset: this run ends on a fault (it does not hold)")
            else:
                sup.reset(t)
                sup.request_arm(t + arm_timeout_s)
                mb.answer(cmd.seq, True, "fault reset: arming again, the scenario restarts when RUNNING")
                return True
        else:
            mb.answer(cmd.seq, False, f"unknown command {kind!r}")
        return False

    def row(self) -> list[float]:
        """This cycle's log row, in ``columns`` order."""
        row: list[float] = []
        cy = self.cycle
        for _, get in self.spec:
            row.extend(get(cy))
        return row

    # ------------------------------------------------------------------ the cycle
    def run(self, duration_s: float, arm_timeout_s: float = 2.0, settle_after_fault_s: float = 0.1,
            status: Callable[["ControlLoop"], None] | None = None, status_period_s: float = 0.2,
            hold_on_fault: bool = False) -> RunResult:
        """Warm up (IDLE, zero current, power stages off) until every channel is fit, arm
        (power stages on), run for ``duration_s`` of RUNNING, stop (ramp, power stages
        off). Returns the summary.

        A FAULT ends the run ``settle_after_fault_s`` later; with ``hold_on_fault`` the loop
        keeps cycling in FAULT (zero current, power stages off, recording) until a stop
        request, or an operator ``reset-fault`` (IDLE, arm again; a new RUNNING restarts
        the reference and the duration)."""
        h, clock, dev, sup = self.h, self.clock, self.dev, self.supervisor
        geo = self.cfg.geometry
        rec = self.recorder
        ctrls = self.controllers
        carriers = self.carriers
        ref = self.reference
        ol = self.open_loop
        ol_idx = CARRIER_INDEX[ol[0]] if ol else -1
        cy = self.cycle
        mb = self.mailbox
        currents = cy.currents
        u_out = cy.u_out
        stats = self.stats
        wall0 = time.perf_counter()
        gc.collect()            # before t0: a collection can take tens of ms
        gc.freeze()
        gc_was_enabled = gc.isenabled()
        gc.disable()
        t0 = clock.now() + h
        k = 0
        sup.request_arm(t0 + arm_timeout_s)
        t_end = math.inf
        t_fault_end = math.inf
        next_status = 0.0
        try:
            while True:
                t_k = t0 + k * h
                t = clock.wait_until(t_k)
                cy.t = t
                cy.lateness = t - t_k
                # ---- operator commands (rig ctl): at the cycle boundary, before anything uses the gains
                if mb is not None:
                    cmd = mb.take()
                    if cmd is not None and self._operator(cmd, t, hold_on_fault, arm_timeout_s):
                        t_fault_end = t_end = math.inf      # a fault was reset: the next RUNNING starts afresh
                # ---- read
                inp = dev.poll(t)
                s = inp.samples
                m = cy.m = measure(s[0].value, s[1].value, s[2].value, s[3].value, s[4].value, s[5].value,
                                   s[6].value, s[7].value, s[8].value, s[9].value, geo)
                cy.extra = inp.extra
                ys = (m.y_f, m.y_r)
                psis = (m.psi_af, m.psi_ar)
                # ---- supervisor: requests, transitions, checks
                if self.stop_requested:
                    sup.request_stop(t, self.stop_reason)
                elif t >= t_end:
                    sup.request_stop(t, "duration reached")
                # periods lost so far: the misses before this cycle and this release's lateness
                # (a stalled loop is the root cause of what it finds on waking, e.g. a drive watchdog)
                misses = stats.overrun_periods + int(cy.lateness / h)
                sup.cycle(t, s, inp.converters, [(ys[i], psis[i]) for i in carriers], misses,
                          rec.healthy if rec is not None else True, rec.error if rec is not None else "")
                if sup.started:
                    self.t_start = t
                    t_end = t + duration_s
                    y_ref0 = ref(0.0)
                    for c, i in zip(ctrls, carriers):
                        c.start(y_ref0, ys[i], psis[i])
                # ---- control
                tr = cy.t_run = t - self.t_start if self.t_start == self.t_start else 0.0
                y_ref = cy.y_ref = ref(tr)
                running = sup.state is State.RUNNING
                u_out[0] = u_out[1] = 0.0
                for c, i in zip(ctrls, carriers):
                    u_out[i] = c.step(y_ref, ys[i], psis[i]) if running and i != ol_idx else 0.0
                if ol is not None and running:
                    u_out[ol_idx] = ol[1](tr)
                # ---- limit
                for i in (0, 1):
                    u_lim = sup.limit(u_out[i], t, i)
                    half = 0.5 * u_lim
                    currents[2 * i] = half
                    currents[2 * i + 1] = -half
                    for c, ci in zip(ctrls, carriers):
                        if ci == i:
                            c.limit_feedback(u_lim)
                    a = abs(u_lim)
                    if a > self.max_abs_current:
                        self.max_abs_current = a
                sup.end_cycle(t)
                cy.state = float(sup.state)
                # ---- write
                dev.write(currents, t)
                if sup.new_fault:
                    t_fault_end = t + settle_after_fault_s
                # ---- record
                cy.work = clock.now() - t
                if rec is not None:
                    rec.append(self.row())
                if status is not None and t >= next_status:
                    next_status = t + status_period_s
                    status(self)
                # ---- timing: skip missed periods, do not catch up
                t_done = clock.now()
                work = t_done - t
                missed = t_done > t_k + h
                k_next = int((t_done - t0) / h) + 1 if missed else k + 1  # next release still ahead
                stats.update(cy.lateness, work, missed, k_next - k - 1)
                k = k_next
                st = sup.state
                if st is State.FAULT and (self.stop_requested if hold_on_fault else t >= t_fault_end):
                    break
                if st is State.IDLE and not sup.arming and (sup.ever_armed or sup.arm_failed or self.stop_requested):
                    break
        except BaseException:
            # anything unexpected inside the loop: zero current and power stages off before leaving
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
                         arm_blockers=sup.arm_blockers if sup.arm_failed or math.isnan(self.t_start) else [])

    def _safe_off(self) -> None:
        """Zero current on the wire and power stages off; never raises."""
        t = self.clock.now()
        for i in range(4):
            self.cycle.currents[i] = 0.0
        try:
            self.dev.write(self.cycle.currents, t)
        except Exception:
            pass
        try:
            self.dev.deactivate(t)
        except Exception:
            pass
