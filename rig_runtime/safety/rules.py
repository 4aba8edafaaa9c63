"""Every rule the supervisor judges, each written once. A rule returns a
:class:`~rig_runtime.safety.types.Finding` (device, check, value, limit, message) or None
(it holds); the supervisor (``safety.supervisor``) applies them in order.

Families, each an ordered tuple: the system rules (loop overruns, recorder, converters, a
recent bus error, a power stage left OPERATION ENABLED), the channel rules (each applied to
every sensor channel before the next rule; ``ARM_RULES`` are what arming asks), the pose
rules (each carrier's measured y, ψ, ψ̇), the speed rules, the observer rules (analytical
redundancy), the degraded stop rules and the output rules (a lane's command)."""

from __future__ import annotations

import math
from typing import Callable, Collection, Optional, Sequence

from ..config import Limits
from ..hardware import Freshness
from .types import BAD_UNIT, NEVER_T, Channel, Converters, Finding, Pose

_NEVER = 1 << 62         # a count limit that is switched off
_finite = math.isfinite


# ---------------------------------------------------------------------- system rules
class System:
    """What the system rules look at in one cycle. The supervisor keeps one and fills it in
    place every cycle (nothing is allocated per cycle); read by name."""

    __slots__ = ("t", "h", "misses", "recorder_ok", "recorder_cause", "conv", "running", "lost")

    def __init__(self, t: float, h: float, misses: int, recorder_ok: bool, recorder_cause: str,
                 conv: Converters, running: bool, lost: Collection[str] = ()):
        self.t = t
        self.h = h
        self.misses = misses                # consecutive control periods lost to deadline misses
        self.recorder_ok = recorder_ok
        self.recorder_cause = recorder_cause
        self.conv = conv
        self.running = running              # the state is RUNNING (power stages must be enabled)
        self.lost = lost                    # the wheels whose drive the run does without (RECONFIGURED)


def overrun(s: System, lim: Limits) -> Optional[Finding]:
    """A starved loop comes first: it makes the converters' watchdogs trip too."""
    if s.misses >= lim.overrun_burst:
        return Finding("loop", "overrun", s.misses, lim.overrun_burst,
                       f"{s.misses} control periods lost to deadline misses")
    return None


def recorder(s: System, lim: Limits) -> Optional[Finding]:
    if not s.recorder_ok:
        return Finding("recorder", "recorder", math.nan, math.nan, s.recorder_cause)
    return None


def converter(s: System, lim: Limits) -> Optional[Finding]:
    """A drive or the bus INVALID (the driver's cause) — but for a drive the run does
    without (RECONFIGURED: its wheel is lost, its report no longer matters)."""
    conv = s.conv
    if conv.ok:
        return None
    for w, cause in conv.drives:
        if w not in s.lost:
            return Finding("converters", "converter", math.nan, math.nan, cause)
    if conv.drives and conv.bus_ok:
        return None
    return Finding("converters", "converter", math.nan, math.nan, conv.cause)


def bus_error(s: System, lim: Limits) -> Optional[Finding]:
    """A bus error within the staleness window: frames may have been lost in it."""
    conv = s.conv
    window = lim.stale_periods * s.h
    ago = s.t - conv.bus_error_t
    if ago <= window:
        return Finding("converters", "converter", ago, window, f"CAN bus: {conv.bus_cause} ({ago * 1e3:.0f} ms ago)")
    return None


def disabled(s: System, lim: Limits) -> Optional[Finding]:
    """A power stage left OPERATION ENABLED while RUNNING (not one of a lost wheel's drive)."""
    conv = s.conv
    if s.running and not conv.enabled and not (conv.not_enabled and all(w in s.lost for w in conv.not_enabled)):
        return Finding("converters", "disabled", math.nan, math.nan,
                       "a power stage left OPERATION ENABLED while running")
    return None


SYSTEM_RULES = (overrun, recorder, converter, bus_error, disabled)


# ---------------------------------------------------------------------- channel rules
# A channel rule takes the channels and returns the finding of the first one that breaks it
# (the finding's device is the channel's name), or None. Each rule loops over the channels
# itself: one call per rule and cycle.
ChannelRule = Callable[[Sequence[Channel], float, Limits], Optional[Finding]]


def invalid(chs: Sequence[Channel], t: float, lim: Limits) -> Optional[Finding]:
    bad = Freshness.INVALID
    for c in chs:
        if c.state is bad:
            return Finding(c.name, "invalid", c.value, math.nan, c.cause)
    return None


