"""The hysteresis of the yaw dynamics, the paper's Bouc-Wen state (9) (Sec. 4.3.4), written once:
the simulated plant (sim_backend/plant.py, n = 1) and the observer's yaw model
(rig_runtime/observer.py) use the same map. Plain floats: the observer steps it in the cycle."""

from __future__ import annotations

import math


def zmap(z: float, dpsi: float, A: float, beta: float, gamma: float) -> float:
    """The Bouc-Wen state (9) (n = 1) after a monotone change ``dpsi`` of ψ: dz/dψ = A − κ z,
    κ = β sign(dψ) + γ sign(z), exact, through at most one zero crossing of z. The simulated plant's
    state (sim_backend/plant.py) and the observer's estimate of it both move by this map."""
    if dpsi == 0.0:
        return z
    s = 1.0 if dpsi > 0.0 else -1.0
    for _ in range(2):
        sig = 1.0 if z > 0.0 else (-1.0 if z < 0.0 else (s if A >= 0.0 else -s))
        kap = beta * s + gamma * sig
        slope = A - kap * z
        kd = kap * dpsi
        zn = z - slope * math.expm1(-kd) / kap if kd != 0.0 else z + slope * dpsi
        if z == 0.0 or zn * z >= 0.0:
            return zn
        d = math.log1p(-kap * z / A) / kap if (kap != 0.0 and A != 0.0) else -z / slope
        dpsi -= d
        z = 0.0
        if dpsi * s <= 0.0:
            return 0.0
    return z
