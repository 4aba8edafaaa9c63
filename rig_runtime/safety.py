"""Safety supervisor: the state machine (it owns every transition), latched faults, the
per-cycle checks and the output limit.

States ``IDLE → ARMED → RUNNING → STOPPING → IDLE``, and ``FAULT`` (latched) from anywhere
until an explicit ``reset``. The ARM transition is the only place that activates the
power stages (``hardware.activate``); FAULT and the end of STOPPING deactivate them. On a
fault the output is zero in the same cycle. Limits come from the frozen config and cannot
be loosened.

Every rule is judged here and only here: drivers report what they observed (the latest
valid value and when it arrived, what the device said, protocol events with counts, the
SYNCs a drive left unanswered); freshness, range, stuck, jump and corruption are decided by
the rules below, each with one setting in ``limits:``. The checks are ordered lists of small
named rules (no second copy of any of them): the system rules (loop overruns, recorder,
converters, a recent bus error), the channel rules (each applied to every sensor channel
before the next rule), then the pose rules (each applied to every controlled carrier before
the next rule), then the observer rules (each applied to every observed carrier, on the
statistics of its latest estimate, and not while a channel rule is gathering evidence on one
of the carrier's sensors: a channel rule that sees the fault names it first). The first rule
that fails in a cycle trips the fault — except, with ``degraded.on_lateral_loss: observe``
while RUNNING, a lost lateral laser (an arm rule's breach) or one the lateral innovation rule
finds disagreeing: those are isolated and the carriers they feed run DEGRADED on the
observer's ŷ (docs/observer.md); while DEGRADED, ``max_s`` is a fault and the degraded stop
rules (the estimate's covariance) end the run in the normal clean stop. The output rules check each lane's command in
:meth:`Supervisor.limit`. Arming asks the same channel rules whether every channel is fit.
"""

from __future__ import annotations

import dataclasses

import enum
import math
from dataclasses import dataclass
from typing import Callable, Mapping, NamedTuple, Optional, Sequence

from .config import Limits
from .hardware import Freshness, Hardware, Health

_NEVER = 1 << 62         # a count limit that is switched off


class State(enum.IntEnum):
    IDLE = 0
    ARMED = 1
    RUNNING = 2
    STOPPING = 3
    FAULT = 4


@dataclass(frozen=True, slots=True)
class Fault:
    t: float
    device: str
    check: str
    value: float
    limit: float
    message: str = ""

    def as_dict(self) -> dict:
        def num(x: float):
            return x if math.isfinite(x) else None
        return {"t": self.t, "device": self.device, "check": self.check,
                "value": num(self.value), "limit": num(self.limit), "message": self.message}


class Sample(NamedTuple):
    """One channel's reading in a cycle: value, the time it arrived (NaN: never), health,
    and for a device that answers the runtime's requests (a SYNC-triggered TPDO) how many
    requests are unanswered (-1: a free-running device, judged by the age of its value)."""
    value: float
    t: float
    health: Health
    unanswered: int = -1


class Converters(NamedTuple):
    """The converters as a cycle sees them: ``ok`` (no drive or bus INVALID, else ``cause``),
    ``enabled`` (every power stage OPERATION ENABLED), when the bus last reported an error
    (send or receive failure, error frame; -inf: never) and what it was."""
    ok: bool
    cause: str
    enabled: bool
    bus_error_t: float = -math.inf
    bus_cause: str = ""


def bus_error(conv: Converters, t: float, lim: Limits, h: float) -> Finding:
    """A bus error within the staleness window: frames may have been lost in it."""
    window = lim.stale_periods * h
    if t - conv.bus_error_t <= window:
        return ("converter", t - conv.bus_error_t, window,
                f"CAN bus: {conv.bus_cause} ({(t - conv.bus_error_t) * 1e3:.0f} ms ago)")
    return None


