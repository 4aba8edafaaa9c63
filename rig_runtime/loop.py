"""The control loop: one fixed period, the stages of ``docs/architecture.md`` in order —
operator command, read, geometry, measured speed, supervisor, control (per lane: schedule and
law), limit, write, record —
with one timestamp per cycle.

The loop owns time (a ``Clock``), never blocks on I/O (drivers drain OS buffers), freezes
and disables the garbage collector while running, times every cycle and skips missed
periods instead of catching up. It asks the supervisor what to do (the supervisor owns
every state transition, every rule and the power stages) and does it. Everything that is
per carrier lives in a :class:`~rig_runtime.lanes.Lane`.

Operator commands (``rig ctl``) arrive through an optional :class:`~rig_runtime.mailbox.Mailbox`,
looked at once at the start of every cycle: ``stop`` is the same request as a stop signal;
``set`` applies an already checked gain change (``tuning.check``) to every controller
before this cycle's step and records an operator event; ``reset-fault`` resets a latched
fault when the run holds on faults (``run(hold_on_fault=True)``) and arms again.
"""

from __future__ import annotations

import gc
import math
import time
from dataclasses import dataclass, field
from operator import attrgetter, itemgetter
from typing import Callable, Mapping, Optional, Sequence

from .clock import Clock, next_release
from .config import WHEELS, RigConfig
from .gains import TuningError, admissible
from .geometry import Measurement, measure
from .hardware import Hardware
from .allocation import wheel_currents
from .lanes import Lane, law_signals, make_lanes
from .memo import by_config
from .reconfig_analysis import table as _outage_table
from .mailbox import Command
from .observer import LOG_FIELDS as OBSERVER_FIELDS
from .observer import ObserverDesign
from .safety import Channel, State, Supervisor
from .speed import SpeedEstimate
from .speed import columns as speed_columns
from .stats import CycleStats

outage_table = by_config(_outage_table)     # reconfig_analysis.table, once per config in a process
_JOINT_LASERS, _B_F, _B_R = ("b_f", "b_r"), ("b_f",), ("b_r",)     # the joint filter's lateral lasers


@dataclass
class RunResult:
    final_state: str
    faults: list
    cycles: int
    max_abs_current_A: float
    timing: dict
    t_start: Optional[float] = None     # when RUNNING began (scenario time origin); None: never
    wall_time_s: float = 0.0
    arm_blockers: list = field(default_factory=list)
    degraded: list = field(default_factory=list)    # DEGRADED intervals (carrier, laser, t_start, t_end, end)
    reconfigured: list = field(default_factory=list)    # RECONFIGURED intervals (carrier, device, t_start, t_end, end)
    max_abs_reconfigured_wheel_A: float = 0.0       # largest wheel current while a wheel was lost (a lone wheel: all of u)


CYCLE_FIELDS = ("t", "t_run", "lateness", "work", "state", "y_ref")
MEASUREMENT_FIELDS = Measurement._fields
LANE_FIELDS = ("u_cmd", "u_lim", "y_ref", "g", "held")     # Lane.log_values, after the law's signals
LOGGED_KINDS = ("laser", "wheel")       # channels whose value and age are logged


def _channel_column(c: Channel) -> str:
    return c.name if c.kind == "laser" else f"omega_{c.name}"


def log_columns(cfg: RigConfig, channels: Sequence[Channel], extra_columns: Sequence[str],
                observed: Sequence[str] = ()) -> list[str]:
    """The log's columns for this config and device set, in row order (:meth:`ControlLoop.row`
    builds its rows from the same lists); ``observed``: the carriers with an observer (their
    ``{carrier}_obs_*`` columns come last)."""
    cols = list(CYCLE_FIELDS)
    for c in channels:
        if c.kind in LOGGED_KINDS:
            n = _channel_column(c)
            cols += (n, f"{n}_age")
    cols += extra_columns
    cols += MEASUREMENT_FIELDS
    cols += speed_columns(cfg.plant)
    lane_fields = (*law_signals(cfg), *LANE_FIELDS)     # the law's signals by name (lanes.law_signals)
    for carrier in cfg.controlled:
        cols += (f"{carrier}_{f}" for f in lane_fields)
    cols += (f"i_{w}" for w in WHEELS)
    for carrier in cfg.controlled:
        if carrier in observed:
            cols += (f"{carrier}_obs_{f}" for f in OBSERVER_FIELDS)
    return cols


