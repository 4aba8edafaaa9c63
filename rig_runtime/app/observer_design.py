"""Design of the lateral-displacement observers at configure time (docs/observer.md).

The linear model of Sec. 4 per carrier, with that carrier's own plant values
(``cfg.plant.carrier(c)``: a_c, c̄_y,c, l0_c, K, ω0, D, offsets) at a speed v — lateral (2b)
(or (2a) for the front, with its own offset term v/(2 l0_f) y_off,f as the plant has it),
yaw (6) without hysteresis, relation (4) as a measurement (its input term with |v|) — held over h (zero-order hold, by the
matrix exponential), the process noise integrated over h (Van Loan), the sensor noise of
``observer.noise`` carried through the Sec. 2 geometry, and the steady-state Kalman gain
from scipy's discrete algebraic Riccati solver, for the two measurement sets the cycle
uses, and the growth of ŷ's error covariance while no lateral laser is used (an outage: the
fixed yaw-and-Δω gains run from the full filter's steady state). With a speed schedule
(``controller.schedule``) the design is repeated over a grid of speeds (:func:`speed_table`;
the lane picks the nearest grid point of v̂ each cycle); without one it is the single design at
``plant.v``. With both carriers controlled, one joint design for the running gear instead
(:func:`joint_design`, :func:`joint_speed_table`). The result is plain floats (:class:`rig_runtime.observer.ObserverDesign`): the cycle's
module imports neither this module nor numpy/scipy. Each design is kept in this process's memory by its
inputs (``functools.lru_cache``); across processes ``app/runner.py`` keeps what a run
needs on disk (``rig_runtime.memo.across_processes``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable, NamedTuple

import numpy as np

from ..config import Observer as ObserverConfig
from ..config import Geometry, Plant, RigConfig
from ..lanes import CARRIER_WHEELS
from ..observer import ObserverDesign, SpeedTable, dw_row, dw_row_at  # noqa: F401 (dw_row: tests)

_SCALE = 1e3        # solve in mm, mrad: the covariances are ~1e-12 in SI
#: the speed grid's ratio: neighbouring grid speeds 15 % apart, so the design the lane uses is
#: at most √1.15 − 1 = 7.2 % off the measured speed (the grid is anchored at the design speed,
#: exact there); the model's v-terms (a, c̄_y v, Γvb/(2r0²), offsets) are off by as much.
SPEED_RATIO = 1.15
#: the grid's lowest |v| as a fraction of schedule.v_min (inside the standstill band): below it
#: the design of that lowest speed (of v̂'s sign) is used.
SPEED_FLOOR = 0.5
#: designs kept per process, least recently used dropped: a vehicle's speed tables are 2 × 42,
#: a design ~0.1 MB (its outage table: up to degraded.max_s / h floats), so at most ~25 MB
DESIGN_CACHE_SIZE = 256


def _lateral_weights(cfg: RigConfig, carrier: str) -> tuple[tuple[str, str], tuple[float, float]]:
    """The carrier's lateral lasers (the stronger first) and ∂y/∂reading of the geometry
    (:func:`_weights`)."""
    return _weights(cfg.geometry, carrier)


def _weights(g: Geometry, carrier: str) -> tuple[tuple[str, str], tuple[float, float]]:
    """The carrier's lateral lasers (the stronger first) and ∂y/∂reading of the geometry
    (y_r = y_m − l0 sin ψ_m, y_f = y_m + l0 sin ψ_m, y_m = (b_f + b_r)/2 − b0,
    ψ_m = atan((b_f − b_r)/l_L))."""
    k = g.l0 / g.l_L
    own, other = ("b_r", "b_f") if carrier == "rear" else ("b_f", "b_r")
    return (own, other), (0.5 + k, 0.5 - k)


def continuous_model(cfg: RigConfig, carrier: str, D: float, v: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A (3×3) and the input matrix for (u, y_other, F_y, 1) of the carrier's model
    (x = y, ψ, ψ̇) at speed ``v`` (None: plant.v), with the carrier's own values
    (sim_backend/plant.py): a_c = c̄_y,c v/(2 l0_c), input gain c̄_y,c v, offset
    v/(2 l0_c) y_off,c — the same sign on both carriers, (2a) written like the paper's (2b) —
    and ψ_off,c. The lateral force enters as the plant's creep velocity |v| F_y/(2 c22),
    c22 ≈ c̄11 (the plant model's ESTIMATE, docs/plant-model.md §3)."""
    p = cfg.plant.carrier(carrier)
    return _model(p, carrier, D, p.v if v is None else v)