class Channel:
    """One sensor channel as the supervisor sees it: its limits, and its history (updated
    in place every cycle by :meth:`Supervisor.cycle`)."""

    __slots__ = ("name", "kind", "value", "t", "state", "cause", "lo", "hi", "stale_s",
                 "step_max", "stuck_check", "same", "delta", "bad", "bad_run", "unanswered", "bad_at_value")

    def __init__(self, name: str, kind: str, lo: float, hi: float, stale_s: float,
                 step_max: float = math.inf, stuck_check: bool = False):
        self.name, self.kind, self.lo, self.hi, self.stale_s = name, kind, lo, hi, stale_s
        self.step_max = step_max          # largest plausible change between two cycles
        self.stuck_check = stuck_check    # a sensor with noise never repeats bit-identically for long
        self.value = math.nan
        self.t = -math.inf
        self.state = Freshness.STALE
        self.cause = "no sample yet"
        self.same = 0
        self.delta = 0.0
        self.bad = 0            # the driver's cumulative count of garbled frames / bytes
        self.bad_run = 0        # consecutive cycles with new garbled data
        self.unanswered = -1    # requests unanswered (-1: free-running, judged by age)
        self.bad_at_value = 0   # the garbled count when the latest valid value arrived

    def observe(self, s: Sample) -> None:
        """This cycle's sample, and the history the rules look at."""
        v = s.value
        h = s.health
        prev = self.value
        self.delta = v - prev
        self.value = v
        t = -math.inf if math.isnan(s.t) else s.t      # NaN: no valid value ever
        if t != self.t:
            self.bad_at_value = h.bad_frames      # a new valid value: garbled frames counted from here
        self.t = t
        self.state = h.state
        self.cause = h.cause
        self.unanswered = s.unanswered
        if self.stuck_check:
            self.same = self.same + 1 if v == prev else 0
        b = h.bad_frames
        self.bad_run = self.bad_run + 1 if b > self.bad else 0
        self.bad = b


Finding = Optional[tuple]   # (check, value, limit, message) or None: the rule holds


# ---------------------------------------------------------------------- channel rules
# A channel rule takes the channels and returns the first one that breaks it, with the
# finding, or None. (Each rule loops over the channels itself: one call per rule and cycle.)
Breach = Optional[tuple]    # (channel, (check, value, limit, message)) or None


def invalid(chs: Sequence[Channel], t: float, lim: Limits) -> Breach:
    for c in chs:
        if c.state is Freshness.INVALID:
            return c, ("invalid", c.value, math.nan, c.cause)
    return None


def _garbled(c: Channel) -> str:
    n = c.bad - c.bad_at_value
    return f": {n} garbled frames in that time" if n > 0 else ""


def stale(chs: Sequence[Channel], t: float, lim: Limits) -> Breach:
    """No valid value in time. A free-running device is judged by the age of its latest
    valid value; a device that answers the runtime's requests (a SYNC-triggered TPDO) by
    the requests it left unanswered — the runtime's own lateness is not the device's fault.
    The finding names what was observed instead: garbled frames in that time make it a
    corrupted link (``corrupt``), not a silent device."""
    n = lim.stale_periods
    for c in chs:
        if c.unanswered >= 0:
            if c.unanswered >= n or c.t == -math.inf:
                what = "no valid value yet" if c.t == -math.inf else "no valid value"
                g = _garbled(c)
                return c, ("corrupt" if g else "stale", c.unanswered, n,
                           f"{what} for {c.unanswered} requests sent{g}")
            continue
        age = t - c.t
        if age > c.stale_s:
            g = _garbled(c)
            what = "no valid value yet" if c.t == -math.inf else f"no valid value for {age * 1e3:.0f} ms"
            return c, ("corrupt" if g else "stale", age, c.stale_s, what + g)
    return None


def not_finite(chs: Sequence[Channel], t: float, lim: Limits) -> Breach:
    for c in chs:
        v = c.value
        if not math.isfinite(v):
            return c, ("nan", v, math.nan, "value is not finite")
    return None


def out_of_range(chs: Sequence[Channel], t: float, lim: Limits) -> Breach:
    for c in chs:
        v = c.value
        if v < c.lo or v > c.hi:
            return c, ("range", v, c.hi if v > c.hi else c.lo, "raw value outside the sensor range")
    return None


def corrupt_link(chs: Sequence[Channel], t: float, lim: Limits) -> Breach:
    n = lim.corrupt_cycles or _NEVER
    for c in chs:
        if c.bad_run >= n:
            return c, ("corrupt", c.bad_run, n, f"garbled frames in {c.bad_run} consecutive cycles ({c.bad} in total)")
    return None


