"""The supervisor: the state machine (it owns every transition), latched faults and the
per-cycle check sequence.

States ``IDLE → ARMED → RUNNING → STOPPING → IDLE``, and ``FAULT`` (latched) from anywhere
until an explicit ``reset``. The ARM transition is the only place that activates the
power stages (``hardware.activate``); FAULT and the end of STOPPING deactivate them. On a
fault the output is zero in the same cycle. Limits come from the frozen config and cannot
be loosened.

Every rule is judged here and only here (``safety.rules``; drivers report what they
observed). The check sequence per cycle: the system rules, the channel rules (each applied
to every sensor channel before the next rule), the pose rules, the speed rules, then the
observer rules (not while a channel rule is gathering evidence on one of the carrier's
sensors: a channel rule that sees the fault names it first). The first finding trips the
fault — except, with ``degraded.on_lateral_loss: observe`` while RUNNING, a lost lateral
laser (an arm rule's breach) or one the lateral innovation rule finds disagreeing: it is
isolated (``safety.reconfig``) and the carriers it feeds run DEGRADED on the observer's ŷ
(docs/observer.md), and the remaining channels are judged afresh from the first rule; while
DEGRADED, ``max_s`` is a fault and the degraded stop rules end the run in the normal clean
stop. Likewise, with ``degraded.on_drive_loss: reallocate`` while RUNNING, a lost drive (what
it reported of itself, its SYNCs left unanswered, or no torque response) is isolated and its
carrier runs RECONFIGURED on its remaining wheels — where the outage table
(``rig_runtime.reconfig_analysis``) finds the loop stable at the measured speed; else the
fault, naming the analysis' answer (docs/safety.md, "Drive outages").
:meth:`Supervisor.limit` judges each lane's command (the output rules) and shapes it
(``safety.limiter``). Arming asks the arm rules whether every channel is fit.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Mapping, Optional, Sequence

from ..config import Limits
from ..hardware import Hardware
from .limiter import Limiter
from .reconfig import Reconfiguration
from ..allocation import allocate
from .rules import (ARM_RULES, CHANNEL_RULES, DEGRADED_STOP_RULES, DRIVE_LOSS_RULES, ISOLATING_RULES,
                    OBSERVER_RULES, OUTPUT_RULES, POSE_RULES, SPEED_RULES, SYSTEM_RULES, System, bus_error,
                    converter, torque_response)
from .types import Channel, Converters, Fault, Finding, Pose, Sample, State, Step


class Supervisor:
    """Owns the states and checks every cycle. ``on_event(t, kind, fault_or_None, text)``
    receives state changes, faults and operator actions (the recorder's event table).

    Per cycle the loop calls :meth:`cycle` (observe, transitions, checks; returns a
    :class:`Step`), then :meth:`limit` for each carrier it drives, then :meth:`end_cycle`
    (returns the fault latched in this cycle, if any). ``carriers``: the carriers whose
    output :meth:`limit` shapes (the lanes')."""

    def __init__(self, limits: Limits, h: float, channels: Sequence[Channel], carriers: Sequence[str],
                 hardware: Hardware, on_event: Callable | None = None, activate_timeout_s: float = 0.5,
                 observers: Sequence = (), degraded=None, v_max: float = math.inf, outages=None,
                 v_fixed: float = math.nan):
        self._limits = limits           # frozen, and not replaceable: see the property
        self.v_max = v_max              # the hardware's ceiling on |v̂| (speed_range)
        self._speed = None              # this cycle's measured speed (rig_runtime.speed), if given
        self.h = h
        self.channels = list(channels)
        for c in self.channels:
            c.periods(h)
        self._by_name = {c.name: c for c in self.channels}
        self._groups: dict[tuple, tuple[Channel, ...]] = {}      # names -> their channels (fit)
        self.observers = tuple(observers)      # the lanes' observers (rig_runtime.observer.Observer)
        # degraded mode (config.Degraded; docs/observer.md): only with on_lateral_loss "observe"
        self._deg = degraded if (degraded is not None and degraded.on_lateral_loss == "observe"
                                 and self.observers) else None
        # the degraded limits, capped at the limits (never looser)
        self._deg_limits = (dataclasses.replace(limits, u_max=min(degraded.limits.u_max, limits.u_max),
                                                y_max=min(degraded.limits.y_max, limits.y_max))
                            if self._deg is not None else limits)
        self._obs_of = {o.d.carrier: o for o in self.observers}
        # lateral laser -> the carriers whose y it feeds (only those with an observer absorb it)
        feeds: dict[str, list[str]] = {}
        for o in self.observers:
            for n in o.d.lateral_lasers:
                feeds.setdefault(n, []).append(o.d.carrier)
        self.lasers = Reconfiguration("DEGRADED", feeds if self._deg is not None else {}, device_key="laser")
        self._deg_stop: str = ""                             # why degraded mode asked for the clean stop
        # drive outages (RECONFIGURED): with degraded.on_drive_loss "reallocate" and the outage
        # table (rig_runtime.reconfig_analysis.OutageTable) of this config
        self._outages = outages if (outages is not None and degraded is not None
                                    and degraded.on_drive_loss == "reallocate") else None
        wfeeds = ({w: (c,) for c in carriers if c in self._outages.controlled for w in self._outages.wheels_of(c)}
                  if self._outages is not None else {})
        self.drives = Reconfiguration("RECONFIGURED", wfeeds, device_key="device")
        self._reconf_limits: dict[str, Limits] = {}          # carrier -> its limits while RECONFIGURED
        self._deg_cfg = degraded
        self._v_fixed = v_fixed                              # the speed when none is measured (plant.v)
        self._why_not = ""                                   # the outage analysis' answer when it said no
        # the torque response: each wheel's latest commands (newest first) and the cycles in a
        # row its reported torque has been off all of them; the largest healthy residual seen
        self._cmds: dict[str, list[float]] = {w: [0.0, 0.0, 0.0] for w in self.drives.feeds}
        # (carrier, left, right, their current limit, their command histories), once
        tb = self._outages
        self._pairs = [(c, *tb.wheels_of(c), min(tb.i_max.get(w, math.inf) for w in tb.wheels_of(c)),
                        *(self._cmds[w] for w in tb.wheels_of(c)))
                       for c in carriers if tb is not None and c in tb.controlled]
        self._torque_run: dict[str, int] = dict.fromkeys(self.drives.feeds, 0)
        self.torque_residual_max: dict[str, float] = dict.fromkeys(self.drives.feeds, 0.0)
        self._lim_of: dict[str, Limits] = {}                 # carrier -> the limits it runs under now
        self.carriers = tuple(carriers)
        self.hw = hardware
        self.activate_timeout_s = activate_timeout_s
        self.state = State.IDLE
        self.fault: Fault | None = None
        self.faults: list[Fault] = []
        self.arm_blockers: list[str] = []
        self.arm_failed = False         # the arm deadline passed with blockers left
        self.ever_armed = False
        self._arm_deadline: float | None = None     # an arm request is pending until then
        self._armed_t = 0.0
        self._stop_reason: str | None = None
        self._out = Limiter(limits, h, self.carriers)
        # what a cycle fills in place (nothing allocated per cycle): each carrier's pose (its ψ
        # of the last cycle it was measured gives ψ̇) and what the system rules look at
        self._poses: dict[str, Pose] = {}
        self._system = System(0.0, h, 0, True, "", Converters(True, "", False), False, self.drives.isolated)
        self._latched: Fault | None = None          # the fault latched in the cycle under way
        self._started = False
        self._on_event = on_event or (lambda *a: None)

    # the degraded mode's bookkeeping, by the names the loop and the summary read
    @property
    def isolated(self):
        """Lateral laser -> its isolation (since, agreeing cycles, readmittable)."""
        return self.lasers.isolated

    @property
    def degraded_since(self) -> dict[str, float]:
        """Carrier -> DEGRADED since t."""
        return self.lasers.since

    @property
    def degraded_log(self) -> list[dict]:
        """The DEGRADED intervals, for the summary."""
        return self.lasers.log

    @property
    def wheels_lost(self):
        """The wheels whose drive the run does without (RECONFIGURED; allocated 0 A)."""
        return self.drives.isolated

    @property
    def reconfigured_log(self) -> list[dict]:
        """The RECONFIGURED intervals, for the summary (device, carrier, t_start, t_end, end)."""
        return self.drives.log

    @property
    def degraded_limits(self) -> Limits:
        """The limits a DEGRADED carrier runs under (the limits when degraded mode is off)."""
        return self._deg_limits

    @property
    def limits(self) -> Limits:
        """The limits given at construction: a frozen value the supervisor cannot be handed
        another of while it exists (the rate and ramp steps are derived from it once)."""
        return self._limits

    # ------------------------------------------------------------------ requests
    def request_arm(self, deadline: float) -> None:
        """Arm as soon as every channel is fit (and the converters are ok), until ``deadline``."""
        if self.state is State.IDLE:
            self._arm_deadline = deadline

    def request_stop(self, t: float, reason: str = "stop requested") -> None:
        """A clean stop: ARMED/RUNNING ramp down (STOPPING, at the next cycle), IDLE stops arming."""
        if self.state in (State.ARMED, State.RUNNING) and self._stop_reason is None:
            self._stop_reason = reason
        self._arm_deadline = None

    def reset(self, t: float) -> None:
        """Explicit operator reset of a latched fault."""
        if self.state is State.FAULT:
            self._on_event(t, "operator", None, "fault reset")
            self.fault = None
            self._stop_reason = None
            self._out.reset()
            self._to(State.IDLE, t)
            self.hw.resume(t)                   # communication on, power off: ready to arm again

    @property
    def arming(self) -> bool:
        """An arm request is pending (IDLE, waiting for every channel to be fit)."""
        return self._arm_deadline is not None

    @property
    def active(self) -> bool:
        return self.state in (State.ARMED, State.RUNNING, State.STOPPING)

    # ------------------------------------------------------------------ transitions
    def _to(self, new: State, t: float, text: str = "") -> None:
        if new is self.state:
            return
        old, self.state = self.state, new
        self._on_event(t, "state", None, f"{old.name} -> {new.name}" + (f": {text}" if text else ""))
        if new is State.ARMED:
            self.ever_armed = True
            self._armed_t = t
            self.hw.activate(t)                 # power stages on: here and nowhere else
        elif new is State.RUNNING:
            self._started = True
        elif new is State.FAULT or (new is State.IDLE and old is State.STOPPING):
            self.hw.deactivate(t)
        if new in (State.FAULT, State.IDLE) and self.lasers.since:     # the run ends DEGRADED
            self.lasers.close(t, new.name + (f" ({self._deg_stop})" if self._deg_stop and new is State.IDLE else ""))
        if new in (State.FAULT, State.IDLE) and self.drives.since:     # the run ends RECONFIGURED
            self.drives.close(t, new.name)
            self._reconf_limits.clear()
        if new in (State.FAULT, State.IDLE):
            self._update_limits()
        if new in (State.FAULT, State.IDLE):
            self._deg_stop = ""

    def trip(self, t: float, f: Finding) -> None:
        """Latch the fault of a finding (the first one of a cycle is the cause recorded; a
        drive outage the analysis would not reconfigure says why)."""
        if self.state is State.FAULT:
            return
        if self._why_not:
            f = dataclasses.replace(f, message=f.message + self._why_not)
        fault = Fault.of(t, f)
        self.fault = fault
        self.faults.append(fault)
        self._latched = fault
        self._on_event(t, "fault", fault, fault.message)
        self._to(State.FAULT, t, f"{f.device} {f.check}")

    def _blockers(self, t: float, conv: Converters, misses: int) -> list[str]:
        why = []
        if misses:      # warm-up still missing deadlines (first drains, imports)
            why.append(f"loop: {misses} periods lost to deadline misses")
        lim = self._limits
        for c in self.channels:
            for rule in ARM_RULES:
                f = rule((c,), t, lim)
                if f is not None:
                    why.append(f"{c.name}: {f.message}")
                    break
        if not conv.ok:
            why.append(f"converters: {conv.cause}")
        elif (f := bus_error(System(t, self.h, misses, True, "", conv, False), lim)) is not None:
            why.append(f"converters: {f.message}")
        return why

    def _transitions(self, t: float, conv: Converters, misses: int) -> None:
        st = self.state
        if st is State.IDLE:
            if self._arm_deadline is not None:      # an arm request is pending
                self.arm_blockers = self._blockers(t, conv, misses)
                if not self.arm_blockers:
                    self._arm_deadline = None
                    self._to(State.ARMED, t)
                elif t >= self._arm_deadline:
                    self._arm_deadline = None
                    self.arm_failed = True
        elif self._stop_reason is not None and st in (State.ARMED, State.RUNNING):
            reason, self._stop_reason = self._stop_reason, None
            self._on_event(t, "operator", None, reason)
            self._to(State.STOPPING, t, reason)
        elif st is State.ARMED:
            if conv.enabled:
                self._to(State.RUNNING, t)
            elif t - self._armed_t > self.activate_timeout_s:
                self.trip(t, Finding("converters", "activate", t - self._armed_t, self.activate_timeout_s,
                                     "power stages not OPERATION ENABLED in time"
                                     + (f" ({conv.cause})" if conv.cause else "")))

    # ------------------------------------------------------------------ per cycle
    def cycle(self, t: float, samples: Mapping[str, Sample], conv: Converters, poses: Sequence[tuple[str, float, float]],
              consecutive_misses: int, recorder_ok: bool, recorder_cause: str, speed=None) -> Step:
        """Observe this cycle's samples (by channel name), make the transitions that are due,
        and (while ARMED/RUNNING/STOPPING) apply every rule in order. ``poses``: (carrier,
        y, ψ) of each controlled carrier; ``speed``: the measured roller speed (judged by
        the speed rules after the pose rules; None: not judged)."""
        self._latched = None
        self._why_not = ""
        self._speed = speed
        self._started = False
        h = self.h
        for c in self.channels:
            c.observe(samples[c.name], t, h)
        slots = self._poses
        pose_list = []
        for carrier, y, psi in poses:
            p = slots.get(carrier)
            if p is None:                   # its first measurement: no ψ̇ yet
                p = slots[carrier] = Pose(carrier, y, psi, 0.0)
            else:
                p.psi_rate = (psi - p.psi) / h
                p.y, p.psi = y, psi
            pose_list.append(p)
        self._transitions(t, conv, consecutive_misses)
        st = self.state
        if self.active:
            system = self._system
            system.t, system.misses, system.conv = t, consecutive_misses, conv
            system.recorder_ok, system.recorder_cause = recorder_ok, recorder_cause
            system.running, system.lost = st is State.RUNNING, self.drives.isolated
            f = self._check(t, system, pose_list)
            if f is not None:
                self.trip(t, f)
        return Step(self.state, self._started)

    def _check(self, t: float, system: System, poses: Sequence[Pose]) -> Optional[Finding]:
        """The check sequence; returns the finding that trips (None: none)."""
        lim = self._limits
        conv = system.conv
        absorb = bool(conv.drives) and self._outages is not None     # what a drive said of itself
        for rule in SYSTEM_RULES:       # root causes first: a starved loop makes the watchdogs trip too
            if absorb and rule is converter:
                self._absorb_drives(t, conv)        # reconfigure?
            f = rule(system, lim)
            if f is not None:
                return f
        f = self._channels(t)
        if f is not None:
            return f
        if self._outages is not None and system.conv.torque and self.state is State.RUNNING:
            f = self._torque(t, system.conv)
            if f is not None:
                return f
        if self.lasers.isolated:
            f = self._degraded_checks(t, poses)
            if f is not None:
                return f
            since = self.lasers.since
            poses = [Pose(p.carrier, self._obs_of[p.carrier].y, p.psi, p.psi_rate)
                     if p.carrier in since else p for p in poses]
        lim_of = self._lim_of
        for rule in POSE_RULES:
            for p in poses:
                f = rule(p, lim_of.get(p.carrier, lim))
                if f is not None:
                    return f
        if self._speed is not None:
            for rule in SPEED_RULES:
                f = rule(self._speed, lim, self.v_max)
                if f is not None:
                    return f
        for rule in OBSERVER_RULES:
            for o in self.observers:
                # a rule that holds has nothing to wait for: the channel evidence (the rules are
                # pure) is asked only of a finding — while a channel rule gathers evidence on one
                # of the carrier's sensors the observer rules wait
                f = rule(o, lim)
                if f is not None and not self._channel_evidence(o.d.channels):
                    iso = ISOLATING_RULES.get(rule)
                    if iso is None or not self._degrade(t, tuple(iso(o)), f, readmit=False):
                        return f
        return None

    def _channels(self, t: float) -> Optional[Finding]:
        """The channel rules, each on every channel not isolated before the next. A lost
        lateral laser (an arm rule's breach, not a lying one: stuck, jumping, garbling) that
        degraded mode absorbs is isolated, and the remaining channels are judged afresh from
        the first rule — a second laser breaching the same rule is caught in this cycle."""
        lim = self._limits
        iso, lost = self.lasers.isolated, self.drives.isolated
        chs = ([c for c in self.channels if c.name not in iso and c.name not in lost] if iso or lost
               else self.channels)
        rules = CHANNEL_RULES
        n = len(rules)
        k = 0
        while k < n:
            rule = rules[k]
            f = rule(chs, t, lim)
            if f is None:
                k += 1
                continue
            # a lost channel (an arm rule's breach), not a lying one: a lateral laser degrades
            # its carriers; a drive that says it is broken (invalid) or went silent (stale)
            # reconfigures its carrier — a wheel speed out of range is a fault, never absorbed
            if rule not in ARM_RULES or not (self._degrade(t, (f.device,), f, readmit=True)
                                             or (rule in DRIVE_LOSS_RULES and self._reconfigure(t, f.device, f))):
                return f
            chs = [c for c in chs if c.name not in iso and c.name not in lost]     # judge the rest afresh
            k = 0
        return None

    # ------------------------------------------------------------------ degraded mode
    def _degrade(self, t: float, lasers: Sequence[str], f: Finding, readmit: bool) -> bool:
        """Lateral lasers of an observed carrier lost (an arm rule's breach: invalid, stale,
        not finite, out of range; ``readmit``) or found lying by the innovation test (not
        readmitted: a creeping laser does not come back by itself), while RUNNING with
        ``degraded.on_lateral_loss: observe``: isolate them and run every carrier whose y
        they feed on its observer's ŷ (DEGRADED) instead of tripping. False: a fault as usual."""
        if self._deg is None or self.state is not State.RUNNING:
            return False
        carriers = self.lasers.isolate(t, lasers, f.check, readmit)
        if not carriers:
            return False
        self._update_limits()
        name = "/".join(lasers)
        dl = self._deg_limits
        self._on_event(t, "degraded", None,
                       f"DEGRADED: {name} {f.check} ({f.message}); {'/'.join(carriers)} carrier(s) on the "
                       f"observer's estimate, u_max {dl.u_max:g} A, y_max {dl.y_max * 1e3:g} mm, at most "
                       f"{self._deg.max_s:g} s" + ("" if readmit else "; not readmitted in this run"))
        return True

    def _degraded_checks(self, t: float, poses: Sequence[Pose]) -> Optional[Finding]:
        """While DEGRADED: ``max_s`` (a finding: the fault), the degraded stop rules (the
        estimate's covariance: the normal clean stop, asked once), and the readmission of each
        readmittable isolated laser that is fit again and whose carriers' measured y agrees
        with ŷ within ``readmit_tol_m`` for ``readmit_s`` without a break."""
        deg = self._deg
        lasers = self.lasers
        for car, since in lasers.since.items():
            if t - since > deg.max_s:
                names = "/".join(n for n in self._obs_of[car].d.lateral_lasers if n in lasers.isolated)
                return Finding(names, "degraded", t - since, deg.max_s,
                               f"{car} carrier DEGRADED (lateral laser {names} isolated) for longer than "
                               f"degraded.max_s = {deg.max_s:g} s")
        if not self._deg_stop and self.state is State.RUNNING:
            for rule in DEGRADED_STOP_RULES:
                for car in lasers.since:
                    f = rule(self._obs_of[car], deg)
                    if f is not None:
                        self._deg_stop = f"{f.check} {f.value * 1e3:.4f} mm > {f.limit * 1e3:g} mm"
                        self._on_event(t, "degraded", None, f"DEGRADED ends: {f.message}: clean stop")
                        self.request_stop(t, f"degraded mode ended: {f.message}")
                        break
                if self._deg_stop:
                    break
        y_meas = {p.carrier: p.y for p in poses}
        lim = self._limits

        def fit(name: str) -> bool:     # fit again, and the measured y agrees with ŷ
            c = (self._by_name[name],)
            if not all(rule(c, t, lim) is None for rule in CHANNEL_RULES):
                return False
            return all(abs(y_meas.get(car, math.nan) - self._obs_of[car].y) <= deg.readmit_tol_m
                       for car in lasers.feeds.get(name, ()))

        for name, ended in lasers.readmit(t, max(1, round(deg.readmit_s / self.h)), fit):
            self._on_event(t, "degraded", None, f"{name} readmitted: fit and within "
                           f"{deg.readmit_tol_m * 1e3:g} mm of the estimate for {deg.readmit_s:g} s")
            for car in ended:
                self._on_event(t, "degraded", None, f"{car} carrier: DEGRADED ended")
            self._update_limits()
        return None

    # ------------------------------------------------------------------ drive outages
    def _absorb_drives(self, t: float, conv: Converters) -> None:
        """Each INVALID drive (what it said of itself: fault, EMCY, heartbeat) not lost yet:
        reconfigure its carrier if the outage analysis allows (else the converter rule trips)."""
        lost = self.drives.isolated
        for w, cause in conv.drives:
            if w not in lost:
                if not self._reconfigure(t, w, Finding("converters", "converter", math.nan, math.nan, cause)):
                    return

    def _reconfigure(self, t: float, wheel: str, f: Finding) -> bool:
        """A drive lost while RUNNING with ``degraded.on_drive_loss: reallocate``: if the
        outage table says the loop with this wheel (and any lost before) gone is stable at the
        measured speed, isolate it — 0 A from this cycle (the allocation), never readmitted in
        this run — and run its carrier RECONFIGURED under the tighter limits. False: a fault
        as usual (the finding's message then names the analysis' answer)."""
        tb = self._outages
        if tb is None or self.state is not State.RUNNING or wheel not in self.drives.feeds:
            return False
        lost = set(self.drives.isolated) | {wheel}
        v = self._speed.v_hat if self._speed is not None else self._v_fixed
        d = tb.decide(lost, v)
        if not d.stable:
            self._why_not = f"; not reconfigured: {d.why}"
            return False
        car = tb.carrier_of(wheel)
        left, right = tb.wheels_of(car)
        keep = [x for x in (left, right) if x not in lost]
        auth = len(keep) * min((tb.i_max.get(x, math.inf) for x in keep), default=0.0)   # the wheels' authority
        deg = self._deg_cfg.limits
        lim = self._limits
        self._reconf_limits[car] = dataclasses.replace(lim, u_max=min(lim.u_max, deg.u_max, auth),
                                                        y_max=min(lim.y_max, deg.y_max))
        self.drives.isolate(t, (wheel,), f.check, readmit=False)
        self.hw.isolate(wheel, t)               # that drive quick-stopped and disabled
        self._update_limits()
        rl = self._reconf_limits[car]
        on = f"on {'/'.join(keep)} alone" if keep else "uncontrolled (both wheels lost)"
        self._on_event(t, "reconfigured", None,
                       f"RECONFIGURED: drive {wheel} lost ({f.message}); {car} carrier {on}, u_max {rl.u_max:g} A, "
                       f"y_max {rl.y_max * 1e3:g} mm ({d.why})")
        return True

    def _torque(self, t: float, conv: Converters) -> Optional[Finding]:
        """The torque response rule on each drive not lost; a finding reconfigures the wheel's
        carrier where the analysis allows (else it is the fault)."""
        deg, lost = self._deg_cfg, self.drives.isolated
        thr = deg.torque_residual_A
        cmds_of, runs, worst, h = self._cmds, self._torque_run, self.torque_residual_max, self.h
        for w, actual in conv.torque:
            cmds = cmds_of.get(w)
            if cmds is None or w in lost:
                continue
            c0, c1, c2 = cmds
            if min(abs(c0), abs(c1), abs(c2)) < thr:
                runs[w] = 0             # commands too small to judge: the rule has nothing to judge
                continue
            r = min(abs(c0 - actual), abs(c1 - actual), abs(c2 - actual))
            if r > worst[w]:
                worst[w] = r            # the largest judged residual (healthy runs: the margin)
            if not r > thr:
                runs[w] = 0             # on one of its commands: no run for the rule to judge
                continue
            run = runs[w] = runs[w] + 1
            f = torque_response(w, run, r, c0, actual, deg, h)
            if f is not None and not self._reconfigure(t, w, f):
                return f
        return None

    def _commanded(self) -> None:
        """Each wheel's command of this cycle (the allocation of the limited outputs), for the
        torque response rule of the next cycles."""
        lost, u = self.drives.isolated, self._out.last
        for car, left, right, i_max, cl, cr in self._pairs:
            il, ir = allocate(u(car), left not in lost, right not in lost, i_max)
            cl[2], cl[1], cl[0] = cl[1], cl[0], il
            cr[2], cr[1], cr[0] = cr[1], cr[0], ir

    def _update_limits(self) -> None:
        """The limits each carrier runs under now: DEGRADED and RECONFIGURED each tighten them
        (the tighter of both when both hold)."""
        lim = self._limits
        out = {}
        for car in set(self.lasers.since) | set(self._reconf_limits):
            a = self._deg_limits if car in self.lasers.since else lim
            b = self._reconf_limits.get(car, lim)
            out[car] = dataclasses.replace(lim, u_max=min(a.u_max, b.u_max), y_max=min(a.y_max, b.y_max))
        self._lim_of = out

    def isolated_any(self, names: Sequence[str]) -> bool:
        """One of the named lateral lasers is isolated (not to be used by the observer)."""
        return self.lasers.isolated_any(names)

    def _channel_evidence(self, names: Sequence[str]) -> bool:
        """A channel rule is gathering evidence on one of the named channels: it has repeated
        its value (``stuck``) or brought garbled data (``corrupt_link``) in its latest
        cycles. The observer rules wait then — a stuck yaw laser disagrees with the model
        long before ``stuck_periods`` have passed, and the channel rule names the sensor
        itself, where the innovation test can only name the measurement (and, for a yaw
        laser frozen on a moving carrier, first sees the lateral lasers disagree). A
        healthy, quantised laser repeats a value for a cycle or two now and then: the rule
        then waits that long."""
        by = self._by_name
        iso = self.lasers.isolated
        for n in names:
            c = by.get(n)
            if c is not None and n not in iso and (c.same > 0 or c.bad_run > 0):
                return True
        return False

    def fit(self, names: Sequence[str], t: float) -> bool:
        """Every named channel fit for use this cycle: what arming asks of a channel (a
        fresh, finite, in-range sample; ``ARM_RULES``). The observer's lateral update uses a
        laser only then. Each rule is asked once of the named channels together (the names
        resolved to channels once per set of names)."""
        if type(names) is not tuple:
            names = tuple(names)
        chs = self._groups.get(names)
        if chs is None:
            chs = self._groups[names] = tuple(self._by_name[n] for n in names)
        lim = self._limits
        for rule in ARM_RULES:
            if rule(chs, t, lim) is not None:
                return False
        return True

    # ------------------------------------------------------------------ output limit
    def limit(self, carrier: str, u: float, t: float) -> float:
        """The current actually sent for ``carrier``: 0 unless RUNNING/STOPPING; checked by
        the output rules, saturated at ±u_max and rate limited while RUNNING; ramped to zero
        while STOPPING (``end_cycle`` then moves to IDLE once every output is zero)."""
        st = self.state
        if st is State.RUNNING:
            lim = self._limits
            for rule in OUTPUT_RULES:
                f = rule(carrier, u, lim)
                if f is not None:
                    self.trip(t, f)
                    return self._out.zero(carrier)
            lim_of = self._lim_of           # empty unless DEGRADED or RECONFIGURED
            return self._out.running(carrier, u, (lim_of.get(carrier, lim) if lim_of else lim).u_max)
        if st is State.STOPPING:
            return self._out.stopping(carrier)
        return self._out.zero(carrier)

    def end_cycle(self, t: float) -> Fault | None:
        """STOPPING ends (→ IDLE, power stages off) once every output has ramped to zero.
        Returns the fault latched in this cycle (None: none)."""
        if self.state is State.STOPPING and self._out.at_rest:
            self._to(State.IDLE, t, "stopped")
        if self._outages is not None:
            self._commanded()
        return self._latched
