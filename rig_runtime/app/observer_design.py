"""Design of the lateral-displacement observers at configure time (docs/observer.md).

The linear model of Sec. 4 per carrier — lateral (2b) (or (2a) for the front), yaw (6)
without hysteresis, relation (4) as a measurement — held over h (zero-order hold, by the
matrix exponential), the process noise integrated over h (Van Loan), the sensor noise of
``observer.noise`` carried through the Sec. 2 geometry, and the steady-state Kalman gain
from scipy's discrete algebraic Riccati solver, for the two measurement sets the cycle
uses, and the growth of ŷ's error covariance while no lateral laser is used (an outage: the
fixed yaw-and-Δω gains run from the full filter's steady state). The result is plain floats (:class:`rig_runtime.observer.ObserverDesign`): the cycle's
module imports neither this module nor numpy/scipy.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import expm, solve_discrete_are

from ..config import Observer as ObserverConfig
from ..config import RigConfig
from ..lanes import CARRIER_WHEELS
from ..observer import ObserverDesign, dw_row

_SCALE = 1e3        # solve in mm, mrad: the covariances are ~1e-12 in SI


def _lateral_weights(cfg: RigConfig, carrier: str) -> tuple[tuple[str, str], tuple[float, float]]:
    """The carrier's lateral lasers (the stronger first) and ∂y/∂reading of the geometry
    (y_r = y_m − l0 sin ψ_m, y_f = y_m + l0 sin ψ_m, y_m = (b_f + b_r)/2 − b0,
    ψ_m = atan((b_f − b_r)/l_L))."""
    g = cfg.geometry
    k = g.l0 / g.l_L
    own, other = ("b_r", "b_f") if carrier == "rear" else ("b_f", "b_r")
    return (own, other), (0.5 + k, 0.5 - k)


def continuous_model(cfg: RigConfig, carrier: str, D: float) -> tuple[np.ndarray, np.ndarray]:
    """A (3×3) and the input matrix for (u, y_other, F_y, 1) of the carrier's model
    (x = y, ψ, ψ̇). The lateral force enters as the plant's creep velocity |v| F_y/(2 c22),
    c22 ≈ c̄11 (the plant model's ESTIMATE, docs/plant-model.md §3)."""
    p = cfg.plant
    a, cyv, w0 = p.a_lat, p.c_y * p.v, p.omega0
    fy = abs(p.v) / (2.0 * p.c11)
    w2 = w0 * w0
    if carrier == "rear":
        a_own, a_other, off = -a, a, p.v / (2 * p.l0) * p.y_off
    else:
        a_own, a_other, off = a, -a, 0.0
    A = np.array([[a_own, cyv, 0.0], [0.0, 0.0, 1.0], [0.0, -w2, -2 * D * w0]])
    Bc = np.array([[0.0, a_other, fy, off], [0.0, 0.0, 0.0, 0.0], [p.K * w2, 0.0, 0.0, w2 * p.psi_off]])
    return A, Bc


def discretise(A: np.ndarray, Bc: np.ndarray, Qc: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zero-order hold of (A, Bc) and the process noise Qc integrated over h (Van Loan)."""
    n, m = A.shape[0], Bc.shape[1]
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A, Bc
    E = expm(M * h)
    V = expm(np.block([[-A, Qc], [np.zeros((n, n)), A.T]]) * h)
    Ad = E[:n, :n]
    Qd = Ad @ V[:n, n:]
    return Ad, E[:n, n:], 0.5 * (Qd + Qd.T)


def steady_state(Ad: np.ndarray, C: np.ndarray, Qd: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steady-state Kalman gain K, innovation covariance S and predictor covariance P (SI)
    of the discrete Riccati equation (solved in mm/mrad units for conditioning)."""
    s2 = _SCALE ** 2
    P = solve_discrete_are(Ad.T, C.T, Qd * s2, R * s2)
    S = C @ P @ C.T + R * s2
    K = P @ C.T @ np.linalg.inv(S)
    return K, S / s2, P / s2


def steady_gain(Ad: np.ndarray, C: np.ndarray, Qd: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Steady-state Kalman gain K and innovation covariance S (see :func:`steady_state`)."""
    K, S, _ = steady_state(Ad, C, Qd, R)
    return K, S


def outage_sigma_y(Ad: np.ndarray, Qd: np.ndarray, P_full: np.ndarray, K_full: np.ndarray, C: np.ndarray,
                   K_nl: np.ndarray, C_nl: np.ndarray, R_nl: np.ndarray, n_max: int,
                   rtol: float = 1e-9) -> tuple[float, ...]:
    """σ of ŷ's error (m) after k = 0, 1, … cycles without a lateral update: the corrected
    covariance starts at the full filter's steady state (I − K C) P and is propagated with
    the fixed no-lateral gain (Joseph form, exact for a suboptimal gain):
    P⁻ = A P⁺ Aᵀ + Q, P⁺ = (I − K C) P⁻ (I − K C)ᵀ + K R Kᵀ. Stops once σ changes by less than
    ``rtol`` relative (the last value then holds) or after ``n_max`` cycles."""
    I = np.eye(Ad.shape[0])
    P = (I - K_full @ C) @ P_full
    M = I - K_nl @ C_nl
    KRK = K_nl @ R_nl @ K_nl.T
    out = [math.sqrt(P[0, 0])]
    for _ in range(n_max):
        P = M @ (Ad @ P @ Ad.T + Qd) @ M.T + KRK
        s = math.sqrt(P[0, 0])
        done = abs(s - out[-1]) <= rtol * s
        out.append(s)
        if done:
            break
    return tuple(out)


def design(cfg: RigConfig, carrier: str, ocfg: ObserverConfig | None = None) -> ObserverDesign:
    """The carrier's filter as plain numbers (see the module docstring)."""
    o = ocfg if ocfg is not None else (cfg.observer or ObserverConfig())
    p, g = cfg.plant, cfg.geometry
    h = cfg.controller.h
    D = o.D if o.D is not None else p.D_min
    A, Bc = continuous_model(cfg, carrier, D)
    Qc = np.diag([o.q_y ** 2, 0.0, o.q_psi_acc ** 2])
    Ad, Bd, Qd = discretise(A, Bc, Qc, h)
    gy, gr, gu = dw_row(cfg)
    lasers, weights = _lateral_weights(cfg, carrier)
    n = o.noise
    r_lat = sum(w * w for w in weights) * n.lateral_laser_m ** 2
    r_psi = 2.0 * n.yaw_laser_m ** 2 / g.d0 ** 2
    r_dw = 2.0 * n.encoder_rad_s ** 2
    C = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [gy, 0.0, gr]])
    K_full, S_full, P_full = steady_state(Ad, C, Qd, np.diag([r_lat, r_psi, r_dw]))
    R_nl = np.diag([r_psi, r_dw])
    K_nl, S_nl = steady_gain(Ad, C[1:], Qd, R_nl)
    # an outage lasts at most degraded.max_s (then the run ends): tabulate no further
    n_max = int(math.ceil(cfg.degraded.max_s / h)) + 1
    sig = outage_sigma_y(Ad, Qd, P_full, K_full, C, K_nl, C[1:], R_nl, n_max)
    left, right = CARRIER_WHEELS[carrier]
    flat = lambda M: tuple(float(v) for v in np.asarray(M).ravel())     # noqa: E731
    return ObserverDesign(
        carrier=carrier, A=flat(Ad), B=flat(Bd[:, 0]), E=flat(Bd[:, 1]), F=flat(Bd[:, 2]), c=flat(Bd[:, 3]),
        dw_row=(gy, gr, gu), K_full=flat(K_full), K_nolat=flat(K_nl),
        S_full=flat(np.diag(S_full)), S_nolat=flat(np.diag(S_nl)),
        window=cfg.limits.innovation_window, lateral_lasers=lasers, lateral_weights=weights,
        yaw_lasers=(f"s_{left}", f"s_{right}"), encoders=(left, right),
        ft_sensors=_ft_sensors(cfg, (left, right)), sigma_y_outage=sig)


def _ft_sensors(cfg: RigConfig, wheels: tuple[str, str]) -> tuple[str, ...]:
    """The F/T sensors of the carrier's two wheels, by the name's wheel suffix (``ft_rl``,
    ``ft_rr``: the convention of the shipped configs and the simulator); both or none (one
    side alone is not the carrier's lateral force)."""
    names = [s.name for s in cfg.devices.ft.sensors]
    found = tuple(next((n for n in names if n.endswith(w)), "") for w in wheels)
    return found if all(found) else ()


def designs(cfg: RigConfig) -> dict[str, ObserverDesign]:
    """A design per controlled carrier when the config has an ``observer:`` section (else none)."""
    if cfg.observer is None:
        return {}
    return {c: design(cfg, c) for c in cfg.controlled}


def steady_std(d: ObserverDesign) -> dict[str, float]:
    """The steady-state standard deviations of the innovations (for docs and tests)."""
    return {m: math.sqrt(s) for m, s in zip(("lat", "psi", "dw"), d.S_full)}