def stuck(chs: Sequence[Channel], t: float, lim: Limits) -> Breach:
    n = lim.stuck_periods or _NEVER
    for c in chs:
        if c.same >= n:
            return c, ("stuck", c.same, n, f"value repeated bit-identically for {c.same} cycles")
    return None


def jump(chs: Sequence[Channel], t: float, lim: Limits) -> Breach:
    for c in chs:
        if abs(c.delta) > c.step_max:
            return c, ("jump", c.delta, c.step_max, "implausible change between two cycles")
    return None


CHANNEL_RULES: tuple[Callable[[Sequence[Channel], float, Limits], Breach], ...] = (
    invalid, stale, not_finite, out_of_range, corrupt_link, stuck, jump)
# what arming needs of every channel: a fresh, finite, in-range sample
ARM_RULES = (invalid, stale, not_finite, out_of_range)


# ---------------------------------------------------------------------- pose rules
class Pose(NamedTuple):
    """One controlled carrier's state as measured this cycle."""
    carrier: str
    y: float
    psi: float
    psi_rate: float


_finite = math.isfinite


def pose_not_finite(p: Pose, lim: Limits) -> Finding:
    if not (_finite(p.psi) and _finite(p.y)):
        return "nan", math.nan, math.nan, f"{p.carrier} carrier: y or psi is not finite ({p.y!r}, {p.psi!r})"
    return None


def psi_limit(p: Pose, lim: Limits) -> Finding:
    if abs(p.psi) > lim.psi_max:
        return "psi_limit", p.psi, lim.psi_max, f"{p.carrier} carrier: yaw angle beyond limit"
    return None


def y_limit(p: Pose, lim: Limits) -> Finding:
    if abs(p.y) > lim.y_max:
        return "y_limit", p.y, lim.y_max, f"{p.carrier} carrier: lateral displacement beyond limit"
    return None


def psi_rate_limit(p: Pose, lim: Limits) -> Finding:
    if lim.psi_rate_max is not None and abs(p.psi_rate) > lim.psi_rate_max:
        return "psi_rate_limit", p.psi_rate, lim.psi_rate_max, f"{p.carrier} carrier: yaw rate beyond limit"
    return None


POSE_RULES = (pose_not_finite, psi_limit, y_limit, psi_rate_limit)


# ---------------------------------------------------------------------- output rules
def output_not_finite(carrier: str, u: float, lim: Limits) -> Finding:
    if not _finite(u):
        return "nan", u, math.nan, f"{carrier} carrier: controller output is not finite"
    return None


OUTPUT_RULES = (output_not_finite,)


# ---------------------------------------------------------------------- speed rules
# A speed rule takes the measured speed (rig_runtime.speed.SpeedEstimate: ``carriers``, their
# filtered speeds ``v`` and v̂ ``v_hat``, m/s), the limits and the hardware's v_max, and
# returns (device, check, value, limit, message) or None. Not finite (no encoder value yet):
# the channel rules judge the encoders themselves.
def speed_disagree(sp, lim: Limits, v_max: float) -> Optional[tuple]:
    """The carriers on the rollers run at one roller speed: encoders that disagree about it by
    more than ``limits.v_disagree_max`` are wrong (a slipping or miscounting encoder, an
    offset) — which of them the rule cannot tell; the finding names both carriers' values."""
    v = sp.v
    if len(v) < 2:
        return None
    lo = hi = v[0]
    for x in v:
        lo = x if x < lo else lo
        hi = x if x > hi else hi
    d = hi - lo
    if d > lim.v_disagree_max:
        each = ", ".join(f"{c} {x:+.3f} m/s" for c, x in zip(sp.carriers, v))
        return ("encoders", "speed_disagree", d, lim.v_disagree_max,
                f"the carriers' wheel encoders disagree about the roller speed by {d:.3f} m/s ({each})")
    return None


def speed_range(sp, lim: Limits, v_max: float) -> Optional[tuple]:
    """|v̂| above the hardware's ``ceilings.v_max``: beyond what the rollers can run."""
    v = sp.v_hat
    if abs(v) > v_max:
        return ("encoders", "speed_range", v, v_max,
                f"measured roller speed {v:+.3f} m/s beyond the hardware's v_max ({'/'.join(sp.carriers)} encoders)")
    return None


