"""Safety supervisor: a state machine with latched faults, the per-cycle checks and the
output limit.

States ``IDLE → ARMED → RUNNING → STOPPING → IDLE``, and ``FAULT`` (latched) from anywhere
until an explicit ``reset``. On a fault the output is zero in the same cycle; the loop then
disables the converters. Limits come from the frozen config and cannot be loosened.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Callable, Sequence

from drivers.base import Freshness

from .config import Limits


_FRESH = Freshness.FRESH
_INF = math.inf
_NINF = -math.inf
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


class Channel:
    """One sensor channel as the supervisor sees it (updated in place every cycle)."""

    __slots__ = ("name", "kind", "value", "t", "state", "cause", "lo", "hi", "stale_s",
                 "step_max", "stuck_check", "prev", "same", "delta", "bad", "bad_prev", "bad_run")

    def __init__(self, name: str, kind: str, lo: float, hi: float, stale_s: float,
                 step_max: float = math.inf, stuck_check: bool = False):
        self.name, self.kind, self.lo, self.hi, self.stale_s = name, kind, lo, hi, stale_s
        self.step_max = step_max          # largest plausible change between two cycles
        self.stuck_check = stuck_check    # a sensor with noise never repeats bit-identically for long
        self.value = math.nan
        self.t = -math.inf
        self.state = Freshness.STALE
        self.cause = "no sample yet"
        self.prev = math.nan
        self.same = 0
        self.delta = 0.0
        self.bad = 0            # the driver's cumulative count of garbled frames / bytes
        self.bad_prev = 0
        self.bad_run = 0        # consecutive cycles with new garbled data


class Supervisor:
    """Checks every cycle and limits the output. ``on_event(t, kind, fault_or_None, text)``
    receives state changes and faults (the recorder's event table)."""

    def __init__(self, limits: Limits, h: float, on_event: Callable | None = None):
        self.limits = limits
        self.h = h
        self.state = State.IDLE
        self.fault: Fault | None = None
        self.faults: list[Fault] = []
        self.new_fault = False          # set in the cycle a fault latched
        self._u_prev = [0.0, 0.0]    # per controlled carrier
        self._du = limits.du_max * h
        self._ramp = limits.u_max * h / limits.stop_ramp_s if limits.stop_ramp_s > 0 else math.inf
        self._psi_prev = math.nan
        self._psi_rate = 0.0
        self._on_event = on_event or (lambda *a: None)

    # ------------------------------------------------------------------ transitions
    def _to(self, new: State, t: float, text: str = "") -> None:
        if new is not self.state:
            old, self.state = self.state, new
            self._on_event(t, "state", None, f"{old.name} -> {new.name}" + (f": {text}" if text else ""))

    def trip(self, t: float, device: str, check: str, value: float, limit: float, message: str = "") -> None:
        """Latch a fault (the first one of a cycle is the cause recorded)."""
        if self.state is State.FAULT:
            return
        f = Fault(t, device, check, float(value), float(limit), message)
        self.fault = f
        self.faults.append(f)
        self.new_fault = True
        self._on_event(t, "fault", f, message)
        self._to(State.FAULT, t, f"{device} {check}")

    def arm_blockers(self, channels: Sequence[Channel], converters_ready: bool, t: float) -> list[str]:
        """Why arming is not possible now (empty list: it is)."""
        why = []
        for c in channels:
            if c.state is not Freshness.FRESH or t - c.t > c.stale_s:
                why.append(f"{c.name}: {c.cause or c.state.value}")
            elif not (c.lo <= c.value <= c.hi):
                why.append(f"{c.name}: {c.value:.6g} outside [{c.lo:.6g}, {c.hi:.6g}]")
        if not converters_ready:
            why.append("converters not ready")
        return why

    def arm(self, channels: Sequence[Channel], converters_ready: bool, t: float) -> list[str]:
        if self.state is not State.IDLE:
            return [f"cannot arm from {self.state.name}"]
        why = self.arm_blockers(channels, converters_ready, t)
        if not why:
            self._to(State.ARMED, t)
        return why

    def start(self, t: float) -> None:
        if self.state is State.ARMED:
            self._to(State.RUNNING, t)

    def request_stop(self, t: float, reason: str = "stop requested") -> None:
        if self.state in (State.ARMED, State.RUNNING):
            self._on_event(t, "operator", None, reason)
            self._to(State.STOPPING, t, reason)

    def reset(self, t: float) -> None:
        """Explicit operator reset of a latched fault."""
        if self.state is State.FAULT:
            self._on_event(t, "operator", None, "fault reset")
            self.fault = None
            self._u_prev = [0.0, 0.0]
            self._to(State.IDLE, t)

    @property
    def active(self) -> bool:
        return self.state in (State.ARMED, State.RUNNING, State.STOPPING)

    # ------------------------------------------------------------------ per-cycle checks
    def check(self, t: float, channels: Sequence[Channel], converters_ok: bool, converter_cause: str,
              y: float, psi: float, consecutive_misses: int, recorder_ok: bool, recorder_cause: str) -> None:
        """Every cycle while active: sample age, NaN/inf, raw range, state limits, overruns,
        converters, recorder. Trips the first failing check."""
        self.new_fault = False
        # yaw-rate estimate (first-order difference, only used if a limit is configured)
        if self._psi_prev == self._psi_prev:  # not NaN
            self._psi_rate = (psi - self._psi_prev) / self.h
        self._psi_prev = psi
        stuck_n = self.limits.stuck_periods or 0
        corrupt_n = self.limits.corrupt_cycles or 0
        s_lim = stuck_n or _NEVER
        c_lim = corrupt_n or _NEVER
        nominal = True          # every channel passes every channel check (known from this one pass)
        for c in channels:
            v, p = c.value, c.prev
            c.prev = v
            d = c.delta = v - p
            if c.stuck_check:
                c.same = c.same + 1 if v == p else 0
            b = c.bad
            c.bad_run = c.bad_run + 1 if b > c.bad_prev else 0
            c.bad_prev = b
            if nominal and not (c.state is _FRESH and t - c.t <= c.stale_s and c.lo <= v <= c.hi
                                and _NINF < v < _INF and -c.step_max <= d <= c.step_max
                                and c.bad_run < c_lim and c.same < s_lim):
                nominal = False
        st = self.state
        if st is not State.RUNNING and st is not State.ARMED and st is not State.STOPPING:
            return
        lim = self.limits
        # root causes first: a starved loop makes the converters' watchdogs trip too
        if consecutive_misses >= lim.overrun_burst:
            return self.trip(t, "loop", "overrun", consecutive_misses, lim.overrun_burst,
                             f"{consecutive_misses} control periods lost to deadline misses")
        if not recorder_ok:
            return self.trip(t, "recorder", "recorder", math.nan, math.nan, recorder_cause)
        if not converters_ok:
            return self.trip(t, "converters", "converter", math.nan, math.nan, converter_cause)
        if not nominal and self._check_channels(t, channels, stuck_n, corrupt_n):
            return
        if psi != psi or y != y:
            return self.trip(t, "geometry", "nan", math.nan, math.nan, "y or psi is not finite")
        if abs(psi) > lim.psi_max:
            return self.trip(t, "geometry", "psi_limit", psi, lim.psi_max, "yaw angle beyond limit")
        if abs(y) > lim.y_max:
            return self.trip(t, "geometry", "y_limit", y, lim.y_max, "lateral displacement beyond limit")
        if lim.psi_rate_max is not None and abs(self._psi_rate) > lim.psi_rate_max:
            return self.trip(t, "geometry", "psi_rate_limit", self._psi_rate, lim.psi_rate_max, "yaw rate beyond limit")

    def _check_channels(self, t: float, channels: Sequence[Channel], stuck_n: int, corrupt_n: int) -> bool:
        """The channel checks one by one, in order (only when some channel is not nominal);
        True if one tripped."""
        for c in channels:
            age = t - c.t
            if c.state is Freshness.INVALID:
                self.trip(t, c.name, "invalid", c.value, math.nan, c.cause)
                return True
            if c.state is Freshness.STALE or age > c.stale_s:
                self.trip(t, c.name, "stale", age, c.stale_s, c.cause or f"sample {age * 1e3:.1f} ms old")
                return True
            v = c.value
            if v != v or v in (math.inf, -math.inf):
                self.trip(t, c.name, "nan", v, math.nan, "value is not finite")
                return True
            if v < c.lo or v > c.hi:
                self.trip(t, c.name, "range", v, c.hi if v > c.hi else c.lo, "raw value outside the sensor range")
                return True
            if corrupt_n and c.bad_run >= corrupt_n:
                self.trip(t, c.name, "corrupt", c.bad_run, corrupt_n,
                          f"garbled frames in {c.bad_run} consecutive cycles ({c.bad} in total)")
                return True
            if stuck_n and c.same >= stuck_n:
                self.trip(t, c.name, "stuck", c.same, stuck_n, f"value repeated bit-identically for {c.same} cycles")
                return True
        for c in channels:
            if abs(c.delta) > c.step_max:
                self.trip(t, c.name, "jump", c.delta, c.step_max,
                          "implausible change between two cycles")
                return True
        return False

    # ------------------------------------------------------------------ output limit
    def limit(self, u: float, t: float, i: int = 0) -> float:
        """The current actually sent for carrier ``i``: 0 unless RUNNING/STOPPING;
        saturated at ±u_max and rate limited while RUNNING; ramped to zero while STOPPING
        (``end_cycle`` then moves to IDLE once every output is zero)."""
        st = self.state
        if st is State.RUNNING:
            if u != u:
                self.trip(t, "controller", "nan", u, math.nan, "controller output is not finite")
                self._u_prev[i] = 0.0
                return 0.0
            m = self.limits.u_max
            u = m if u > m else (-m if u < -m else u)
            p, d = self._u_prev[i], self._du
            u = p + d if u > p + d else (p - d if u < p - d else u)
        elif st is State.STOPPING:
            p, r = self._u_prev[i], self._ramp
            u = p - r if p > r else (p + r if p < -r else 0.0)
        else:
            u = 0.0
        self._u_prev[i] = u
        return u

    def end_cycle(self, t: float) -> None:
        """STOPPING ends (→ IDLE) once every output has ramped to zero."""
        if self.state is State.STOPPING and self._u_prev[0] == 0.0 and self._u_prev[1] == 0.0:
            self._to(State.IDLE, t, "stopped")