class Cycle:
    """The values of the cycle being recorded (one object, updated in place)."""

    __slots__ = CYCLE_FIELDS + ("m", "wrench", "currents")

    def __init__(self) -> None:
        self.t = self.t_run = self.lateness = self.work = self.state = self.y_ref = 0.0
        self.m: Measurement | None = None
        self.wrench: tuple[float, ...] = ()
        self.currents = dict.fromkeys(WHEELS, 0.0)      # A per wheel, by name


class ControlLoop:
    """Runs the cycle against a device set with a clock, a supervisor and a recorder; its
    collaborators are given here, at construction."""

    def __init__(self, cfg: RigConfig, devices: Hardware, clock: Clock, *,
                 reference: Callable[[float], float] | Mapping[str, Callable[[float], float]] = lambda t: 0.0,
                 open_loop: Optional[tuple[str, Callable[[float], float]]] = None,
                 recorder=None, mailbox=None, on_event: Callable | None = None,
                 observers: Optional[Mapping[str, ObserverDesign]] = None):
        self.cfg = cfg
        self.h = cfg.controller.h
        self.dev = devices
        self.clock = clock
        self.recorder = recorder        # a recorder.Recorder (or anything with append/event/healthy/error)
        self.mailbox = mailbox          # a mailbox.Mailbox: operator commands (rig ctl), taken once per cycle
        self._events = on_event
        self.channels = devices.channels()
        self.lanes: list[Lane] = make_lanes(cfg, reference, open_loop, observers)
        self.controllers = [l.controller for l in self.lanes if l.controlled]
        self.observed = [l for l in self.lanes if l.observer is not None]
        self._front_contact = cfg.plant.front_contact
        self.speed = SpeedEstimate.from_config(cfg)
        self.supervisor = Supervisor(cfg.limits, self.h, self.channels, [l.carrier for l in self.lanes], devices,
                                     on_event=self._event, observers=[l.observer for l in self.observed],
                                     degraded=cfg.degraded, v_max=cfg.hardware.ceilings.v_max,
                                     outages=outage_table(cfg) if cfg.degraded.on_drive_loss == "reallocate" else None,
                                     v_fixed=cfg.plant.v)
        self._i_wheel = min((d.rated_current_A for d in cfg.devices.can.drives),
                            default=cfg.hardware.drive_rated_current_A)   # each wheel's current limit (allocation)
        self.stats = CycleStats()
        self.stop_requested = False
        self.stop_reason = "stop requested (signal)"
        self.t_start: float | None = None
        self.max_abs_current = 0.0
        self.max_abs_reconfigured_wheel = 0.0
        self.cycle = Cycle()
        self._values: Mapping[str, float] = {}      # this cycle's channel values by name
        self.columns = log_columns(cfg, self.channels, devices.extra_columns, [l.carrier for l in self.observed])
        # what the cycle reads, resolved once here: the geometry, the controlled lanes, and the
        # row's parts in log_columns order (getters by name, the objects whose values it copies)
        self._geometry = cfg.geometry
        self._controlled = [l for l in self.lanes if l.controlled]
        self._cycle_fields = attrgetter(*CYCLE_FIELDS)
        self._logged = [c for c in self.channels if c.kind in LOGGED_KINDS]
        self._wheel_currents = itemgetter(*WHEELS)
        self._observers = [l.observer for l in self.lanes if l.observer is not None]
        # the running gear's joint filter (both carriers' lanes hold a view of it), else None
        self._joint = next((o.joint for o in self._observers if getattr(o, "joint", None) is not None), None)
        self._joint_lanes = tuple(next(l for l in self.observed if l.carrier == c) for c in ("front", "rear")) \
            if self._joint is not None else ()

    @property
    def currents(self) -> dict[str, float]:
        """The current of each wheel (A, by wheel name) sent in the latest cycle."""
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
        """This cycle's log row, in ``columns`` order (a new list: the recorder may keep it)."""
        cy = self.cycle
        t = cy.t
        row = [*self._cycle_fields(cy)]
        add = row.append
        for c in self._logged:                  # each logged channel's value and age
            add(c.value)
            add(t - c.t)
        row += cy.wrench
        row += cy.m
        row += self.speed.log_values()
        for lane in self._controlled:           # the law's signals + LANE_FIELDS per controlled carrier
            row += lane.signal_values()
            row += lane.log_values()
        row += self._wheel_currents(cy.currents)
        for o in self._observers:
            row += o.log_values()
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
        h, clock, sup, cy, stats = self.h, self.clock, self.supervisor, self.cycle, self.stats
        self._duration, self._hold, self._arm_timeout = duration_s, hold_on_fault, arm_timeout_s
        self._t_end = self._t_fault_end = math.inf
        wall0 = time.perf_counter()
        if clock.deadlines:
            gc.collect()        # before t0: a collection can take tens of ms (none in the run: disabled)
        gc.freeze()
        gc_was_enabled = gc.isenabled()
        gc.disable()
        t0 = clock.now() + h
        k = 0
        next_status = 0.0
        sup.request_arm(t0 + arm_timeout_s)
        try:
            while True:
                t_k = t0 + k * h
                t = cy.t = clock.wait_until(t_k)
                cy.lateness = t - t_k
                self._operator_command(t)
                reading = self.dev.poll(t)
                self._measure(reading)
                self.speed.update(reading.values)     # v̂ from the wheel encoders of the carriers in contact
                step = self._supervise(t, reading)
                self._estimate(t)
                if step.started:
                    self._start(t)
                self._control(t, step.state is State.RUNNING)
                fault = self._limit(t)
                self.dev.write(cy.currents, t)
                if fault is not None:
                    self._t_fault_end = t + settle_after_fault_s
                cy.work = clock.now() - t
                if self.recorder is not None:
                    self.recorder.append(self.row())
                if status is not None and t >= next_status:
                    next_status = t + status_period_s
                    status(self)
                k = self._account(t0, k, t, clock.now())
                if self._finished(t):
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
                         arm_blockers=sup.arm_blockers if sup.arm_failed or self.t_start is None else [],
                         degraded=list(sup.degraded_log), reconfigured=list(sup.reconfigured_log),
                         max_abs_reconfigured_wheel_A=self.max_abs_reconfigured_wheel)

    # ---- the stages, in cycle order
    def _operator_command(self, t: float) -> None:
        """At the cycle boundary, before anything uses the gains."""
        if self.mailbox is not None:
            cmd = self.mailbox.take()
            if cmd is not None and self._operator(cmd, t, self._hold, self._arm_timeout):
                self._t_fault_end = self._t_end = math.inf     # a fault was reset: the next RUNNING starts afresh

    def _measure(self, reading) -> None:
        """Sec. 2 geometry from the reading by name; each lane takes its carrier's part."""
        m = self.cycle.m = measure(reading.values, self._geometry)
        self.cycle.wrench = reading.wrench
        self._values = reading.values
        for lane in self.lanes:
            lane.sense(m)

    def _supervise(self, t: float, reading):
        """Requests (stop, duration), then the supervisor's transitions and rules."""
        sup, rec = self.supervisor, self.recorder
        if self.stop_requested:
            sup.request_stop(t, self.stop_reason)
        elif t >= self._t_end:
            sup.request_stop(t, "duration reached")
        # periods lost so far: the misses before this cycle and this release's lateness
        # (a stalled loop is the root cause of what it finds on waking, e.g. a drive watchdog)
        misses = self.stats.overrun_periods + int(self.cycle.lateness / self.h)
        poses = [(l.carrier, l.y, l.psi) for l in self._controlled]
        ok = rec.healthy if rec is not None else True
        cause = "" if ok else rec.error           # the cause only of an unhealthy recorder (the rule's)
        return sup.cycle(t, reading.samples, reading.converters, poses, misses, ok, cause, self.speed)

    def _estimate(self, t: float) -> None:
        """Each observed lane's observer on this cycle's measurement; the lateral lasers are
        used only if the supervisor finds them fit this cycle, the F/T sensors' lateral
        force (the sum of the carrier's two sides' Fy) likewise, else no force is assumed. The other carrier's y is a
        known input where both carriers are on the rollers (else 0: the lifted one's)."""
        if not self.observed:
            return
        sup, m, values = self.supervisor, self.cycle.m, self._values
        joint = self._joint
        if joint is not None:                   # the running gear's filter: each lateral laser on its own
            lf, lr = self._joint_lanes
            if sup.fit(_JOINT_LASERS, t) and not sup.isolated_any(_JOINT_LASERS):
                ok_f = ok_r = True              # the common case: one check for both
            else:
                ok_f = sup.fit(_B_F, t) and not sup.isolated_any(_B_F)
                ok_r = sup.fit(_B_R, t) and not sup.isolated_any(_B_R)
            joint.step(values["b_f"], values["b_r"], ok_f, ok_r, lf.psi, lr.psi, lf.dw, lr.dw,
                       lf.u, lr.u, self._force(lf, t), self._force(lr, t))
        for lane in self.observed:
            if joint is not None:
                self._mark_degraded(lane)
                continue
            y_other = 0.0
            if self._front_contact:
                y_other = m.y_f if lane.carrier == "rear" else m.y_r
            f_lat = 0.0
            ft = lane.ft_sensors
            if ft and sup.fit(ft, t):
                for n in ft:
                    f_lat += values[n]
            lat = lane.lateral_lasers
            lane.estimate(sup.fit(lat, t) and not sup.isolated_any(lat), y_other, f_lat)
            self._mark_degraded(lane)

    def _mark_degraded(self, lane) -> None:
        """A DEGRADED carrier's lane runs on its observer's ŷ (and its log says so)."""
        o = lane.observer
        if lane.carrier in self.supervisor.degraded_since:      # DEGRADED: the lane runs on ŷ
            lane.y = o.y
            o.degraded = 1.0
        else:
            o.degraded = 0.0

    def _force(self, lane, t: float) -> float:
        """The carrier's measured lateral force (the sum of its F/T sensors' Fy; 0 unless all fit)."""
        ft = lane.ft_sensors
        if not ft or not self.supervisor.fit(ft, t):
            return 0.0
        values = self._values
        return sum(values[n] for n in ft)

    def _start(self, t: float) -> None:
        """RUNNING began: the scenario's time origin, the duration, bumpless controllers."""
        self.t_start = t
        self._t_end = t + self._duration
        for lane in self.lanes:
            lane.start()

    def _control(self, t: float, running: bool) -> None:
        """Each lane's schedule on v̂ (gain factor, hold), then its command."""
        cy = self.cycle
        tr = cy.t_run = t - self.t_start if self.t_start is not None else 0.0
        v_hat = self.speed.v_hat
        for lane in self.lanes:
            lane.schedule(v_hat)
            lane.control(tr, running)
        cy.y_ref = self.lanes[0].y_ref if self.lanes else 0.0

    def _limit(self, t: float):
        """Each lane's output through the supervisor, onto its wheels; returns the fault
        latched in this cycle (None: none)."""
        sup, cy = self.supervisor, self.cycle
        for lane in self.lanes:
            u = sup.limit(lane.carrier, lane.u_cmd, t)
            lane.apply(u)
            if abs(u) > self.max_abs_current:
                self.max_abs_current = abs(u)
        fault = sup.end_cycle(t)
        cy.state = float(sup.state)
        lost = sup.wheels_lost
        wheel_currents(self.lanes, cy.currents, lost, self._i_wheel)
        if lost:                            # RECONFIGURED: a lone wheel carries its carrier's whole command
            m = max(abs(i) for i in cy.currents.values())
            if m > self.max_abs_reconfigured_wheel:
                self.max_abs_reconfigured_wheel = m
        return fault

    def _account(self, t0: float, k: int, t: float, t_done: float) -> int:
        """Time this cycle; the next release index (missed periods are skipped, not caught up)."""
        missed, k_next = next_release(t0, k, self.h, t_done)
        self.stats.update(self.cycle.lateness, t_done - t, missed, k_next - k - 1)
        return k_next

    def _finished(self, t: float) -> bool:
        sup = self.supervisor
        st = sup.state
        if st is State.FAULT:
            return self.stop_requested if self._hold else t >= self._t_fault_end
        return st is State.IDLE and not sup.arming and (sup.ever_armed or sup.arm_failed or self.stop_requested)

    def _safe_off(self) -> None:
        """Zero current on the wire and power stages off; never raises."""
        t = self.clock.now()
        currents = self.cycle.currents
        for w in currents:
            currents[w] = 0.0
        try:
            self.dev.write(self.cycle.currents, t)
        except Exception:
            pass
        try:
            self.dev.deactivate(t)
        except Exception:
            pass
