"""The simulated operator's hands (``sim: {operator: commission}``): until the power stages
are first on, they move the vehicle as ``rig
commission``'s passive prompt asks a person to — push the vehicle to the left and let go,
turn the rear carrier nose-left and let go, turn the front carrier nose-right and let go —
over and over, one motion after the other, each a smooth bump (raised cosine).

The hands let go when every power stage is first on (the runtime's first ARM), wherever
they are: the largest step the lasers then see (1.5 mm lateral, 3 mrad in 5 ms) stays
inside ``limits.laser_step_max`` and ``limits.psi_rate_max``.

The motion is a displacement of the pose the lasers see (the plant's own state is left
alone: by hand, nothing of the rolling dynamics is involved)."""

from __future__ import annotations

import math
from typing import NamedTuple

PERIOD_S = 2.0          # one round of the three motions
PUSH_S = 0.4            # each motion: in and out again
LATERAL_M = 1.5e-3      # the vehicle pushed 1.5 mm to the left (+y)
YAW_RAD = 3.0e-3        # a carrier turned by 3 mrad
STARTS = {"lateral": 0.3, "rear": 0.9, "front": 1.5}     # s into each round


class HandOffset(NamedTuple):
    dy: float           # added to y_f and y_r, m
    dpsi_af: float      # rad
    dpsi_ar: float      # rad


NO_HANDS = HandOffset(0.0, 0.0, 0.0)


def _bump(tau: float, start: float) -> float:
    x = (tau - start) / PUSH_S
    return 0.5 * (1.0 - math.cos(2.0 * math.pi * x)) if 0.0 <= x < 1.0 else 0.0


def offset(t: float) -> HandOffset:
    """The hands' displacement at simulated time ``t``."""
    tau = t % PERIOD_S
    return HandOffset(LATERAL_M * _bump(tau, STARTS["lateral"]), -YAW_RAD * _bump(tau, STARTS["front"]),
                      YAW_RAD * _bump(tau, STARTS["rear"]))
