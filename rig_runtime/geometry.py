"""Sensor geometry of Sec. 2: raw laser distances and wheel speeds -> y, ψ, Δω.

Conventions (docs/conventions.md): x forward, y to the left, z up; ψ positive
counter-clockwise seen from above (nose to the left); Δω = ω_left − ω_right.

The paper writes ``sin(ψ_m) = (b_f − b_r)/l_L`` and ``ψ_af = tan((s_fl − s_fr)/d0)``.
An angle is obtained from a ratio by an inverse function, and for a straight plate
(or carrier face) seen by two parallel beams a baseline apart, the ratio of the distance
difference to the baseline is the *tangent* of the angle: we use ``atan`` for ψ_m, ψ_af
and ψ_ar. The carriers sit at ±l0 along the frame axis, so their lateral offset is
``l0·sin(ψ_m)`` exactly, as the paper writes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from operator import itemgetter
from typing import Mapping, NamedTuple

from .config import Geometry


class Measurement(NamedTuple):
    """Derived quantities of one cycle (SI: m, rad, rad/s). Immutable; a named tuple
    because it is built every 5 ms and a frozen dataclass costs three times as much."""

    y_m: float      # lateral displacement of the frame centre
    psi_m: float    # angle between rail and frame
    y_f: float      # lateral displacement of the front carrier
    y_r: float      # lateral displacement of the rear carrier
    psi_af: float   # angle between frame and front carrier
    psi_ar: float   # angle between frame and rear carrier
    psi_f: float    # ψ_af + ψ_m: front carrier to rail
    psi_r: float    # ψ_ar + ψ_m: rear carrier to rail
    dw_f: float     # ω_fl − ω_fr
    dw_r: float     # ω_rl − ω_rr

    def carrier(self, name: str) -> tuple[float, float, float]:
        """(y, ψ, Δω) of the ``front`` or ``rear`` carrier: ψ is the carrier's angle to the
        frame (ψ_af, ψ_ar), the angle its yaw lasers measure and the PI-PD law controls."""
        if name == "rear":
            return self.y_r, self.psi_ar, self.dw_r
        if name == "front":
            return self.y_f, self.psi_af, self.dw_f
        raise KeyError(name)


@dataclass(frozen=True, slots=True)
class Pose:
    """Physical pose of frame and carriers, the input of the ideal sensor model."""

    y_m: float = 0.0
    psi_m: float = 0.0
    psi_af: float = 0.0
    psi_ar: float = 0.0


@dataclass(frozen=True, slots=True)
class Readings:
    """Ideal laser distances (m) for a pose."""

    b_f: float
    b_r: float
    s_fl: float
    s_fr: float
    s_rl: float
    s_rr: float


#: the channels the geometry reads, by name, resolved into one getter each at import: a cycle
#: takes the six distances and the four speeds in two C calls, not ten lookups
_LASERS = itemgetter("b_f", "b_r", "s_fl", "s_fr", "s_rl", "s_rr")
_WHEELS = itemgetter("fl", "fr", "rl", "rr")
_atan, _sin = math.atan, math.sin


def measure(v: Mapping[str, float], geo: Geometry) -> Measurement:
    """Sec. 2 geometry from the latest values by name: the lasers by role (``b_f`` … ``s_rr``,
    m) and the wheel speeds by wheel (``fl`` … ``rr``, rad/s). Scalar math only: this runs
    every cycle."""
    b_f, b_r, s_fl, s_fr, s_rl, s_rr = _LASERS(v)
    fl, fr, rl, rr = _WHEELS(v)
    y_m = 0.5 * (b_f + b_r) - geo.b0
    psi_m = _atan((b_f - b_r) / geo.l_L)
    lat = geo.l0 * _sin(psi_m)
    psi_af = _atan((s_fl - s_fr) / geo.d0)
    psi_ar = _atan((s_rl - s_rr) / geo.d0)
    y_f, y_r = y_m + lat, y_m - lat
    psi_f, psi_r = psi_af + psi_m, psi_ar + psi_m
    dw_f, dw_r = fl - fr, rl - rr
    return Measurement(y_m=y_m, psi_m=psi_m, y_f=y_f, y_r=y_r, psi_af=psi_af, psi_ar=psi_ar,
                       psi_f=psi_f, psi_r=psi_r, dw_f=dw_f, dw_r=dw_r)


def ideal_readings(pose: Pose, geo: Geometry, s0: float = 0.0375) -> Readings:
    """Distances an ideal sensor set reads for ``pose``; ``s0`` is the yaw lasers'
    nominal distance (it cancels in the geometry)."""
    db = 0.5 * geo.l_L * math.tan(pose.psi_m)
    dsf = 0.5 * geo.d0 * math.tan(pose.psi_af)
    dsr = 0.5 * geo.d0 * math.tan(pose.psi_ar)
    return Readings(geo.b0 + pose.y_m + db, geo.b0 + pose.y_m - db,
                    s0 + dsf, s0 - dsf, s0 + dsr, s0 - dsr)


def pose_from_carriers(y_f: float, y_r: float, psi_af: float, psi_ar: float, geo: Geometry) -> Pose:
    """The frame pose that puts the carriers at lateral displacements y_f, y_r."""
    s = (y_f - y_r) / (2.0 * geo.l0)
    if not -1.0 < s < 1.0:
        raise ValueError(f"carrier displacements {y_f}, {y_r} m are not reachable with l0 = {geo.l0} m")
    return Pose(0.5 * (y_f + y_r), math.asin(s), psi_af, psi_ar)
