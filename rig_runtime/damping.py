"""The variable damping of the yaw dynamics, the paper's (7) (Sec. 4.3.3), written once.

    D(u̇) = D_min                                        if |u̇| >= c_udot_max
           D_max − |u̇|/c_udot_max (D_max − D_min)       otherwise

u̇ the derivative of the input low-pass filtered at ``u_filter_hz`` (10 Hz): with the input held
over a period, uf' = (u − uf)/τ, τ = 1/(2π u_filter_hz), so u̇ = e/τ with e = u − uf the filter's
residual, which decays by exp(−h/τ) over a period and jumps by each change of u.

Used by the simulated plant (sim_backend/plant.py), the observer's yaw model
(rig_runtime/observer.py) and a control law that knows its damping (:class:`InputDamping`: the
law's own commanded current through the same filter and (7), rig_runtime/control.py). Plain
floats (no numpy): the loop steps it every cycle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


def damping(rho, D_min: float, D_max: float, select=None):
    """(7) at ρ = |u̇| / c_udot_max: D_min from ρ = 1 on, rising linearly to D_max at ρ = 0.
    ``select(cond, a, b)`` (e.g. numpy.where) evaluates it for an array of ρ, the same line."""
    if select is not None:
        return select(rho >= 1.0, D_min, D_max - rho * (D_max - D_min))
    return D_min if rho >= 1.0 else D_max - rho * (D_max - D_min)


@dataclass(frozen=True)
class YawDamping:
    """A carrier's yaw parameters a law needs to know its damping and schedule its yaw loop on it
    (the model values of the config, ``plant.carrier(c)``): ω0, K of (6) and (7)'s."""

    omega0: float
    K: float
    D_min: float
    D_max: float
    c_udot_max: float
    u_filter_hz: float

    @classmethod
    def of(cls, p) -> "YawDamping":
        """From a carrier's resolved plant parameters (``cfg.plant.carrier(c)``)."""
        return cls(p.omega0, p.K, p.D_min, p.D_max, p.c_udot_max, p.u_filter_hz)

    @property
    def tau(self) -> float:
        return 1.0 / (2.0 * math.pi * self.u_filter_hz)


class InputDamping:
    """D̂ of (7) from a sequence of held inputs (the law's own commands, one per period h):
    the 10 Hz filter's residual e advanced exactly as the plant advances it. ``now`` is the
    damping at the end of the last period (before the next input change)."""

    __slots__ = ("m", "e", "u", "ef", "irc", "now")

    def __init__(self, m: YawDamping, h: float, u0: float = 0.0):
        self.m = m
        self.ef = math.exp(-h / m.tau)
        self.irc = 1.0 / (m.tau * m.c_udot_max)
        self.start(u0)

    def start(self, u0: float) -> None:
        """The law starts from input u0 (the filter settled on it) and takes D̂ = D_min for its
        first command: a closed loop's first commands move the current (the plant's D drops to
        D_min with them), and gains at D_max for one period would kick the current by up to σ
        times the P term (docs/vehicle.md §3). From the first :meth:`hold` on, D̂ is (7)'s."""
        self.e, self.u = 0.0, u0
        self.now = self.m.D_min

    def hold(self, u: float) -> None:
        """Input ``u`` held over the next period: the residual jumps by the change, decays over h."""
        r = self.e + (u - self.u)
        self.u = u
        self.e = r * self.ef
        rho = (r if r >= 0.0 else -r) * self.ef * self.irc
        self.now = damping(rho, self.m.D_min, self.m.D_max)

    def correct(self, u: float) -> None:
        """The last period's input was ``u``, not what :meth:`hold` was given (a limit downstream)."""
        if u != self.u:
            self.e += (u - self.u) * self.ef
            self.u = u
            rho = abs(self.e) * self.irc
            self.now = damping(rho, self.m.D_min, self.m.D_max)
