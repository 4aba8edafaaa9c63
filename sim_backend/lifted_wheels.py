"""The wheels of a carrier lifted off the rollers: each spins freely under its own motor's
torque, with no rolling contact and nothing coupling it to the other wheels.

Per wheel, with the current i its motor applies (A):

    J_x dω/dt = k_τ i − J_x ω / FRICTION_TIME_S

J_x (rolling inertia) and k_τ (motor constant) are the plant's (``plant.J_x``, ``plant.k_tau``,
both ESTIMATEs in configs/plant.yaml). The friction term is an ESTIMATE: viscous bearing and
seal drag that lets a lifted wheel spun to roller speed coast down over tens of seconds
(time constant 10 s); Coulomb friction (a breakaway torque of a few 0.01 N m for bearings of
this size, ESTIMATE) is neglected — a commissioning bump's 0.3 A gives k_τ i = 0.15 N m.
The update over a step with the current held is exact (a first-order lag).

The simulated rig uses this for every wheel of a carrier that is off the rollers: the front
carrier with ``plant.front_contact: false``, the rear with a scenario's ``lifted_carrier:
rear``, and any carrier the simulated operator holds lifted for ``rig commission``'s lifted
bumps (sim_backend/hands.py). A carrier set back on the rollers follows the plant again.
"""

from __future__ import annotations

import math
from typing import Mapping

FRICTION_TIME_S = 10.0      # ESTIMATE: J_x / (viscous drag coefficient) of a 1:5 hub-motor wheel


class LiftedWheels:
    """The speeds (rad/s) of the lifted wheels, by wheel name; a wheel not lifted has none."""

    def __init__(self, J_x: float, k_tau: float, friction_time_s: float = FRICTION_TIME_S):
        if not (J_x > 0 and friction_time_s > 0):
            raise ValueError(f"lifted wheels: J_x and the friction time constant must be > 0, got {J_x!r}, "
                             f"{friction_time_s!r}")
        self.J_x, self.k_tau, self.tau = float(J_x), float(k_tau), float(friction_time_s)
        self.omega: dict[str, float] = {}

    def lift(self, wheel: str, omega: float = 0.0) -> None:
        """Take ``wheel`` off the rollers, turning at ``omega`` (rad/s); no-op if it is lifted."""
        self.omega.setdefault(wheel, float(omega))

    def lower(self, wheel: str) -> None:
        """Set ``wheel`` back on the rollers (the plant gives its speed again)."""
        self.omega.pop(wheel, None)

    def step(self, dt: float, currents: Mapping[str, float]) -> None:
        """Advance every lifted wheel by ``dt`` with its motor's current held (A, by wheel)."""
        if not self.omega or dt <= 0.0:
            return
        decay = math.exp(-dt / self.tau)
        gain = self.k_tau * self.tau / self.J_x * (1.0 - decay)     # ω∞ per ampere times the step's share
        for w, om in self.omega.items():
            self.omega[w] = om * decay + gain * currents.get(w, 0.0)