SPEED_RULES = (speed_disagree, speed_range)


# ---------------------------------------------------------------------- observer rules
# An observer rule takes one carrier's observer (rig_runtime.observer.Observer: its window
# statistics of the normalised innovations, as of the latest estimate) and returns
# (device, check, value, limit, message) or None.
def _joined(names: Sequence[str]) -> str:
    return "/".join(names)


def innovation_yaw(o, lim: Limits) -> Optional[tuple]:
    """Analytical redundancy (docs/observer.md): a measurement whose window-mean normalised
    innovation has χ²(1) ``T`` above ``limits.innovation_chi2`` disagrees with the model and
    the other sensors. The yaw lasers are tested first (every other measurement leans on ψ);
    the test cannot tell the two apart."""
    thr = lim.innovation_chi2
    if thr is None or not o.window_full or not o.T_psi > thr:
        return None
    d = o.d
    return (_joined(d.yaw_lasers), "innovation", o.T_psi, thr,
            f"{d.carrier} carrier: yaw lasers {_joined(d.yaw_lasers)} disagree with the model and the other "
            f"sensors (chi2 {o.T_psi:.1f} > {thr:g}); the test cannot tell the two apart")


def innovation_lateral(o, lim: Limits) -> Optional[tuple]:
    """The lateral y disagrees with (2b) driven by the measured ψ — the reference that does
    not follow a drifting laser. Judged only while the latest estimate used the lateral
    lasers (``lat_used``): an isolated or unfit laser brings no evidence, and the window it
    left behind must not find it again. With ``degraded.on_lateral_loss: observe`` the
    supervisor isolates the lasers on this finding instead of tripping."""
    thr = lim.innovation_chi2
    if thr is None or not o.window_full or not o.lat_used or not o.T_lat > thr:
        return None
    d = o.d
    L = d.lateral_lasers
    return (_joined(L), "innovation", o.T_lat, thr,
            f"{d.carrier} carrier: lateral lasers {_joined(L)} disagree with the model driven by psi "
            f"(window-mean innovation {o.mean_lat * 1e6:+.1f} um, chi2 {o.T_lat:.1f} > {thr:g}; "
            f"y weights {L[0]} {d.lateral_weights[0]:.2f}, {L[1]} {d.lateral_weights[1]:.2f})")


def innovation_dw(o, lim: Limits) -> Optional[tuple]:
    """Δω disagrees with the estimate, which follows the precise lateral lasers: the
    carrier's lateral lasers or its encoders — which of them the test cannot tell, and the
    finding says so (never a degradation: the observer cannot vouch for Δω, which carries
    ŷ without the lateral lasers)."""
    thr = lim.innovation_chi2
    if thr is None or not o.window_full or not o.T_dw > thr:
        return None
    d = o.d
    L, enc = d.lateral_lasers, d.encoders
    gy = d.dw_row[0]
    return (f"{L[0]}|{_joined(enc)}", "innovation", o.T_dw, thr,
            f"{d.carrier} carrier: {L[0]} (y weight {d.lateral_weights[0]:.2f}; {L[1]} {d.lateral_weights[1]:.2f}) "
            f"and the encoders {_joined(enc)} disagree by {o.mean_dw * 1e3:+.2f} mrad/s of dw "
            f"(= {o.mean_dw / gy * 1e3:+.3f} mm of y; chi2 {o.T_dw:.1f} > {thr:g}): the innovation "
            "test cannot tell the lateral laser from the encoders")


OBSERVER_RULES = (innovation_yaw, innovation_lateral, innovation_dw)
# the observer rules whose finding isolates sensors instead of tripping (degraded mode):
# the rule -> the sensors it isolates, of the observer it judged
ISOLATING_RULES = {innovation_lateral: lambda o: o.d.lateral_lasers}


def innovation(o, lim: Limits) -> Optional[tuple]:
    """The first finding of the observer rules on one observer, in their order (yaw, lateral,
    Δω)."""
    for rule in OBSERVER_RULES:
        f = rule(o, lim)
        if f is not None:
            return f
    return None


