"""Scenarios: the reference profile for y_ref, open-loop inputs, disturbances and timed
fault injections, from YAML files in ``configs/scenarios/``.

``rig run`` uses the reference (or the open-loop input) and the duration; the simulated
plant also applies the disturbances and fault injections. The profile is mm at the edge
(``y_mm``) and metres inside.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

from . import schema
from .config import CONFIG_DIR, _read_yaml
from .errors import ConfigError
from .schema import check, nonneg, positive, probability

SCENARIO_DIR = CONFIG_DIR / "scenarios"
FAULT_KINDS = ("dropout", "corrupt", "stuck", "offset", "out_of_range", "no_heartbeat", "bus_error", "stall", "drift")


@dataclass(frozen=True, kw_only=True)
class RefPoint:
    t: float = check(nonneg)
    y_mm: float
    ramp_s: float = check(nonneg, default=0.0)   # 0 = step at t; else a ramp from the previous value


@dataclass(frozen=True, kw_only=True)
class SpeedPoint:
    t: float = check(nonneg)
    v: float                                     # roller surface speed, m/s (sign = running direction)
    ramp_s: float = check(nonneg, default=0.0)   # 0 = jump at t; else a ramp from the previous value


@dataclass(frozen=True, kw_only=True)
class SineInput:
    amplitude_A: float
    freq_mhz: float = check(positive)
    bias_A: float = 0.0
    t0: float = check(nonneg, default=0.0)


@dataclass(frozen=True, kw_only=True)
class OpenLoop:
    carrier: Literal["front", "rear", "both"] = "rear"     # both: every carrier plays it (the controller off)
    steps: tuple[tuple[float, float], ...] = ()      # [[t, u_A], ...]
    sine: Optional[tuple[SineInput, ...]] = None      # consecutive sines (e.g. 4.8 then 2.4 mHz)

    def __post_init__(self) -> None:
        if bool(self.steps) == bool(self.sine):
            raise ConfigError(None, "steps", "either steps or sine (one of them, not both)")
        _increasing([t for t, _ in self.steps], "steps", "[t, u_A] pairs with times >= 0, increasing")
        _increasing([s.t0 for s in self.sine or ()], "sine", "sines whose t0 increase")

    @property
    def carriers(self) -> tuple[str, ...]:
        """The carriers that play the input."""
        return ("front", "rear") if self.carrier == "both" else (self.carrier,)


@dataclass(frozen=True, kw_only=True)
class Disturbance:
    kind: Literal["pulse", "constant"]
    carrier: Literal["front", "rear"] = "rear"
    t: float = check(nonneg)
    duration_s: float = check(positive)
    F_y: float = 0.0      # lateral force, N
    M_z: float = 0.0      # yaw moment, N m


@dataclass(frozen=True, kw_only=True)
class FaultInjection:
    kind: Literal["dropout", "corrupt", "stuck", "offset", "out_of_range", "no_heartbeat", "bus_error", "stall", "drift",
                  "motor_outage"]
    t: float = check(nonneg)
    duration_s: float = check(positive, default=1e9)
    device: str = ""                 # laser role, wheel (fl…rr) or F/T name; "" for stall
    fraction: float = check(probability, default=0.5)   # corrupt / bus_error
    amount: float = 0.0              # offset: m for lasers, rad/s for wheels, N for F/T
    rate_mm_s: float = 0.0           # drift (lasers): the reading creeps off the truth at this rate, mm/s
    mode: Literal["announced", "silent"] = "announced"   # motor_outage (drives): the drive faults, or not


@dataclass(frozen=True, kw_only=True)
class Scenario:
    name: str
    description: str = ""
    duration_s: float = check(positive)
    reference: tuple[RefPoint, ...] = (RefPoint(t=0.0, y_mm=0.0),)
    # per-carrier references: in YAML `reference: {front: [...], rear: [...]}` (a list = every carrier)
    references: dict[Literal["front", "rear"], tuple[RefPoint, ...]] = field(default_factory=dict)
    speed: tuple[SpeedPoint, ...] = ()   # the roller speed profile (empty: the plant's fixed v)
    open_loop: Optional[OpenLoop] = None
    disturbances: tuple[Disturbance, ...] = ()
    faults: tuple[FaultInjection, ...] = ()
    expect_fault: Optional[str] = None   # for fault scenarios: the check expected to trip
    # identification experiments (Sec. 4; docs/identification.md): the kind is stored in the log
    experiment: Optional[Literal["free-response", "steps", "sine", "open-loop-steps"]] = None
    lifted_carrier: Optional[Literal["rear", "front"]] = None   # simulator: the carrier off the rollers (Sec. 4.3.2)
    initial_psi_mrad: Optional[float] = None   # simulator: the open-loop carrier's yaw angle at the start
    source: str = ""

    def __post_init__(self) -> None:
        if not self.reference:
            raise ConfigError(None, "reference", "at least one point {t, y_mm}")
        _increasing([p.t for p in self.reference], "reference", "points in increasing time order")
        for carrier, points in self.references.items():
            if not points:
                raise ConfigError(None, f"reference.{carrier}", "at least one point {t, y_mm}")
            _increasing([p.t for p in points], f"reference.{carrier}", "points in increasing time order")
        _increasing([p.t for p in self.speed], "speed", "points {t, v, ramp_s} in increasing time order")

    def reference_for(self, carrier: str) -> tuple[RefPoint, ...]:
        """The reference points of ``carrier``: its own, else the common list."""
        return self.references.get(carrier, self.reference)

    def speed_profile(self, v0: float) -> "Profile":
        """The roller speed v(t) (m/s) over scenario time; the constant ``v0`` (the plant's v)
        without a ``speed:`` profile."""
        if not self.speed:
            return Profile([0.0], [v0], [0.0])
        return Profile([p.t for p in self.speed], [p.v for p in self.speed], [p.ramp_s for p in self.speed])


def _increasing(ts: list[float], key: str, expected: str) -> None:
    """Times >= 0 and strictly increasing (two points at one time would be ambiguous)."""
    for i, t in enumerate(ts):
        if t < 0 or (i and not t > ts[i - 1]):
            raise ConfigError(None, f"{key}[{i}]", expected, t)


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A scenario by name (``configs/scenarios/NAME.yaml``) or by path."""
    p = Path(name_or_path)
    if not p.suffix:
        p = SCENARIO_DIR / f"{name_or_path}.yaml"
    if not p.exists():
        known = ", ".join(sorted(q.stem for q in SCENARIO_DIR.glob("*.yaml")))
        raise ConfigError(str(p), "", f"an existing scenario file (known scenarios: {known})")
    data = _read_yaml(p)
    if isinstance(data.get("reference"), dict):      # per-carrier references
        data = {**data, "references": data["reference"]}
        del data["reference"]
    try:
        sc = schema.build(Scenario, data, "", str(p.resolve()))
    except ConfigError as e:
        key = e.key_path.replace("references", "reference", 1) if e.key_path.startswith("references") else e.key_path
        raise ConfigError(str(p.resolve()), key, e.expected, e.got) from None
    return Scenario(**{**{f: getattr(sc, f) for f in sc.__dataclass_fields__}, "source": str(p.resolve())})


class Profile:
    """A piecewise profile x(t): at each point a jump (``ramp_s`` 0) or a ramp from the
    previous value; before the first point, the first value."""

    def __init__(self, t: list[float], x: list[float], ramp: list[float]):
        self.t, self.y, self.ramp = t, x, ramp

    def __call__(self, t: float) -> float:
        i = bisect.bisect_right(self.t, t) - 1
        if i < 0:
            return self.y[0]
        r = self.ramp[i]
        if r > 0 and i > 0 and t < self.t[i] + r:
            y0 = self.y[i - 1]
            return y0 + (self.y[i] - y0) * (t - self.t[i]) / r
        return self.y[i]


class Reference(Profile):
    """y_ref(t) in metres from the scenario's points (steps and ramps)."""

    def __init__(self, points: tuple[RefPoint, ...]):
        super().__init__([p.t for p in points], [p.y_mm * 1e-3 for p in points], [p.ramp_s for p in points])

    def steps(self) -> list[tuple[float, float, float]]:
        """(t0, from_m, to_m) for every change of the reference (step or ramp start)."""
        out = []
        for i in range(1, len(self.t)):
            if self.y[i] != self.y[i - 1]:
                out.append((self.t[i], self.y[i - 1], self.y[i]))
        return out


def open_loop_input(ol: OpenLoop):
    """The open-loop input u(t) (A) of a scenario."""
    from .control import Sinusoid, StepSequence
    if ol.sine:
        sines = [Sinusoid(s.amplitude_A, s.freq_mhz, s.bias_A, s.t0) for s in ol.sine]
        starts = [s.t0 for s in ol.sine]

        def u(t: float) -> float:
            i = bisect.bisect_right(starts, t) - 1
            return sines[max(i, 0)](t)
        return u
    return StepSequence(ol.steps)
