"""Which drive outages the loop can run on, decided by the coupled analysis at configure
time (the loop only looks the answer up).

A carrier's yaw is steered by the difference of its wheel currents. The allocation
(``rig_runtime.allocation``) gives the remaining wheel of a carrier that lost one the whole
differential command, within its current limit: the linear loop is the nominal one, with
half the authority (``i_max`` instead of ``2·i_max``). A carrier that lost both wheels has
Δu = 0: its yaw is free, and whether the other carrier alone holds both lateral positions
(the coupled (2a)/(2b)) is the coupled loop with that carrier in contact but not controlled
— :func:`rig_runtime.coupled.at_speed` on that layout, at every analysed speed
(:func:`rig_runtime.coupled.speeds`), both directions where the schedule runs them.

numpy only through coupled.py; built once per run (``ControlLoop``), never per cycle."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Collection, Mapping, Optional

import numpy as np

from . import coupled
from .config import RigConfig
from .lanes import CARRIER_WHEELS


@dataclass(frozen=True)
class Decision:
    """The answer for one set of lost wheels at one speed: whether the reconfigured loop is
    stable (the sampled loop's spectral radius below 1 at the analysed speed nearest the
    measured one, in the same direction, and the carriers still controlled have authority),
    the numbers, and one line saying why."""
    stable: bool
    radius: float
    v: float                        # the analysed speed looked up (NaN: none in that direction)
    uncontrolled: tuple[str, ...]   # carriers with both wheels lost
    why: str


@dataclass(frozen=True)
class OutageTable:
    """Per set of carriers with both wheels lost (empty: every carrier keeps at least one
    wheel), the sampled loop's spectral radius at each analysed speed."""
    controlled: tuple[str, ...]                 # the carriers the lanes control, in contact
    in_contact: tuple[str, ...]
    speeds: tuple[float, ...]
    radius: Mapping[frozenset, tuple[float, ...]]   # uncontrolled carriers -> radius per speed
    i_max: Mapping[str, float]                  # wheel -> its current limit (A)

    def wheels_of(self, carrier: str) -> tuple[str, str]:
        return CARRIER_WHEELS[carrier]

    def carrier_of(self, wheel: str) -> Optional[str]:
        for c in self.controlled:
            if wheel in CARRIER_WHEELS[c]:
                return c
        return None

    def decide(self, lost: Collection[str], v: float) -> Decision:
        """Is the loop stable with the wheels ``lost``, at the measured speed ``v``?"""
        lost = set(lost)
        out = tuple(c for c in self.controlled if set(CARRIER_WHEELS[c]) <= lost)
        if any(self.carrier_of(w) is None for w in lost):
            return Decision(False, math.nan, math.nan, out, "a drive of a carrier no lane controls")
        if len(out) == len(self.controlled):
            return Decision(False, math.nan, math.nan, out, "no controlled carrier keeps a wheel")
        same = [k for k, s in enumerate(self.speeds) if s * v > 0] if math.isfinite(v) else []
        if not same:
            return Decision(False, math.nan, math.nan, out, f"no analysed speed in the direction of v = {v:+.3f} m/s")
        k = min(same, key=lambda i: abs(self.speeds[i] - v))
        r = self.radius[frozenset(out)][k]      # (every carrier uncontrolled was refused above)
        vs = self.speeds[k]
        what = (f"{'/'.join(out)} carrier uncontrolled" if out else "every carrier keeps a wheel")
        ok = r < 1.0
        return Decision(ok, r, vs, out, f"{what}: sampled loop spectral radius {r:.4f} at v = {vs:+.2f} m/s "
                                        f"({'stable' if ok else 'not stable'})")


def table(cfg: RigConfig) -> OutageTable:
    """The outage table of a config: the coupled loop for every set of controlled carriers
    that lost both wheels, at every analysed speed."""
    lay = coupled.layout(cfg)
    vs, _ = coupled.speeds(cfg)
    radius = {}
    ctl = lay.controlled
    for k in range(len(ctl)):           # every carrier uncontrolled: never a reconfiguration
        for gone in _subsets(ctl, k):
            sub = coupled.Layout(lay.carriers, tuple(c for c in ctl if c not in gone), lay.n_plant)
            radius[frozenset(gone)] = tuple(_radius(cfg, v, sub) for v in vs)
    rated = cfg.hardware.drive_rated_current_A
    i_max = {d.wheel: min(rated, d.rated_current_A) for d in cfg.devices.can.drives}
    return OutageTable(ctl, lay.carriers, tuple(vs), radius, i_max)


def _radius(cfg: RigConfig, v: float, lay: "coupled.Layout") -> float:
    """The sampled loop's spectral radius at v, the largest over the damping cases the
    stability gate judges (``coupled.damping_cases``; as ``coupled.at_speed`` without the
    continuous eigenvalues and the reported-only cases)."""
    worst = 0.0
    for D in coupled.damping_cases(cfg, v, lay):
        with np.errstate(all="ignore"):
            z = np.linalg.eigvals(coupled.sampled_matrix(cfg, v, D, lay))
        r = float(np.max(np.abs(z))) if len(z) else 0.0
        worst = max(worst, r if math.isfinite(r) else math.inf)
    return worst


def _subsets(items: tuple, k: int):
    if k == 0:
        yield ()
        return
    for i, x in enumerate(items):
        for rest in _subsets(items[i + 1:], k - 1):
            yield (x,) + rest
