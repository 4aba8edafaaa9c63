"""The output limiter: what a lane's command becomes before it is sent. Saturated at the
carrier's ±u_max and rate limited (``du_max``) while RUNNING, ramped to zero while STOPPING
(``stop_ramp_s`` from u_max to 0), zero otherwise. The supervisor decides the state and
judges the command (the output rules); this only shapes it."""

from __future__ import annotations

import math
from typing import Sequence

from ..config import Limits


class Limiter:
    """The last current sent per carrier and the steps derived once from the frozen limits."""

    __slots__ = ("_u_prev", "_du", "_ramp")

    def __init__(self, limits: Limits, h: float, carriers: Sequence[str]):
        self._u_prev = dict.fromkeys(carriers, 0.0)
        self._du = limits.du_max * h
        self._ramp = limits.u_max * h / limits.stop_ramp_s if limits.stop_ramp_s > 0 else math.inf

    def running(self, carrier: str, u: float, u_max: float) -> float:
        """Saturated at ±u_max, then at most ``du_max·h`` from the last current sent."""
        u = u_max if u > u_max else (-u_max if u < -u_max else u)
        p, d = self._u_prev[carrier], self._du
        u = p + d if u > p + d else (p - d if u < p - d else u)
        self._u_prev[carrier] = u
        return u

    def stopping(self, carrier: str) -> float:
        """One ramp step towards zero."""
        p, r = self._u_prev[carrier], self._ramp
        u = p - r if p > r else (p + r if p < -r else 0.0)
        self._u_prev[carrier] = u
        return u

    def zero(self, carrier: str) -> float:
        self._u_prev[carrier] = 0.0
        return 0.0

    def reset(self) -> None:
        for c in self._u_prev:
            self._u_prev[c] = 0.0

    def last(self, carrier: str) -> float:
        """The current sent for ``carrier`` in the latest cycle."""
        return self._u_prev[carrier]

    @property
    def at_rest(self) -> bool:
        """Every output is zero (STOPPING may end)."""
        return not any(self._u_prev.values())
