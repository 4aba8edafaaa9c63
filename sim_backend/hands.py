"""The simulated operator's hands (``sim: {operator: commission}``): what the person at the
rig does when ``rig commission`` asks, in the procedure's order (docs/commissioning.md).

1. Until the power stages are first on, the passive motions, over and over, one after the
   other, each a smooth bump (raised cosine) and let go again: push the vehicle to the left,
   push its rear end to the left (the front end held: only the rear carrier moves
   laterally), turn the rear carrier nose-left, turn the front carrier nose-right. The hands
   let go when every power stage is first on (the runtime's first ARM), wherever they are:
   the largest step the lasers then see (1.5 mm lateral, 3 mrad in 5 ms) stays inside
   ``limits.laser_step_max`` and ``limits.psi_rate_max``. The motion is a displacement of the
   pose the lasers see (the plant's own state is left alone: by hand, nothing of the rolling
   dynamics is involved).
2. The carriers are off the rollers, their wheels at rest, from the start (the lasers are
   moved by hand and the lifted bumps made so) until ``sim.operator_lifted_sessions``
   power-on sessions have ended (2: ``lifted-rear`` and ``lifted-front``); then they are set
   on the rollers for the encoders and the contact bumps. Only the wheels
   are lifted (sim_backend/lifted_wheels.py); the plant's yaw and lateral dynamics are left
   as they are (a lifted carrier's yaw answers the current as in contact, with other damping).
"""

from __future__ import annotations

import math
from typing import NamedTuple

PERIOD_S = 2.0          # one round of the four motions
PUSH_S = 0.4            # each motion: in and out again
LATERAL_M = 1.5e-3      # the vehicle (or its rear end) pushed 1.5 mm to the left (+y)
YAW_RAD = 3.0e-3        # a carrier turned by 3 mrad
STARTS = {"lateral": 0.1, "rear_end": 0.6, "rear": 1.1, "front": 1.6}     # s into each round


class HandOffset(NamedTuple):
    dy_f: float         # added to y_f, m
    dy_r: float         # added to y_r, m
    dpsi_af: float      # rad
    dpsi_ar: float      # rad


NO_HANDS = HandOffset(0.0, 0.0, 0.0, 0.0)


def _bump(tau: float, start: float) -> float:
    x = (tau - start) / PUSH_S
    return 0.5 * (1.0 - math.cos(2.0 * math.pi * x)) if 0.0 <= x < 1.0 else 0.0


def offset(t: float) -> HandOffset:
    """The hands' displacement at simulated time ``t``."""
    tau = t % PERIOD_S
    lateral = LATERAL_M * _bump(tau, STARTS["lateral"])
    return HandOffset(lateral, lateral + LATERAL_M * _bump(tau, STARTS["rear_end"]),
                      -YAW_RAD * _bump(tau, STARTS["front"]), YAW_RAD * _bump(tau, STARTS["rear"]))


def carriers_lifted(sessions_ended: int, lifted_sessions: int) -> bool:
    """Whether the operator holds the carriers off the rollers: from the start until
    ``lifted_sessions`` sessions of power have ended."""
    return sessions_ended < lifted_sessions