def _model(p: Plant, carrier: str, D: float, v: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`continuous_model` from the carrier's plant values ``p``."""
    a, cyv, w0 = p.c_y * v / (2 * p.l0), p.c_y * v, p.omega0
    fy = abs(v) / (2.0 * p.c11)
    w2 = w0 * w0
    off = v / (2 * p.l0) * p.y_off
    if carrier == "rear":
        a_own, a_other = -a, a
    else:
        a_own, a_other = a, -a
    A = np.array([[a_own, cyv, 0.0], [0.0, 0.0, 1.0], [0.0, -w2, -2 * D * w0]])
    Bc = np.array([[0.0, a_other, fy, off], [0.0, 0.0, 0.0, 0.0], [p.K * w2, 0.0, 0.0, w2 * p.psi_off]])
    return A, Bc


def yaw_model(p: Plant, D0: float, h: float, on: bool, sigma_psi: float = 0.0):
    """The carrier's hysteresis (9) and damping law (7) for the estimate's known nonlinear input
    (:class:`rig_runtime.observer.YawModel`), from its plant values ``p``; None when ``on`` is
    false (``observer.yaw_model``). The hysteresis only for n = 1 (the exact map; the shipped
    plants' n, Sec. 4.3.4), else left to the process noise as before (gain 0). ``sigma_psi``:
    the σ of the measured ψ (rad); ẑ moves once ψ̂ has moved by 4 of it (its jitter does not)."""
    from ..observer import YawModel
    if not on:
        return None
    bw = p.bouc_wen
    hyst = bw is not None and bw.a < 1.0 and bw.n == 1
    tau = 1.0 / (2.0 * math.pi * p.u_filter_hz)
    return YawModel(gain=(1.0 - bw.a) / p.K if hyst else 0.0,
                    A=bw.A if hyst else 1.0, beta=bw.beta if hyst else 0.0, gamma=bw.gamma if hyst else 0.0,
                    w0=p.omega0, D0=D0, D_min=p.D_min, D_max=p.D_max, irc=1.0 / (tau * p.c_udot_max),
                    ef=math.exp(-h / tau), mid=math.exp(-0.5 * h / tau), h=h, dead=4.0 * sigma_psi)


def discretise(A: np.ndarray, Bc: np.ndarray, Qc: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zero-order hold of (A, Bc) and the process noise Qc integrated over h (Van Loan)."""
    n, m = A.shape[0], Bc.shape[1]
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A, Bc
    from scipy.linalg import expm
    E = expm(M * h)
    V = expm(np.block([[-A, Qc], [np.zeros((n, n)), A.T]]) * h)
    Ad = E[:n, :n]
    Qd = Ad @ V[:n, n:]
    return Ad, E[:n, n:], 0.5 * (Qd + Qd.T)


def steady_state(Ad: np.ndarray, C: np.ndarray, Qd: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steady-state Kalman gain K, innovation covariance S and predictor covariance P (SI)
    of the discrete Riccati equation (solved in mm/mrad units for conditioning)."""
    s2 = _SCALE ** 2
    from scipy.linalg import solve_discrete_are
    P = solve_discrete_are(Ad.T, C.T, Qd * s2, R * s2)
    S = C @ P @ C.T + R * s2
    K = P @ C.T @ np.linalg.inv(S)
    return K, S / s2, P / s2


def steady_state_sda(Ad: np.ndarray, C: np.ndarray, Qd: np.ndarray, R: np.ndarray,
                     tol: float = 1e-13, max_iter: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`steady_state` by the structure-preserving doubling algorithm (Chu et al. 2004:
    the Riccati equation's stabilising solution as the limit of H_k, quadratically; a few dozen
    6×6 products instead of scipy's generalised Schur form — the joint filter's four gain sets
    over 42 speeds are most of its design time). Falls back to :func:`steady_state` when it
    does not converge or the result does not satisfy the equation."""
    s2 = _SCALE ** 2
    Rs, Qs = R * s2, Qd * s2
    n = Ad.shape[0]
    I = np.eye(n)
    A, G, H = Ad.T.copy(), C.T @ np.linalg.solve(Rs, C), Qs.copy()
    for _ in range(max_iter):
        W = I + G @ H
        WA = np.linalg.solve(W, A)
        WG = np.linalg.solve(W, G)
        H_next = H + A.T @ H @ WA
        G = G + A @ WG @ A.T
        A = A @ WA
        done = np.max(np.abs(H_next - H)) <= tol * max(1.0, np.max(np.abs(H_next)))
        H = H_next
        if done:
            P = 0.5 * (H + H.T)
            S = C @ P @ C.T + Rs
            res = Ad @ P @ Ad.T - Ad @ P @ C.T @ np.linalg.solve(S, C @ P @ Ad.T) + Qs - P
            if np.max(np.abs(res)) <= 1e-9 * max(1.0, np.max(np.abs(P))):
                K = P @ C.T @ np.linalg.inv(S)
                return K, S / s2, P / s2
            break
    return steady_state(Ad, C, Qd, R)


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
    fast = _outage_closed_form(M @ Ad, M @ Qd @ M.T + KRK, P, n_max, rtol)
    if fast is not None:
        return fast
    out = [math.sqrt(P[0, 0])]
    for _ in range(n_max):
        P = M @ (Ad @ P @ Ad.T + Qd) @ M.T + KRK
        s = math.sqrt(P[0, 0])
        done = abs(s - out[-1]) <= rtol * s
        out.append(s)
        if done:
            break
    return tuple(out)


def _outage_closed_form(Phi: np.ndarray, W: np.ndarray, P0: np.ndarray, n_max: int,
                        rtol: float) -> tuple[float, ...] | None:
    """The recursion P_k+1 = Φ P_k Φᵀ + W of :func:`outage_sigma_y` in closed form,
    P_k = P∞ + Φᵏ (P0 − P∞) Φᵏᵀ with P∞ its fixed point, by Φ's eigenvectors (vectorised
    over k: the table of a design costs ~1 ms instead of a loop of n_max matrix products), cut
    where the loop would stop. None where Φ is not safely diagonalisable (the loop then)."""
    lam, V = np.linalg.eig(Phi)
    if not np.all(np.abs(lam) < 1.0) or np.linalg.cond(V) > 1e8:
        return None
    from scipy.linalg import solve_discrete_lyapunov
    P_inf = solve_discrete_lyapunov(Phi, W)
    Vi = np.linalg.inv(V)
    G = Vi @ (P0 - P_inf) @ Vi.T
    k = np.arange(n_max + 1)[:, None]
    Lk = lam[None, :] ** k                                   # (n_max+1) × 3
    vy = V[0]
    s2 = P_inf[0, 0] + np.einsum("ki,i,ij,j,kj->k", Lk, vy, G, vy, Lk).real
    sig = np.sqrt(np.maximum(s2, 0.0))
    step = np.abs(np.diff(sig)) <= rtol * sig[1:]
    n = int(np.argmax(step)) + 2 if step.any() else len(sig)
    return tuple(float(x) for x in sig[:n])


def design(cfg: RigConfig, carrier: str, ocfg: ObserverConfig | None = None, v: float | None = None) -> ObserverDesign:
    """The carrier's filter as plain numbers at speed ``v`` (None: plant.v; see the module
    docstring). Memoised on its inputs (:func:`design_inputs`): a process that runs many
    dry runs designs each filter once."""
    return _design(*design_inputs(cfg, carrier, ocfg, v))


class DesignInputs(NamedTuple):
    """Every value a design depends on (frozen config values: the memo's key). The design
    itself (:func:`_design`) sees only these, never the config, so the key cannot miss one."""
    carrier: str
    plant: Plant                # the carrier's own plant values (cfg.plant.carrier(carrier))
    geometry: Geometry
    observer: ObserverConfig
    h: float
    outage_max_s: float         # degraded.max_s: how far the outage table goes
    window: int                 # limits.innovation_window
    ft_sensors: tuple[str, ...]
    v: float


def design_inputs(cfg: RigConfig, carrier: str, ocfg: ObserverConfig | None = None,
                  v: float | None = None) -> DesignInputs:
    """The inputs of :func:`design` taken from the config."""
    o = ocfg if ocfg is not None else (cfg.observer or ObserverConfig())
    p = cfg.plant.carrier(carrier)
    return DesignInputs(carrier, p, cfg.geometry, o, cfg.controller.h, cfg.degraded.max_s,
                        cfg.limits.innovation_window, _ft_sensors(cfg, CARRIER_WHEELS[carrier]),
                        p.v if v is None else float(v))


@functools.lru_cache(maxsize=DESIGN_CACHE_SIZE)
def _design(carrier: str, p: Plant, g: Geometry, o: ObserverConfig, h: float, outage_max_s: float,
            window: int, ft_sensors: tuple[str, ...], v: float) -> ObserverDesign:
    """:func:`design` from its inputs (:class:`DesignInputs`); the result is frozen (shared
    by every caller with these inputs)."""
    D = o.D if o.D is not None else p.D_min
    A, Bc = _model(p, carrier, D, v)
    Qc = np.diag([o.q_y ** 2, 0.0, o.q_psi_acc ** 2])
    Ad, Bd, Qd = discretise(A, Bc, Qc, h)
    gy, gr, gu = dw_row_at(p, v)
    lasers, weights = _weights(g, carrier)
    n = o.noise
    r_lat = sum(w * w for w in weights) * n.lateral_laser_m ** 2
    r_psi = 2.0 * n.yaw_laser_m ** 2 / g.d0 ** 2
    r_dw = 2.0 * n.encoder_rad_s ** 2
    C = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [gy, 0.0, gr]])
    K_full, S_full, P_full = steady_state(Ad, C, Qd, np.diag([r_lat, r_psi, r_dw]))
    R_nl = np.diag([r_psi, r_dw])
    K_nl, S_nl = steady_gain(Ad, C[1:], Qd, R_nl)
    # an outage lasts at most degraded.max_s (then the run ends): tabulate no further
    n_max = int(math.ceil(outage_max_s / h)) + 1
    sig = outage_sigma_y(Ad, Qd, P_full, K_full, C, K_nl, C[1:], R_nl, n_max)
    left, right = CARRIER_WHEELS[carrier]
    flat = lambda M: tuple(float(v) for v in np.asarray(M).ravel())     # noqa: E731
    return ObserverDesign(
        carrier=carrier, A=flat(Ad), B=flat(Bd[:, 0]), E=flat(Bd[:, 1]), F=flat(Bd[:, 2]), c=flat(Bd[:, 3]),
        dw_row=(gy, gr, gu), K_full=flat(K_full), K_nolat=flat(K_nl),
        S_full=flat(np.diag(S_full)), S_nolat=flat(np.diag(S_nl)),
        window=window, lateral_lasers=lasers, lateral_weights=weights,
        yaw_lasers=(f"s_{left}", f"s_{right}"), encoders=(left, right),
        ft_sensors=ft_sensors, sigma_y_outage=sig, v=v, yaw=yaw_model(p, D, h, o.yaw_model, math.sqrt(r_psi)))


def over_speed_grid(cfg: RigConfig, design: Callable, inputs: tuple):
    """``design(*inputs, v)`` (a pure function of its arguments: ``_design``, ``_joint``) over the
    schedule's speed grid, returned as the design at v_d carrying the table (``table``, a
    :class:`SpeedTable`): |v_k| = |v_d| ρᵏ (v_d = schedule.v_design or plant.v, ρ =
    ``SPEED_RATIO``) for both signs, from ``SPEED_FLOOR``·v_min (inside the standstill band) to
    the largest |v| of v_range."""
    sch = cfg.controller.schedule
    v_d = sch.v_design if sch.v_design is not None else cfg.plant.v
    ref = abs(v_d)
    lr = math.log(SPEED_RATIO)
    k_lo = math.floor(math.log(SPEED_FLOOR * sch.v_min / ref) / lr)
    k_hi = math.ceil(math.log(max(abs(sch.v_range[0]), abs(sch.v_range[1])) / ref) / lr)
    speeds = [ref * SPEED_RATIO ** k for k in range(k_lo, k_hi + 1)]
    fw = tuple(design(*inputs, v) for v in speeds)
    bw = tuple(design(*inputs, -v) for v in speeds)
    base = (fw if v_d > 0 else bw)[-k_lo]
    table = SpeedTable(v_ref=ref, ratio=SPEED_RATIO, k_lo=k_lo, k_hi=k_hi, forward=fw, backward=bw)
    return dataclasses.replace(base, table=table)


def speed_table(cfg: RigConfig, carrier: str, ocfg: ObserverConfig | None = None) -> ObserverDesign:
    """The carrier's designs over a grid of speeds for the schedule (docs/observer.md,
    "vehicle"): |v_k| = |v_d| ρᵏ (v_d = schedule.v_design or plant.v, ρ = ``SPEED_RATIO``) for
    both signs, from ``SPEED_FLOOR``·v_min (inside the standstill band) to the largest |v| of
    v_range; returned as the design at v_d carrying the table (``ObserverDesign.table``)."""
    return over_speed_grid(cfg, _design, design_inputs(cfg, carrier, ocfg)[:-1])


def _ft_sensors(cfg: RigConfig, wheels: tuple[str, str]) -> tuple[str, ...]:
    """The F/T sensors of the carrier's two wheels, by the name's wheel suffix (``ft_rl``,
    ``ft_rr``: the convention of the shipped configs and the simulator); both or none (one
    side alone is not the carrier's lateral force)."""
    names = [s.name for s in cfg.devices.ft.sensors]
    found = tuple(next((n for n in names if n.endswith(w)), "") for w in wheels)
    return found if all(found) else ()


def joint_applies(cfg: RigConfig) -> bool:
    """Both carriers on the rollers and controlled: one filter for the running gear."""
    return cfg.plant.front_contact and cfg.plant.rear_contact and set(cfg.controlled) == {"front", "rear"}


def designs(cfg: RigConfig) -> dict:
    """A design per controlled carrier when the config has an ``observer:`` section (else
    none): both carriers on the rollers and controlled — the running gear's joint filter
    (each carrier a ``JointCarrier`` of one design; with a speed schedule its table);
    otherwise per carrier, with a schedule the carrier's speed table, else the single design
    at plant.v."""
    if cfg.observer is None:
        return {}
    if joint_applies(cfg):
        from ..observer import JointCarrier
        if cfg.controller.schedule is not None:
            j = joint_speed_table(cfg)
        else:
            j = joint_design(cfg)
        return {c: JointCarrier(c, j) for c in ("front", "rear")}
    if cfg.controller.schedule is not None:
        return {c: speed_table(cfg, c) for c in cfg.controlled}
    return {c: design(cfg, c) for c in cfg.controlled}


def steady_std(d: ObserverDesign) -> dict[str, float]:
    """The steady-state standard deviations of the innovations (for docs and tests)."""
    return {m: math.sqrt(s) for m, s in zip(("lat", "psi", "dw"), d.S_full)}


# ---------------------------------------------------------------------- the running gear's filter
#: the joint filter's state (both carriers) and measurements, in matrix order
JOINT_STATE = ("y_f", "psi_f", "rate_f", "y_r", "psi_r", "rate_r")


def laser_rows(g: Geometry) -> tuple[tuple[float, float], tuple[float, float]]:
    """∂(b_f − b0)/∂(y_f, y_r) and ∂(b_r − b0)/∂(y_f, y_r) of the Sec. 2 geometry, small angle:
    b_f − b0 = y_m + (l_L/2) tan ψ_m, b_r − b0 = y_m − (l_L/2) tan ψ_m, y_m = (y_f + y_r)/2,
    sin ψ_m = (y_f − y_r)/(2 l0) — one lateral laser measures a combination of y_f and y_r."""
    k = g.l_L / (4.0 * g.l0)
    return (0.5 + k, 0.5 - k), (0.5 - k, 0.5 + k)


def joint_model(pf: Plant, pr: Plant, D_f: float, D_r: float, v: float) -> tuple[np.ndarray, np.ndarray]:
    """A (6×6) and the input matrix for (u_f, u_r, F_f, F_r, 1) of both carriers in one state
    (``JOINT_STATE``): each carrier's (2a)/(2b) and (6) as :func:`_model` writes them, the other
    carrier's y no longer a known input but a state (the coupling ∓a_c y_other)."""
    A = np.zeros((6, 6))
    Bc = np.zeros((6, 5))
    for i, (carrier, p, D) in enumerate((("front", pf, D_f), ("rear", pr, D_r))):
        Ai, Bi = _model(p, carrier, D, v)
        s, o = 3 * i, 3 * (1 - i)
        A[s:s + 3, s:s + 3] = Ai
        A[s:s + 3, o] = Bi[:, 1]               # the other carrier's y
        Bc[s:s + 3, i] = Bi[:, 0]              # u of this carrier
        Bc[s:s + 3, 2 + i] = Bi[:, 2]          # F_y of this carrier
        Bc[s:s + 3, 4] = Bi[:, 3]              # offsets
    return A, Bc


def _joint_C(g: Geometry, dw_f, dw_r) -> np.ndarray:
    """Rows (b_f, b_r, ψ_f, ψ_r, Δω_f, Δω_r) over ``JOINT_STATE`` (the lasers less b0)."""
    (ff, fr), (rf, rr) = laser_rows(g)
    return np.array([[ff, 0, 0, fr, 0, 0], [rf, 0, 0, rr, 0, 0], [0, 1, 0, 0, 0, 0], [0, 0, 0, 0, 1, 0],
                     [dw_f[0], 0, dw_f[1], 0, 0, 0], [0, 0, 0, dw_r[0], 0, dw_r[1]]], dtype=float)


def joint_design(cfg: RigConfig, ocfg: ObserverConfig | None = None, v: float | None = None):
    """The running gear's filter at speed ``v`` (None: plant.v; docs/observer.md, "One filter
    for the running gear"). Memoised like :func:`design`."""
    return _joint(*_joint_inputs(cfg, ocfg), cfg.plant.carrier("rear").v if v is None else float(v))


def _joint_inputs(cfg: RigConfig, ocfg: ObserverConfig | None) -> tuple:
    """The arguments of :func:`_joint` but the speed, taken from the config."""
    o = ocfg if ocfg is not None else (cfg.observer or ObserverConfig())
    return (cfg.plant.carrier("front"), cfg.plant.carrier("rear"), cfg.geometry, o, cfg.controller.h,
            cfg.degraded.max_s, cfg.limits.innovation_window,
            _ft_sensors(cfg, CARRIER_WHEELS["front"]), _ft_sensors(cfg, CARRIER_WHEELS["rear"]))


@functools.lru_cache(maxsize=DESIGN_CACHE_SIZE)
def _joint(pf: Plant, pr: Plant, g: Geometry, o: ObserverConfig, h: float, outage_max_s: float, window: int,
           ft_f: tuple[str, ...], ft_r: tuple[str, ...], v: float):
    from ..observer import JOINT_SETS, CarrierPart, JointDesign
    D_f = o.D if o.D is not None else pf.D_min
    D_r = o.D if o.D is not None else pr.D_min
    A, Bc = joint_model(pf, pr, D_f, D_r, v)
    q = [o.q_y ** 2, 0.0, o.q_psi_acc ** 2]
    Ad, Bd, Qd = discretise(A, Bc, np.diag(q + q), h)
    _zero_outside_blocks(Ad, Bd)
    dwf, dwr = dw_row_at(pf, v), dw_row_at(pr, v)
    C = _joint_C(g, dwf, dwr)
    n = o.noise
    R = np.diag([n.lateral_laser_m ** 2] * 2 + [2.0 * n.yaw_laser_m ** 2 / g.d0 ** 2] * 2
                + [2.0 * n.encoder_rad_s ** 2] * 2)
    n_max = int(math.ceil(outage_max_s / h)) + 1
    gains, variances, sigmas = [], [], []
    P_full = K_full = None
    for used in JOINT_SETS:
        idx = list(used)
        K, S, P = steady_state_sda(Ad, C[idx], Qd, R[np.ix_(idx, idx)])
        Kp = np.zeros((6, 6))
        Kp[:, idx] = K                              # padded: an unused measurement's column is 0
        Sp = np.ones(6)
        Sp[idx] = np.diag(S)
        gains.append(tuple(float(x) for x in Kp.ravel()))
        variances.append(tuple(float(x) for x in Sp))
        if P_full is None:
            P_full, K_full = P, K
            glr = _isolation_weights(Ad, C, K, S)
            ramp = _ramp_weights(Ad, C, K, S, window)
            Pp = (np.eye(6) - K @ C[idx]) @ P
            sigmas.append(((math.sqrt(Pp[0, 0]),), (math.sqrt(Pp[3, 3]),)))
        else:
            sigmas.append(_outage_sigmas(Ad, Qd, P_full, K_full, C, K, C[idx], R[np.ix_(idx, idx)], n_max))
    (ff, fr), (rf, rr) = laser_rows(g)
    parts = []
    for carrier, p, dw, ft, D in (("front", pf, dwf, ft_f, D_f), ("rear", pr, dwr, ft_r, D_r)):
        L, W = _weights(g, carrier)
        left, right = CARRIER_WHEELS[carrier]
        parts.append(CarrierPart(carrier=carrier, lateral_lasers=L, lateral_weights=W,
                                 yaw_lasers=(f"s_{left}", f"s_{right}"), encoders=(left, right),
                                 ft_sensors=ft, dw_row=dw,
                                 yaw=yaw_model(p, D, h, o.yaw_model, math.sqrt(R[2, 2]))))
    flat = lambda M: tuple(float(x) for x in np.asarray(M).ravel())     # noqa: E731
    return JointDesign(A=flat(Ad), Bu=flat(Bd[:, 0:2]), BF=flat(Bd[:, 2:4]), c=flat(Bd[:, 4]),
                       laser_rows=((ff, fr), (rf, rr)), b0=g.b0, K=tuple(gains), S=tuple(variances),
                       sigma_y=tuple(sigmas), window=window, front=parts[0], rear=parts[1], v=v,
                       isolation=flat(glr), drift=flat(ramp))


def _isolation_weights(Ad: np.ndarray, C: np.ndarray, K: np.ndarray, S: np.ndarray) -> np.ndarray:
    """The generalised likelihood ratio test of a bias on one measurement (rows: b_f, b_r, ψ_f,
    ψ_r, Δω_f, Δω_r): a constant bias β on measurement j leaves the steady-state filter's
    innovations at β g_j, g_j = (I − C (I − A(I − K C))⁻¹ A K) e_j (the predictor error settles at
    −(I − A(I − KC))⁻¹ A K e_j β); row j of the result, w_j = S⁻¹ g_j / √(g_jᵀ S⁻¹ g_j), makes
    (w_j · Σν)²/N over a window of N cycles χ²(1) without a bias and N (β √(g_jᵀ S⁻¹ g_j))² with
    one — the statistic that names the measurement whose bias explains the innovations best."""
    n = Ad.shape[0]
    G = np.eye(C.shape[0]) - C @ np.linalg.solve(np.eye(n) - Ad @ (np.eye(n) - K @ C), Ad @ K)
    Si = np.linalg.inv(S)
    W = Si @ G
    norm = np.sqrt(np.einsum("ij,ij->j", G, W))
    return (W / norm[None, :]).T


def _ramp_weights(Ad: np.ndarray, C: np.ndarray, K: np.ndarray, S: np.ndarray, N: int) -> np.ndarray:
    """The generalised likelihood ratio test of a *drift* on one measurement (a bias β_k = β0 +
    ρ k, both unknown): it leaves the steady-state filter's innovations at g_j β_k + ℓ_j ρ, with
    g_j of :func:`_isolation_weights` and the lag term ℓ_j = C (I − Φ)⁻² A K e_j (Φ = A(I − KC):
    the predictor error follows a ramp with a constant lag). Over a window of N cycles (k = 0 …
    N−1, oldest first) the statistic is zᵀ M⁻¹ z with z = (u_j·Σν, u_j·Σkν + l_j·Σν), u_j = S⁻¹g_j,
    l_j = S⁻¹ℓ_j, and M the 2×2 information matrix of (β0, ρ): χ²(2) without a drift. Row j:
    (u_j (6), l_j (6), M⁻¹₁₁, M⁻¹₁₂, M⁻¹₂₂)."""
    n, m = Ad.shape[0], C.shape[0]
    I = np.eye(n)
    Phi = Ad @ (I - K @ C)
    IP = np.linalg.inv(I - Phi)
    G = np.eye(m) - C @ IP @ Ad @ K
    L = C @ IP @ IP @ Ad @ K
    Si = np.linalg.inv(S)
    k = np.arange(N, dtype=float)
    s1, s2 = k.sum(), (k * k).sum()
    rows = []
    for j in range(m):
        g, ell = G[:, j], L[:, j]
        a, b, c = g @ Si @ g, g @ Si @ ell, ell @ Si @ ell
        M = np.array([[N * a, a * s1 + N * b], [a * s1 + N * b, a * s2 + 2 * b * s1 + N * c]])
        Mi = np.linalg.inv(M)
        rows.append(np.concatenate([Si @ g, Si @ ell, [Mi[0, 0], Mi[0, 1], Mi[1, 1]]]))
    return np.array(rows)


#: the entries of the held model the yaw rows may have (each carrier's ψ, ψ̇ and its own u and
#: offsets): (6) does not see y, so the rest is zero exactly; the cycle's step uses this structure
_YAW_ROWS = {1: (1, 2), 2: (1, 2), 4: (4, 5), 5: (4, 5)}
_YAW_INPUTS = {1: (0, 4), 2: (0, 4), 4: (1, 4), 5: (1, 4)}


def _zero_outside_blocks(Ad: np.ndarray, Bd: np.ndarray) -> None:
    """Set the yaw rows' structural zeros of the held model to 0 (the matrix exponential leaves
    them at rounding level at most; beyond 1e-12 of the row it is a modelling error: raised)."""
    for i, cols in _YAW_ROWS.items():
        for M, keep in ((Ad, cols), (Bd, _YAW_INPUTS[i])):
            rest = [j for j in range(M.shape[1]) if j not in keep]
            if np.max(np.abs(M[i, rest])) > 1e-12 * max(1.0, np.max(np.abs(M[i]))):
                raise ValueError(f"joint model: the yaw row {i} depends on more than its own carrier")
            M[i, rest] = 0.0


def _outage_sigmas(Ad, Qd, P_full, K_full, C, K_nl, C_nl, R_nl, n_max: int,
                   rtol: float = 1e-7) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The outage tables of y_f and y_r (states 0 and 3) of the joint filter: the recursion of
    :func:`outage_sigma_y` in closed form by Φ's eigenvectors, evaluated in blocks of k that
    double until both have converged (the table stops where the slower one has; the loop of
    :func:`outage_sigma_y`, per state, where Φ is not safely diagonalisable)."""
    n = Ad.shape[0]
    I = np.eye(n)
    P0 = (I - K_full @ C) @ P_full
    M = I - K_nl @ C_nl
    Phi, W = M @ Ad, M @ Qd @ M.T + K_nl @ R_nl @ K_nl.T
    lam, V = np.linalg.eig(Phi)
    if not np.all(np.abs(lam) < 1.0) or np.linalg.cond(V) > 1e8:
        return tuple(_outage_sigma_loop(Ad, Qd, P_full, K_full, C, K_nl, C_nl, R_nl, n_max, i) for i in (0, 3))
    from scipy.linalg import solve_discrete_lyapunov
    P_inf = solve_discrete_lyapunov(Phi, W)
    Vi = np.linalg.inv(V)
    G = Vi @ (P0 - P_inf) @ Vi.T
    rows = V[[0, 3]]                                          # 2 × n
    m = 1024
    while True:
        m = min(m, n_max + 1)
        Lk = np.exp(np.arange(m)[:, None] * np.log(lam.astype(complex))[None, :])   # λᵏ, m × n
        out, done = [], True
        for r, i in zip(rows, (0, 3)):
            a = Lk * r[None, :]
            s2 = P_inf[i, i] + np.einsum("kj,kj->k", a @ G, a).real
            sig = np.sqrt(np.maximum(s2, 0.0))
            step = np.abs(np.diff(sig)) <= rtol * sig[1:]
            # converged: the step below rtol from some k on, to the end of the block
            conv = np.nonzero(~step)[0]
            last = int(conv[-1]) + 2 if conv.size else 1
            done = done and (last < m or m == n_max + 1)
            out.append((sig, last))
        if done:
            cut = min(max(last for _, last in out) + 1, m)
            return tuple(tuple(sig[:cut].tolist()) for sig, _ in out)
        m *= 2


def _outage_sigma_loop(Ad, Qd, P_full, K_full, C, K_nl, C_nl, R_nl, n_max, i) -> tuple[float, ...]:
    """:func:`outage_sigma_y` for state ``i`` (its first state made ``i``)."""
    perm = [i] + [j for j in range(Ad.shape[0]) if j != i]
    Pm = np.eye(Ad.shape[0])[perm]
    return outage_sigma_y(Pm @ Ad @ Pm.T, Pm @ Qd @ Pm.T, Pm @ P_full @ Pm.T, Pm @ K_full, C @ Pm.T,
                          Pm @ K_nl, C_nl @ Pm.T, R_nl, n_max)


def joint_speed_table(cfg: RigConfig, ocfg: ObserverConfig | None = None):
    """The joint design over the schedule's speed grid (as :func:`speed_table`), returned as
    the design at v_d carrying the table."""
    return over_speed_grid(cfg, _joint, _joint_inputs(cfg, ocfg))