def _discarded(c: Channel) -> str:
    n = c.bad - c.bad_at_value
    return f": {n} {BAD_UNIT.get(c.kind, 'garbled frames')} in that time" if n > 0 else ""


def stale(chs: Sequence[Channel], t: float, lim: Limits) -> Optional[Finding]:
    """No valid value in time, judged in whole control periods for every kind (an exact
    N-period silence is stale whatever the arrival phase): a free-running device by the
    cycles since its latest valid value was first seen (``Channel.silent``), a device that
    answers the runtime's requests (a SYNC-triggered TPDO) by the requests it left
    unanswered — the runtime's own lateness is not the device's fault. Either reaching
    ``stale_n`` is stale. The finding names what was observed instead: discarded data in
    that time makes it a corrupted link (``corrupt``), not a silent device."""
    never = NEVER_T
    for c in chs:
        n = c.stale_n
        if c.unanswered >= 0:
            if c.unanswered >= n or c.t == never:
                what = "no valid value yet" if c.t == never else "no valid value"
                g = _discarded(c)
                return Finding(c.name, "corrupt" if g else "stale", c.unanswered, n,
                               f"{what} for {c.unanswered} requests sent{g}")
            continue
        if c.t == never or c.silent >= n:
            age = t - c.t
            g = _discarded(c)
            what = "no valid value yet" if c.t == never else f"no valid value for {age * 1e3:.0f} ms"
            return Finding(c.name, "corrupt" if g else "stale", age, c.stale_s, what + g)
    return None


def not_finite(chs: Sequence[Channel], t: float, lim: Limits) -> Optional[Finding]:
    finite = _finite
    for c in chs:
        v = c.value
        if not finite(v):
            return Finding(c.name, "nan", v, math.nan, "value is not finite")
    return None


def out_of_range(chs: Sequence[Channel], t: float, lim: Limits) -> Optional[Finding]:
    for c in chs:
        v = c.value
        if v < c.lo or v > c.hi:
            return Finding(c.name, "range", v, c.hi if v > c.hi else c.lo, "raw value outside the sensor range")
    return None


def corrupt_link(chs: Sequence[Channel], t: float, lim: Limits) -> Optional[Finding]:
    n = lim.corrupt_cycles or _NEVER
    for c in chs:
        if c.bad_run >= n:
            unit = BAD_UNIT.get(c.kind, "garbled frames")
            return Finding(c.name, "corrupt", c.bad_run, n,
                           f"{unit} in {c.bad_run} consecutive cycles ({c.bad} in total)")
    return None


def stuck(chs: Sequence[Channel], t: float, lim: Limits) -> Optional[Finding]:
    n = lim.stuck_periods or _NEVER
    for c in chs:
        if c.same >= n:
            return Finding(c.name, "stuck", c.same, n, f"value repeated bit-identically for {c.same} cycles")
    return None


def jump(chs: Sequence[Channel], t: float, lim: Limits) -> Optional[Finding]:
    for c in chs:
        d, m = c.delta, c.step_max
        if d > m or -d > m:                 # |delta| > step_max
            return Finding(c.name, "jump", c.delta, c.step_max, "implausible change between two cycles")
    return None


CHANNEL_RULES: tuple[ChannelRule, ...] = (invalid, stale, not_finite, out_of_range, corrupt_link, stuck, jump)
# what arming needs of every channel: a fresh, finite, in-range sample (a lost channel,
# not a lying one: only these may be isolated and readmitted)
ARM_RULES = (invalid, stale, not_finite, out_of_range)
# the channel rules whose breach on a drive's wheel channel is a lost drive (what it said of
# itself, or its silence), which reconfiguration may absorb
DRIVE_LOSS_RULES = (invalid, stale)


# ---------------------------------------------------------------------- drive rules
def torque_response(wheel: str, run: int, residual: float, commanded: float, actual: float, deg,
                    h: float) -> Optional[Finding]:
    """A drive that answers but whose wheel gets no torque (a silent outage, e.g. a lost
    phase): its reported torque actual further than ``degraded.torque_residual_A`` from each
    of its latest commands (the answer may lag by a SYNC or two), every one of them at least
    that large, either sign, for ``degraded.torque_hold_s`` (``run`` cycles so far)."""
    need = max(1, round(deg.torque_hold_s / h))
    if run >= need:
        return Finding(wheel, "torque", residual, deg.torque_residual_A,
                       f"drive {wheel}: no torque response ({actual:+.3f} A reported against {commanded:+.3f} A "
                       f"commanded, off by more than {deg.torque_residual_A:g} A for {run} cycles)")
    return None


