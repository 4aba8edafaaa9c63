"""Allocation: the one place a carrier's differential current command u = i_left − i_right
(A) becomes its wheels' currents, onto the wheels still available and within each wheel's
current limit.

Both wheels available: ±u/2 (each within its limit as long as |u| ≤ 2·i_max, which the
ceilings guarantee for limits.u_max). One wheel lost: the other alone makes the difference
— i_left = u (right lost) or i_right = −u (left lost), saturated at its limit: the same yaw
torque for |u| ≤ i_max, half the authority beyond it (the longitudinal force it adds is
taken by the rollers). Both lost: nothing, the carrier's yaw is free. A lost wheel always
gets 0 A. The supervisor decides which wheels are lost (``Supervisor.wheels_lost``); this
only distributes."""

from __future__ import annotations

import math
from typing import Collection, MutableMapping, Sequence

from .config import WHEELS


def _clip(x: float, lim: float) -> float:
    return lim if x > lim else (-lim if x < -lim else x)


def allocate(u: float, left_ok: bool = True, right_ok: bool = True,
             i_max: float = math.inf) -> tuple[float, float]:
    """(i_left, i_right) for the differential command ``u`` onto the available wheels, each
    within ±``i_max``."""
    if left_ok and right_ok:
        half = 0.5 * u
        return _clip(half, i_max), _clip(-half, i_max)
    if left_ok:
        return _clip(u, i_max), 0.0
    if right_ok:
        return 0.0, _clip(-u, i_max)
    return 0.0, 0.0


def split(u: float) -> tuple[float, float]:
    """Both wheels available: a carrier's differential current ``u`` (A) as its (left, right)
    wheels' currents (±u/2)."""
    return allocate(u)


def wheel_currents(lanes: Sequence, out: MutableMapping[str, float], lost: Collection[str] = (),
                   i_max: float = math.inf) -> MutableMapping[str, float]:
    """Every wheel's current from the lanes' limited outputs (in place; a wheel no lane owns
    and a lost wheel get 0 A). ``lanes``: anything with ``wheels`` (left, right) and ``u``."""
    for w in WHEELS:
        out[w] = 0.0
    for lane in lanes:
        left, right = lane.wheels
        out[left], out[right] = allocate(lane.u, left not in lost, right not in lost, i_max)
    return out


def authority(left_ok: bool, right_ok: bool, i_max: float) -> float:
    """The largest |u| the available wheels can make within ±``i_max`` (2·i_max, i_max, 0)."""
    return (2.0 if left_ok and right_ok else 1.0 if left_ok or right_ok else 0.0) * i_max