# ---------------------------------------------------------------------- degraded rules
# A degraded rule takes one DEGRADED carrier's observer and the degraded settings
# (config.Degraded) and returns (device, check, value, limit, message) or None.
def degraded_covariance(o, deg) -> Optional[tuple]:
    """The estimate the carrier runs on is no longer good enough: the σ of ŷ's error after
    this outage (the design's outage covariance, ``Observer.sigma_y``) beyond
    ``degraded.sigma_y_max``. The supervisor ends the run in the normal clean stop."""
    s = o.sigma_y
    if s > deg.sigma_y_max:
        return ("/".join(o.d.lateral_lasers), "sigma_y", s, deg.sigma_y_max,
                f"{o.d.carrier} carrier: the estimate's sigma_y {s * 1e3:.4f} mm after {o.outage} cycles without "
                f"a lateral laser is beyond degraded.sigma_y_max {deg.sigma_y_max * 1e3:g} mm")
    return None


DEGRADED_STOP_RULES = (degraded_covariance,)


class Step(NamedTuple):
    """What :meth:`Supervisor.cycle` decided: the state after this cycle's transitions and
    checks, and whether RUNNING began in this cycle."""
    state: "State"
    started: bool


class Supervisor:
    """Owns the states and checks every cycle. ``on_event(t, kind, fault_or_None, text)``
    receives state changes, faults and operator actions (the recorder's event table).

    Per cycle the loop calls :meth:`cycle` (observe, transitions, checks; returns a
    :class:`Step`), then :meth:`limit` for each carrier it drives, then :meth:`end_cycle`
    (returns the fault latched in this cycle, if any). ``carriers``: the carriers whose
    output :meth:`limit` shapes (the lanes')."""

    def __init__(self, limits: Limits, h: float, channels: Sequence[Channel], carriers: Sequence[str],
                 hardware: Hardware, on_event: Callable | None = None, activate_timeout_s: float = 0.5,
                 observers: Sequence = (), degraded=None, v_max: float = math.inf):
        self._limits = limits           # frozen, and not replaceable: see the property
        self.v_max = v_max              # the hardware's ceiling on |v̂| (speed_range)
        self._speed = None              # this cycle's measured speed (rig_runtime.speed), if given
        self.h = h
        self.channels = list(channels)
        self._by_name = {c.name: c for c in self.channels}
        self.observers = tuple(observers)      # the lanes' observers (rig_runtime.observer.Observer)
        # degraded mode (config.Degraded; docs/observer.md): only with on_lateral_loss "observe"
        self._deg = degraded if (degraded is not None and degraded.on_lateral_loss == "observe"
                                 and self.observers) else None
        # the degraded limits, capped at the limits (never looser)
        self._deg_limits = (dataclasses.replace(limits, u_max=min(degraded.limits.u_max, limits.u_max),
                                                y_max=min(degraded.limits.y_max, limits.y_max))
                            if self._deg is not None else limits)
        self._obs_of = {o.d.carrier: o for o in self.observers}
        # lateral laser -> (since t, agreeing cycles, readmittable: lost, not found lying)
        self.isolated: dict[str, tuple[float, int, bool]] = {}
        self.degraded_since: dict[str, float] = {}           # carrier -> DEGRADED since t
        self.degraded_log: list[dict] = []                   # the DEGRADED intervals, for the summary
        self._deg_stop: str = ""                             # why degraded mode asked for the clean stop
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
        self._u_prev = dict.fromkeys(self.carriers, 0.0)
        self._du = limits.du_max * h
        self._ramp = limits.u_max * h / limits.stop_ramp_s if limits.stop_ramp_s > 0 else math.inf
        self._psi_prev: dict[str, float] = {}      # the carrier's ψ of the last cycle it was measured
        self._latched: Fault | None = None          # the fault latched in the cycle under way
        self._started = False
        self._on_event = on_event or (lambda *a: None)

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
            self._u_prev = dict.fromkeys(self.carriers, 0.0)
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
        if new in (State.FAULT, State.IDLE) and self.degraded_since:
            end = new.name + (f" ({self._deg_stop})" if self._deg_stop and new is State.IDLE else "")
            for e in self.degraded_log:         # the run ends DEGRADED: close the interval
                if e["t_end"] is None:
                    e["t_end"], e["end"] = t, end
            self.degraded_since.clear()
            self.isolated.clear()
        if new in (State.FAULT, State.IDLE):
            self._deg_stop = ""

    def trip(self, t: float, device: str, check: str, value: float, limit: float, message: str = "") -> None:
        """Latch a fault (the first one of a cycle is the cause recorded)."""
        if self.state is State.FAULT:
            return
        f = Fault(t, device, check, float(value), float(limit), message)
        self.fault = f
        self.faults.append(f)
        self._latched = f
        self._on_event(t, "fault", f, message)
        self._to(State.FAULT, t, f"{device} {check}")

    def _blockers(self, t: float, conv: Converters, misses: int) -> list[str]:
        why = []
        if misses:      # warm-up still missing deadlines (first drains, imports)
            why.append(f"loop: {misses} periods lost to deadline misses")
        lim = self.limits
        for c in self.channels:
            for rule in ARM_RULES:
                b = rule((c,), t, lim)
                if b is not None:
                    why.append(f"{c.name}: {b[1][3]}")
                    break
        if not conv.ok:
            why.append(f"converters: {conv.cause}")
        elif (f := bus_error(conv, t, lim, self.h)) is not None:
            why.append(f"converters: {f[3]}")
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
                self.trip(t, "converters", "activate", t - self._armed_t, self.activate_timeout_s,
                          "power stages not OPERATION ENABLED in time" + (f" ({conv.cause})" if conv.cause else ""))

    # ------------------------------------------------------------------ per cycle
    def cycle(self, t: float, samples: Mapping[str, Sample], conv: Converters, poses: Sequence[tuple[str, float, float]],
              consecutive_misses: int, recorder_ok: bool, recorder_cause: str, speed=None) -> Step:
        """Observe this cycle's samples (by channel name), make the transitions that are due,
        and (while ARMED/RUNNING/STOPPING) apply every rule in order. ``poses``: (carrier,
        y, ψ) of each controlled carrier; ``speed``: the measured roller speed (judged by
        the speed rules after the pose rules; None: not judged)."""
        self._latched = None
        self._speed = speed
        self._started = False
        for c in self.channels:
            c.observe(samples[c.name])
        h = self.h
        pp = self._psi_prev
        pose_list = []
        for carrier, y, psi in poses:
            p = pp.get(carrier)
            pose_list.append(Pose(carrier, y, psi, 0.0 if p is None else (psi - p) / h))
            pp[carrier] = psi
        self._transitions(t, conv, consecutive_misses)
        if self.active:
            self._check(t, conv, pose_list, consecutive_misses, recorder_ok, recorder_cause)
        return Step(self.state, self._started)

    def _check(self, t: float, conv: Converters, poses: Sequence[Pose], misses: int,
               recorder_ok: bool, recorder_cause: str) -> None:
        lim = self.limits
        # root causes first: a starved loop makes the converters' watchdogs trip too
        if misses >= lim.overrun_burst:
            return self.trip(t, "loop", "overrun", misses, lim.overrun_burst,
                             f"{misses} control periods lost to deadline misses")
        if not recorder_ok:
            return self.trip(t, "recorder", "recorder", math.nan, math.nan, recorder_cause)
        if not conv.ok:
            return self.trip(t, "converters", "converter", math.nan, math.nan, conv.cause)
        f = bus_error(conv, t, lim, self.h)
        if f is not None:
            return self.trip(t, "converters", *f)
        if self.state is State.RUNNING and not conv.enabled:
            return self.trip(t, "converters", "disabled", math.nan, math.nan,
                             "a power stage left OPERATION ENABLED while running")
        chs = self.channels
        if self.isolated:
            chs = [c for c in chs if c.name not in self.isolated]
        rules = iter(CHANNEL_RULES)
        for rule in rules:
            b = rule(chs, t, lim)
            if b is not None:
                c, (check, _, _, message) = b
                # a lost laser (an arm rule's breach), not a lying one (stuck, jumping, garbling)
                if rule not in ARM_RULES or not self._degrade(t, (c.name,), check, message, readmit=True):
                    return self.trip(t, c.name, *b[1])
                chs = [c for c in chs if c.name not in self.isolated]      # judge the rest afresh
                rules = iter(CHANNEL_RULES)
        if self.isolated:
            f = self._degraded_checks(t, poses)
            if f is not None:
                return self.trip(t, *f)
            poses = [Pose(p.carrier, self._obs_of[p.carrier].y, p.psi, p.psi_rate)
                     if p.carrier in self.degraded_since else p for p in poses]
        for rule in POSE_RULES:
            for p in poses:
                f = rule(p, self._deg_limits if p.carrier in self.degraded_since else lim)
                if f is not None:
                    return self.trip(t, "geometry", *f)
        if self._speed is not None:
            for rule in SPEED_RULES:
                f = rule(self._speed, lim, self.v_max)
                if f is not None:
                    return self.trip(t, *f)
        for rule in OBSERVER_RULES:
            for o in self.observers:
                if self._channel_evidence(o.d.channels):
                    continue
                f = rule(o, lim)
                if f is not None:
                    iso = ISOLATING_RULES.get(rule)
                    if iso is None or not self._degrade(t, iso(o), f[1], f[4], readmit=False):
                        return self.trip(t, *f)

    # ------------------------------------------------------------------ degraded mode

    def _degrade(self, t: float, lasers: Sequence[str], check: str, message: str, readmit: bool) -> bool:
        """Lateral lasers of an observed carrier lost (an arm rule's breach: invalid, stale,
        not finite, out of range; ``readmit``) or found lying by the innovation test (not
        readmitted: a creeping laser does not come back by itself), while RUNNING with
        ``degraded.on_lateral_loss: observe``: isolate them and run every carrier whose y
        they feed on its observer's ŷ (DEGRADED) instead of tripping. False: a fault as usual."""
        if self._deg is None or self.state is not State.RUNNING:
            return False
        carriers = [o.d.carrier for o in self.observers if any(n in o.d.lateral_lasers for n in lasers)]
        if not carriers:
            return False
        for n in lasers:
            self.isolated[n] = (t, 0, readmit)
        name = "/".join(lasers)
        for car in carriers:
            if car not in self.degraded_since:
                self.degraded_since[car] = t
                self.degraded_log.append({"carrier": car, "laser": name, "check": check, "t_start": t,
                                          "t_end": None, "end": ""})
        self._on_event(t, "degraded", None,
                       f"DEGRADED: {name} {check} ({message}); {'/'.join(carriers)} carrier(s) on the "
                       f"observer's estimate, u_max {self._deg_limits.u_max:g} A, y_max "
                       f"{self._deg_limits.y_max * 1e3:g} mm, at most {self._deg.max_s:g} s"
                       + ("" if readmit else "; not readmitted in this run"))
        return True

    def _degraded_checks(self, t: float, poses: Sequence[Pose]) -> Optional[tuple]:
        """While DEGRADED: ``max_s`` (a finding: the fault), the degraded stop rules (the
        estimate's covariance: the normal clean stop, asked once), and the readmission of each
        readmittable isolated laser that is fit again and whose carriers' measured y agrees
        with ŷ within ``readmit_tol_m`` for ``readmit_s`` without a break."""
        deg = self._deg
        for car, since in self.degraded_since.items():
            if t - since > deg.max_s:
                lasers = "/".join(n for n in self._obs_of[car].d.lateral_lasers if n in self.isolated)
                return (lasers, "degraded", t - since, deg.max_s,
                        f"{car} carrier DEGRADED (lateral laser {lasers} isolated) for longer than "
                        f"degraded.max_s = {deg.max_s:g} s")
        if not self._deg_stop and self.state is State.RUNNING:
            for rule in DEGRADED_STOP_RULES:
                for car in self.degraded_since:
                    f = rule(self._obs_of[car], deg)
                    if f is not None:
                        self._deg_stop = f"{f[1]} {f[2] * 1e3:.4f} mm > {f[3] * 1e3:g} mm"
                        self._on_event(t, "degraded", None, f"DEGRADED ends: {f[4]}: clean stop")
                        self.request_stop(t, f"degraded mode ended: {f[4]}")
                        break
                if self._deg_stop:
                    break
        need = max(1, round(deg.readmit_s / self.h))
        y_meas = {p.carrier: p.y for p in poses}
        lim = self.limits
        for name, (since, n, readmit) in list(self.isolated.items()):
            if not readmit:
                continue
            c = (self._by_name[name],)
            ok = all(rule(c, t, lim) is None for rule in CHANNEL_RULES)
            if ok:
                for o in self.observers:
                    if name in o.d.lateral_lasers:
                        y = y_meas.get(o.d.carrier, math.nan)
                        if not abs(y - o.y) <= deg.readmit_tol_m:
                            ok = False
            n = n + 1 if ok else 0
            if n < need:
                self.isolated[name] = (since, n, readmit)
                continue
            del self.isolated[name]
            self._on_event(t, "degraded", None, f"{name} readmitted: fit and within "
                           f"{deg.readmit_tol_m * 1e3:g} mm of the estimate for {deg.readmit_s:g} s")
            for car in list(self.degraded_since):
                if not any(l in self.isolated for l in self._obs_of[car].d.lateral_lasers):
                    del self.degraded_since[car]
                    for e in self.degraded_log:
                        if e["carrier"] == car and e["t_end"] is None:
                            e["t_end"], e["end"] = t, f"{name} readmitted"
                    self._on_event(t, "degraded", None, f"{car} carrier: DEGRADED ended")
        return None

    def isolated_any(self, names: Sequence[str]) -> bool:
        """One of the named lateral lasers is isolated (not to be used by the observer)."""
        iso = self.isolated
        return bool(iso) and any(n in iso for n in names)

    def _channel_evidence(self, names: Sequence[str]) -> bool:
        """A channel rule is gathering evidence on one of the named channels: it has repeated
        its value (``stuck``) or brought garbled frames (``corrupt_link``) in its latest
        cycles. The observer rules wait then — a stuck yaw laser disagrees with the model
        long before ``stuck_periods`` have passed, and the channel rule names the sensor
        itself, where the innovation test can only name the measurement (and, for a yaw
        laser frozen on a moving carrier, first sees the lateral lasers disagree). A
        healthy, quantised laser repeats a value for a cycle or two now and then: the rule
        then waits that long."""
        by = self._by_name
        for n in names:
            c = by.get(n)
            if c is not None and n not in self.isolated and (c.same > 0 or c.bad_run > 0):
                return True
        return False

    def fit(self, names: Sequence[str], t: float) -> bool:
        """Every named channel fit for use this cycle: what arming asks of a channel (a
        fresh, finite, in-range sample; ``ARM_RULES``). The observer's lateral update uses a
        laser only then."""
        lim = self.limits
        by = self._by_name
        for n in names:
            c = (by[n],)
            for rule in ARM_RULES:
                if rule(c, t, lim) is not None:
                    return False
        return True

    # ------------------------------------------------------------------ output limit
    def limit(self, carrier: str, u: float, t: float) -> float:
        """The current actually sent for ``carrier``: 0 unless RUNNING/STOPPING; checked by
        the output rules, saturated at ±u_max and rate limited while RUNNING; ramped to zero
        while STOPPING (``end_cycle`` then moves to IDLE once every output is zero)."""
        st = self.state
        if st is State.RUNNING:
            lim = self.limits
            for rule in OUTPUT_RULES:
                f = rule(carrier, u, lim)
                if f is not None:
                    self.trip(t, "controller", *f)
                    self._u_prev[carrier] = 0.0
                    return 0.0
            m = self._deg_limits.u_max if carrier in self.degraded_since else lim.u_max
            u = m if u > m else (-m if u < -m else u)
            p, d = self._u_prev[carrier], self._du
            u = p + d if u > p + d else (p - d if u < p - d else u)
        elif st is State.STOPPING:
            p, r = self._u_prev[carrier], self._ramp
            u = p - r if p > r else (p + r if p < -r else 0.0)
        else:
            u = 0.0
        self._u_prev[carrier] = u
        return u

    def end_cycle(self, t: float) -> Fault | None:
        """STOPPING ends (→ IDLE, power stages off) once every output has ramped to zero.
        Returns the fault latched in this cycle (None: none)."""
        if self.state is State.STOPPING and not any(self._u_prev.values()):
            self._to(State.IDLE, t, "stopped")
        return self._latched