# ---------------------------------------------------------------------- pose rules
def pose_not_finite(p: Pose, lim: Limits) -> Optional[Finding]:
    if not (_finite(p.psi) and _finite(p.y)):
        return Finding("geometry", "nan", math.nan, math.nan,
                       f"{p.carrier} carrier: y or psi is not finite ({p.y!r}, {p.psi!r})")
    return None


def psi_limit(p: Pose, lim: Limits) -> Optional[Finding]:
    if abs(p.psi) > lim.psi_max:
        return Finding("geometry", "psi_limit", p.psi, lim.psi_max, f"{p.carrier} carrier: yaw angle beyond limit")
    return None


def y_limit(p: Pose, lim: Limits) -> Optional[Finding]:
    if abs(p.y) > lim.y_max:
        return Finding("geometry", "y_limit", p.y, lim.y_max,
                       f"{p.carrier} carrier: lateral displacement beyond limit")
    return None


def psi_rate_limit(p: Pose, lim: Limits) -> Optional[Finding]:
    if lim.psi_rate_max is not None and abs(p.psi_rate) > lim.psi_rate_max:
        return Finding("geometry", "psi_rate_limit", p.psi_rate, lim.psi_rate_max,
                       f"{p.carrier} carrier: yaw rate beyond limit")
    return None


POSE_RULES = (pose_not_finite, psi_limit, y_limit, psi_rate_limit)


# ---------------------------------------------------------------------- output rules
def output_not_finite(carrier: str, u: float, lim: Limits) -> Optional[Finding]:
    if not _finite(u):
        return Finding("controller", "nan", u, math.nan, f"{carrier} carrier: controller output is not finite")
    return None


OUTPUT_RULES = (output_not_finite,)


# ---------------------------------------------------------------------- speed rules
# A speed rule takes the measured speed (rig_runtime.speed.SpeedEstimate: ``carriers``, their
# filtered speeds ``v`` and v̂ ``v_hat``, m/s), the limits and the hardware's v_max. Not
# finite (no encoder value yet): the channel rules judge the encoders themselves.
def speed_disagree(sp, lim: Limits, v_max: float) -> Optional[Finding]:
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
        return Finding("encoders", "speed_disagree", d, lim.v_disagree_max,
                       f"the carriers' wheel encoders disagree about the roller speed by {d:.3f} m/s ({each})")
    return None


def speed_range(sp, lim: Limits, v_max: float) -> Optional[Finding]:
    """|v̂| above the hardware's ``ceilings.v_max``: beyond what the rollers can run."""
    v = sp.v_hat
    if abs(v) > v_max:
        return Finding("encoders", "speed_range", v, v_max,
                       f"measured roller speed {v:+.3f} m/s beyond the hardware's v_max ({'/'.join(sp.carriers)} encoders)")
    return None


SPEED_RULES = (speed_disagree, speed_range)


# ---------------------------------------------------------------------- observer rules
# An observer rule takes one carrier's observer (rig_runtime.observer.Observer: its window
# statistics of the normalised innovations, as of the latest estimate).
def _joined(names: Sequence[str]) -> str:
    return "/".join(names)


def _leads(o, kind: str) -> bool:
    """The observer names this kind of measurement as the one whose fault explains its
    innovations best (the running gear's filter: ``CarrierView.lead``, the largest of its six
    statistics — another beyond the threshold is a symptom of the same fault); an observer that
    does not decide (``lead`` None: the per-carrier filter, or a laser out) leaves it to the
    rules' order."""
    lead = getattr(o, "lead", None)
    return lead is None or lead == kind


def innovation_yaw(o, lim: Limits) -> Optional[Finding]:
    """Analytical redundancy (docs/observer.md): a measurement whose window-mean normalised
    innovation has χ²(1) ``T`` above ``limits.innovation_chi2`` disagrees with the model and
    the other sensors. The yaw lasers are tested first (every other measurement leans on ψ);
    the test cannot tell the two apart."""
    thr = lim.innovation_chi2
    if thr is None or not o.window_full or not o.T_psi > thr or not _leads(o, "psi"):
        return None
    d = o.d
    return Finding(_joined(d.yaw_lasers), "innovation", o.T_psi, thr,
                   f"{d.carrier} carrier: yaw lasers {_joined(d.yaw_lasers)} disagree with the model and the other "
                   f"sensors (chi2 {o.T_psi:.1f} > {thr:g}); the test cannot tell the two apart")


