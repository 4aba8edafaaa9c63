"""The supervisor's value types: its states, a latched fault, what a cycle brings (a
channel's sample, the converters, a carrier's pose), one rule's finding, and a sensor
channel as the supervisor sees it (its limits and the history the rules look at)."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import NamedTuple

from ..hardware import Freshness, Health


class State(enum.IntEnum):
    IDLE = 0
    ARMED = 1
    RUNNING = 2
    STOPPING = 3
    FAULT = 4


@dataclass(frozen=True, slots=True)
class Finding:
    """What one rule found broken: the device it names, the check, the observed value, the
    limit it broke and one line saying what was seen. Every rule returns one of these or
    None (the rule holds); it is read by name, never by position."""
    device: str
    check: str
    value: float
    limit: float
    message: str


@dataclass(frozen=True, slots=True)
class Fault:
    t: float
    device: str
    check: str
    value: float
    limit: float
    message: str = ""

    @classmethod
    def of(cls, t: float, f: Finding) -> "Fault":
        return cls(t, f.device, f.check, float(f.value), float(f.limit), f.message)

    def as_dict(self) -> dict:
        def num(x: float):
            return x if math.isfinite(x) else None
        return {"t": self.t, "device": self.device, "check": self.check,
                "value": num(self.value), "limit": num(self.limit), "message": self.message}


class Sample(NamedTuple):
    """One channel's reading in a cycle: value, the time it arrived (NaN: never), health,
    and for a device that answers the runtime's requests (a SYNC-triggered TPDO) how many
    requests are unanswered (-1: a free-running device, judged by the cycles its value is old)."""
    value: float
    t: float
    health: Health
    unanswered: int = -1


class Converters(NamedTuple):
    """The converters as a cycle sees them: ``ok`` (no drive or bus INVALID, else ``cause``),
    ``enabled`` (every power stage OPERATION ENABLED), when the bus last reported an error
    (send or receive failure, error frame; -inf: never) and what it was; per wheel, what
    each drive reported: ``drives`` the (wheel, cause) of every INVALID drive (its own
    fault, EMCY, heartbeat), ``not_enabled`` the wheels whose power stage is not OPERATION
    ENABLED, ``bus_ok`` the bus itself not INVALID, ``torque`` each drive's reported current."""
    ok: bool
    cause: str
    enabled: bool
    bus_error_t: float = -math.inf
    bus_cause: str = ""
    drives: tuple[tuple[str, str], ...] = ()
    not_enabled: tuple[str, ...] = ()
    bus_ok: bool = True
    torque: tuple[tuple[str, float], ...] = ()      # (wheel, torque actual in A of its latest TPDO)


class Pose:
    """One controlled carrier's state as measured this cycle. The supervisor keeps one per
    carrier and updates it in place every cycle (its ψ is the previous ψ for the next ψ̇)."""

    __slots__ = ("carrier", "y", "psi", "psi_rate")

    def __init__(self, carrier: str, y: float, psi: float, psi_rate: float):
        self.carrier, self.y, self.psi, self.psi_rate = carrier, y, psi, psi_rate


class Step(NamedTuple):
    """What :meth:`Supervisor.cycle` decided: the state after this cycle's transitions and
    checks, and whether RUNNING began in this cycle."""
    state: State
    started: bool


NEVER_T = -math.inf     # a channel's arrival time before its first valid value

# what a channel's discarded data is counted in, by kind (the driver's ``Health.bad_frames``)
BAD_UNIT = {"laser": "bytes of unparseable data", "wheel": "garbled frames", "ft": "garbled replies"}


class Channel:
    """One sensor channel as the supervisor sees it: its limits, and its history (updated
    in place every cycle by :meth:`Supervisor.cycle`).

    Freshness is judged in whole control periods for every kind: ``silent`` counts the
    cycles since the cycle that first saw the latest valid value (a value already more than a
    period old when first seen starts at its whole periods of age), ``unanswered`` the
    requests a request-answering device left open; either reaching ``stale_n`` is stale.
    ``stale_n`` is ``stale_s`` in periods, set by the supervisor (it knows h)."""

    __slots__ = ("name", "kind", "value", "t", "state", "cause", "lo", "hi", "stale_s", "stale_n", "silent",
                 "step_max", "stuck_check", "same", "delta", "bad", "bad_run", "unanswered", "bad_at_value")

    def __init__(self, name: str, kind: str, lo: float, hi: float, stale_s: float,
                 step_max: float = math.inf, stuck_check: bool = False):
        self.name, self.kind, self.lo, self.hi, self.stale_s = name, kind, lo, hi, stale_s
        self.stale_n = 1                  # stale_s in whole periods (Supervisor sets it)
        self.step_max = step_max          # largest plausible change between two cycles
        self.stuck_check = stuck_check    # a sensor with noise never repeats bit-identically for long
        self.value = math.nan
        self.t = NEVER_T
        self.silent = 0                   # cycles since the latest valid value was first seen
        self.state = Freshness.STALE
        self.cause = "no sample yet"
        self.same = 0
        self.delta = 0.0
        self.bad = 0            # the driver's cumulative count of discarded data (BAD_UNIT)
        self.bad_run = 0        # consecutive cycles with newly discarded data
        self.unanswered = -1    # requests unanswered (-1: free-running, judged by silent cycles)
        self.bad_at_value = 0   # the discarded count when the latest valid value arrived

    def periods(self, h: float) -> None:
        """Set ``stale_n`` from ``stale_s`` for the period ``h`` (at least one period)."""
        self.stale_n = max(1, round(self.stale_s / h))

    def observe(self, s: Sample, now: float, h: float) -> None:
        """This cycle's sample (the cycle runs at ``now``, period ``h``), and the history the
        rules look at."""
        v = s.value
        hl = s.health
        prev = self.value
        self.delta = v - prev
        self.value = v
        t = s.t
        if t != t:
            t = NEVER_T                            # NaN: no valid value ever
        if t != self.t:
            self.t = t
            self.bad_at_value = hl.bad_frames      # a new valid value: discarded data counted from here
            # whole periods it was already late: 0 if it arrived within the period before
            # the cycle that sees it, at any phase (a micro-period tolerance for k·h rounding)
            age = now - t
            self.silent = 0 if age <= h * (1 + 1e-6) or age == math.inf else math.ceil(age / h - 1e-6) - 1
        else:
            self.silent += 1
        self.unanswered = s.unanswered
        if self.stuck_check:
            self.same = self.same + 1 if v == prev else 0
        self.state = hl.state
        self.cause = hl.cause
        b = hl.bad_frames
        self.bad_run = self.bad_run + 1 if b > self.bad else 0
        self.bad = b