def innovation_lateral(o, lim: Limits) -> Optional[Finding]:
    """The lateral y disagrees with (2b) driven by the measured ψ — the reference that does
    not follow a drifting laser. Judged only while the latest estimate used the lateral
    lasers (``lat_used``): an isolated or unfit laser brings no evidence, and the window it
    left behind must not find it again. With ``degraded.on_lateral_loss: observe`` the
    supervisor isolates the lasers on this finding instead of tripping."""
    thr = lim.innovation_chi2
    if thr is None or not o.window_full or not o.lat_used or not o.T_lat > thr or not _leads(o, "lat"):
        return None
    d = o.d
    L = d.lateral_lasers
    return Finding(_joined(L), "innovation", o.T_lat, thr,
                   f"{d.carrier} carrier: lateral lasers {_joined(L)} disagree with the model driven by psi "
                   f"(window-mean innovation {o.mean_lat * 1e6:+.1f} um, chi2 {o.T_lat:.1f} > {thr:g}; "
                   f"y weights {L[0]} {d.lateral_weights[0]:.2f}, {L[1]} {d.lateral_weights[1]:.2f})")


def innovation_dw(o, lim: Limits) -> Optional[Finding]:
    """Δω disagrees with the estimate, which follows the precise lateral lasers: the
    carrier's lateral lasers or its encoders — which of them the test cannot tell, and the
    finding says so (never a degradation: the observer cannot vouch for Δω, which carries
    ŷ without the lateral lasers)."""
    thr = lim.innovation_chi2
    if thr is None or not o.window_full or not o.T_dw > thr or not _leads(o, "dw"):
        return None
    d = o.d
    L, enc = d.lateral_lasers, d.encoders
    gy = d.dw_row[0]
    return Finding(f"{L[0]}|{_joined(enc)}", "innovation", o.T_dw, thr,
                   f"{d.carrier} carrier: {L[0]} (y weight {d.lateral_weights[0]:.2f}; {L[1]} "
                   f"{d.lateral_weights[1]:.2f}) and the encoders {_joined(enc)} disagree by "
                   f"{o.mean_dw * 1e3:+.2f} mrad/s of dw (= {o.mean_dw / gy * 1e3:+.3f} mm of y; chi2 "
                   f"{o.T_dw:.1f} > {thr:g}): the innovation test cannot tell the lateral laser from the encoders")


OBSERVER_RULES = (innovation_yaw, innovation_lateral, innovation_dw)
# the observer rules whose finding isolates sensors instead of tripping (degraded mode):
# the rule -> the sensors it isolates, of the observer it judged
ISOLATING_RULES = {innovation_lateral: lambda o: o.d.lateral_lasers}


def innovation(o, lim: Limits) -> Optional[Finding]:
    """The first finding of the observer rules on one observer, in their order (yaw, lateral,
    Δω)."""
    for rule in OBSERVER_RULES:
        f = rule(o, lim)
        if f is not None:
            return f
    return None


# ---------------------------------------------------------------------- degraded rules
# A degraded stop rule takes one DEGRADED carrier's observer and the degraded settings
# (config.Degraded): a finding ends the degraded run in the normal clean stop.
def degraded_covariance(o, deg) -> Optional[Finding]:
    """The estimate the carrier runs on is no longer good enough: the σ of ŷ's error after
    this outage (the design's outage covariance, ``Observer.sigma_y``) beyond
    ``degraded.sigma_y_max``. The supervisor ends the run in the normal clean stop."""
    s = o.sigma_y
    if s > deg.sigma_y_max:
        return Finding("/".join(o.d.lateral_lasers), "sigma_y", s, deg.sigma_y_max,
                       f"{o.d.carrier} carrier: the estimate's sigma_y {s * 1e3:.4f} mm after {o.outage} cycles "
                       f"without a lateral laser is beyond degraded.sigma_y_max {deg.sigma_y_max * 1e3:g} mm")
    return None


DEGRADED_STOP_RULES = (degraded_covariance,)
