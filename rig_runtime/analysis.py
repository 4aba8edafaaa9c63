"""The tuning analysis of Sec. 5.1 and 5.2.3, from the configured parameters and gains.

Linear model (10) of the rear carrier: x = [y, ψ, ψ̇], input Δu,
    A = [[-a, c̄_y v, 0], [0, 0, 1], [0, -ω0², -2Dω0]],  B = [0, 0, Kω0²]ᵀ,  a = c̄_y v/(2 l0).
The damping used for tuning is D_min (the low damping the rig shows under a changing
input, Sec. 4.3.3 and 5.1). Sec. 5.2.3's outer loop (17) is printed with c̄_y v/l0 instead
of (10)'s c̄_y v/(2 l0); ``tuning.outer_lateral_form`` chooses which the PI-PD analysis
uses (``eq17`` reproduces the paper's printed eigenvalues; docs/paper-notes.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from . import coupled
from .config import PIPDGains, RigConfig
from .control import DiscreteLaw, PIPDLaw, PLaw, law_of
from .coupled import Instability
from .damping import YawDamping
from .errors import ConfigError


@dataclass(frozen=True)
class TuneResult:
    inner: np.ndarray
    inner_filtered: np.ndarray
    outer: np.ndarray
    closed_loop: np.ndarray
    closed_loop_sampled: np.ndarray
    open_loop_poles: np.ndarray
    stability_boundary_kp: float
    checks: dict
    params: dict


def _sorted(ev: np.ndarray) -> np.ndarray:
    ev = np.asarray(ev, dtype=complex)
    return ev[np.lexsort((ev.imag, ev.real))]


def model_10(cfg: RigConfig, D: float | None = None, a: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A, B of (10) for the rear carrier."""
    p = cfg.plant
    D = p.D_min if D is None else D
    a = p.a_lat if a is None else a
    w2 = p.omega0 ** 2
    A = np.array([[-a, p.c_y * p.v, 0.0], [0.0, 0.0, 1.0], [0.0, -w2, -2 * D * p.omega0]])
    B = np.array([0.0, 0.0, p.K * w2])
    return A, B


def pipd_gains(cfg: RigConfig) -> PIPDGains:
    """The PI-PD gains the continuous formulas (15)–(19) and Sec. 5.2.3's checks are of: the
    configured law's (``controller.decoupled`` for law decoupled, else ``controller.pipd``)."""
    c = cfg.controller
    return c.decoupled if c.law == "decoupled" else c.pipd


def _outer_a(cfg: RigConfig) -> float:
    p = cfg.plant
    return p.c_y * p.v / p.l0 if cfg.tuning.outer_lateral_form == "eq17" else p.a_lat


def inner_matrix(cfg: RigConfig) -> np.ndarray:
    """A_ψ,cl of (15)."""
    A, B = model_10(cfg)
    g = pipd_gains(cfg)
    return A[1:, 1:] - np.outer(B[1:], [g.K_P_psi, g.K_D_psi])


def inner_filtered_matrix(cfg: RigConfig) -> np.ndarray:
    """Ā_ψ,cl of (16a): inner loop with the differentiator (12)."""
    p, g = cfg.plant, pipd_gains(cfg)
    w2, T, KD = p.omega0 ** 2, g.T_f_psi, g.K_D_psi
    Kw = p.K * w2
    return np.array([[0.0, 1.0, 0.0],
                     [-w2 - Kw * (g.K_P_psi + KD / T), -2 * p.D_min * p.omega0, -Kw * KD / T ** 2],
                     [-1.0, 0.0, -1.0 / T]])


def outer_matrix(cfg: RigConfig) -> np.ndarray:
    """A_y,x1 of (17) in states [x_I, e_y] (with ψ = ψ_ref; sign of the K_I entry as it
    follows from (13), (14))."""
    p, g = cfg.plant, pipd_gains(cfg)
    cv = p.c_y * p.v
    return np.array([[0.0, 1.0], [-g.K_I_y * cv, -_outer_a(cfg) - cv * g.K_P_y]])


def closed_loop_matrix(cfg: RigConfig) -> np.ndarray:
    """Ā_cl of (19), states [y, ψ, ψ̇, x_I, x_diff] (a similarity transform of the paper's
    error coordinates: same eigenvalues). ψ̇_ref is taken exactly, ψ̇ through (12)."""
    g = pipd_gains(cfg)
    A, B = model_10(cfg, a=_outer_a(cfg))
    T = g.T_f_psi
    M = np.zeros((5, 5))
    M[:3, :3] = A
    # u = K_Pψ (ψ_ref − ψ) + K_Dψ (ψ̇_ref − ψ̂̇), ψ_ref = −K_Py y + K_Iy x_I (y_ref = 0),
    # ψ̇_ref = −K_Py ẏ − K_Iy y, ψ̂̇ = −x_d/T² + ψ/T
    u = np.zeros(5)
    u[0] += -g.K_P_psi * g.K_P_y - g.K_D_psi * g.K_I_y
    u[3] += g.K_P_psi * g.K_I_y
    u[1] += -g.K_P_psi - g.K_D_psi / T
    u[:3] += -g.K_D_psi * g.K_P_y * A[0]
    u[4] += g.K_D_psi / T ** 2
    M[2] += B[2] * u
    M[3, 0] = -1.0
    M[4, 1] = 1.0
    M[4, 4] = -1.0 / T
    return M


def _held_plant(cfg: RigConfig, D: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Plant (10) with its input held over one sample time h (zero-order hold): A_d, B_d (a column)."""
    A, B = model_10(cfg, D=D)
    n = 3
    Md = expm(np.block([[A, B[:, None]], [np.zeros((1, n + 1))]]) * cfg.controller.h)
    return Md[:n, :n], Md[:n, n:]


PAPER_LAYOUT = coupled.Layout(("rear",), ("rear",), 3)     # plant (10): [y, ψ, ψ̇] of the rear carrier


def _sampled(cfg: RigConfig, law: DiscreteLaw, D: float | None) -> np.ndarray:
    """Eigenvalues (ln(z)/h, 1/s) of ``law`` (its description, as the runtime steps it) on
    plant (10) held over h, y_ref = 0."""
    Ad, Bd = _held_plant(cfg, D)
    return _continuous(np.linalg.eigvals(coupled.close(Ad, Bd, PAPER_LAYOUT, {"rear": law})), cfg.controller.h)


def sampled_closed_loop(cfg: RigConfig, D: float | None = None) -> np.ndarray:
    """Eigenvalues of the PI-PD loop as implemented: plant (10) (with (10)'s own lateral pole,
    damping ``D``, default D_min) held over h, the Tustin PI-PD of ``control.py`` (its
    :class:`~rig_runtime.control.DiscreteLaw`); returned as ln(z)/h (1/s)."""
    c = cfg.controller
    return _sampled(cfg, PIPDLaw.of(pipd_gains(cfg), c.h, _yaw(cfg)).discrete(D=D), D)


def _continuous(z: np.ndarray, h: float) -> np.ndarray:
    """ln(z)/h: |z| < 1 (stable sampled pole) is Re < 0. Poles at z = 0 (deadbeat) dropped."""
    z = z[np.abs(z) > 1e-9]
    return np.log(z.astype(complex)) / h


def sampled_p_loop(cfg: RigConfig, D: float | None = None) -> np.ndarray:
    """Eigenvalues (ln(z)/h, 1/s) of the P law of Sec. 5.1 as implemented: u_k = K_P (y_ref − y_k)
    on plant (10) held over h."""
    c = cfg.controller
    return _sampled(cfg, PLaw(c.K_P, c.h).discrete(), D)


def sampled_loop(cfg: RigConfig, D: float | None = None) -> np.ndarray:
    """The sampled closed loop of the configured law (``controller.law``), as implemented."""
    return _sampled(cfg, law_of(cfg.controller, yaw=_yaw(cfg)).discrete(D=D), D)


def _yaw(cfg: RigConfig) -> YawDamping:
    """The rear carrier's yaw parameters (plant (10)'s carrier): a law scheduled on its damping needs them."""
    return YawDamping.of(cfg.plant.carrier("rear"))


class UnstableLoopError(ConfigError):
    """The configured gains give an unstable closed loop: they are never armed."""


def ev_text(e: complex) -> str:
    return f"{e.real:+.3g}" + (f"{e.imag:+.3g}j" if abs(e.imag) > 1e-9 else "") + " 1/s"


def sampled_instability(cfg: RigConfig) -> "Instability | None":
    """Where the sampled closed loop as implemented (the configured law, h, Tustin) is not
    stable, or None: at every speed the config runs at (``plant.v``; with a schedule every
    speed of ``schedule.v_range`` outside the standstill band, both signs) and for each
    carrier's D_min and D_max, with every carrier in contact (:mod:`rig_runtime.coupled`).
    With the paper's set-up (front lifted, fixed speed) this is plant (10) at D_min, then D_max."""
    return coupled.instability(cfg)


def stability_gate(cfg: RigConfig) -> None:
    """Refuse (``UnstableLoopError``) gains whose sampled closed loop is unstable
    (:func:`sampled_instability`). ``rig run``, ``rig dry-run`` and ``rig check`` call this
    before anything is opened; ``rig tune`` fails on it too."""
    bad = sampled_instability(cfg)
    if bad is not None:
        law = cfg.controller.law
        ev = bad.s
        what = ("gains whose sampled closed loop ({law}, h = {h:g} s, {where}) is stable, but "
                .format(law=law, h=cfg.controller.h, where=bad.where()))
        raise UnstableLoopError(
            cfg.source or None, "controller.K_P" if law == "p" else _gains_key(cfg, bad),
            what + ("it cannot be computed with these parameters (numbers overflow)" if ev != ev
                    else f"it has an eigenvalue at {ev_text(ev)} (`rig tune` shows the analysis)"))


def _gains_key(cfg: RigConfig, bad: "Instability") -> str:
    c = cfg.controller
    keys = ["controller.decoupled" if c.law == "decoupled" else "controller.pipd"] + [f"controller.{k}" for k in ("front", "rear") if getattr(c, k) is not None]
    if c.schedule is not None:
        keys.append("controller.schedule")
    return " / ".join(keys)


# the single-carrier loops that describe the paper's set-up (rear carrier, front lifted, fixed
# speed) and not the loop a vehicle config runs: reported by `rig tune`, judged only there
SINGLE_CARRIER_ONLY = ("complete closed loop (19)", "slowest_outer_eigenvalue")


def tune_failures(cfg: RigConfig, r: "TuneResult") -> list[str]:
    """What makes ``rig tune`` fail: a loop of (15), (16), (19) or the sampled loop as
    implemented with an eigenvalue Re >= 0, or a design check of Sec. 5.2.3 that fails.
    On a vehicle config (:func:`coupled.applies`) the coupled loop at every analysed speed and
    every D_min/D_max combination (continuous and sampled) replaces (19) and the outer-loop
    criterion of (17), which assume the rear carrier alone with its stable lateral pole (the
    vehicle's lateral pair has a double pole at 0)."""
    vehicle = coupled.applies(cfg)
    out = []
    for name, ev in (("inner loop (15)", r.inner), ("inner loop with differentiator (16)", r.inner_filtered),
                     ("complete closed loop (19)", r.closed_loop)):
        bad = [e for e in ev if not e.real < 0]
        if bad and not (vehicle and name in SINGLE_CARRIER_ONLY):
            out.append(f"{name} unstable: eigenvalue at {ev_text(max(bad, key=lambda e: e.real))}")
    bad = sampled_instability(cfg)    # r.closed_loop_sampled is its D_min case (pipd, paper's set-up)
    if bad is not None:
        where = bad.where().replace("plant (10) with ", "")
        out.append(f"sampled loop as implemented ({cfg.controller.law}, {where}) unstable: "
                   f"eigenvalue at {ev_text(bad.s)}")
    if vehicle:       # continuous, at every D_min/D_max combination (the sampled one is the gate's, above)
        for p in coupled.analyse(cfg).points:
            if not (p.stable and p.rightmost.real < 0):
                ev, D = (p.least_damped, None) if not p.stable else (p.rightmost, p.rightmost_D)
                Ds = "" if D is None else " (" + ", ".join(f"D_{c} = {d:g}" for c, d in D.items()) + ")"
                out.append(f"coupled loop at v = {p.v:+g} m/s{Ds} unstable: eigenvalue at {ev_text(ev)}")
                break
    for k, c in r.checks.items():
        if not c["ok"] and not (vehicle and k in SINGLE_CARRIER_ONLY):
            out.append(f"design check {k} fails: {c['value']:.4g} (limit {c['limit']:g})")
    return out


def p_control_boundary(cfg: RigConfig, D: float | None = None, kp_hi: float = 1e7) -> float:
    """Smallest K_P > 0 at which u = K_P (y_ref − y) around (10) becomes unstable."""
    A, B = model_10(cfg, D=D)
    C = np.array([1.0, 0.0, 0.0])

    def unstable(kp: float) -> bool:
        return np.max(np.linalg.eigvals(A - kp * np.outer(B, C)).real) > 0

    lo, hi = 0.0, 1.0
    while not unstable(hi):
        lo, hi = hi, hi * 2
        if hi > kp_hi:
            return float("inf")
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if unstable(mid) else (mid, hi)
    return hi


def root_locus(cfg: RigConfig, kps: np.ndarray, D: float | None = None) -> np.ndarray:
    """Closed-loop poles of the P law for each K_P (rows)."""
    A, B = model_10(cfg, D=D)
    C = np.array([1.0, 0.0, 0.0])
    return np.array([_sorted(np.linalg.eigvals(A - k * np.outer(B, C))) for k in kps])


def design_checks(cfg: RigConfig, outer: np.ndarray) -> dict:
    """The criteria of Sec. 5.2.3 (worst-case input and reference yaw angle, slowest pole)."""
    t, g = cfg.tuning, pipd_gains(cfg)
    terms = [abs(g.K_P_psi) * t.psi_design, abs(g.K_D_psi) * t.psi_rate_design]   # worst case: signs aligned
    u_worst = sum(terms)
    psi_ref_worst = g.K_P_y * t.y_design      # (law decoupled: its feed term is bounded by psi_ref_max, docs/vehicle.md §5)
    slowest = float(np.max(outer.real))
    return {
        # Sec. 5.2.3 asks for <= 2 A; its gains give 2 A per term (4 A together), so the
        # criterion is read per term (docs/paper-notes.md); the sum is checked against u_max.
        "worst_case_input_per_term_A": {"value": max(terms), "limit": t.u_design_max,
                                        "ok": max(terms) <= t.u_design_max, "terms_A": terms},
        "worst_case_psi_ref_rad": {"value": psi_ref_worst, "limit": t.psi_ref_design_max,
                                   "ok": psi_ref_worst <= t.psi_ref_design_max},
        "slowest_outer_eigenvalue": {"value": slowest, "limit": t.slowest_eig_min, "ok": slowest <= t.slowest_eig_min},
        "input_within_saturation": {"value": u_worst, "limit": cfg.limits.u_max, "ok": u_worst <= cfg.limits.u_max},
    }


def tune(cfg: RigConfig) -> TuneResult:
    p = cfg.plant
    A, _ = model_10(cfg)
    outer = _sorted(np.linalg.eigvals(outer_matrix(cfg)))
    return TuneResult(
        inner=_sorted(np.linalg.eigvals(inner_matrix(cfg))),
        inner_filtered=_sorted(np.linalg.eigvals(inner_filtered_matrix(cfg))),
        outer=outer,
        closed_loop=_sorted(np.linalg.eigvals(closed_loop_matrix(cfg))),
        closed_loop_sampled=_sorted(sampled_closed_loop(cfg)),
        open_loop_poles=_sorted(np.linalg.eigvals(A)),
        stability_boundary_kp=p_control_boundary(cfg),
        checks=design_checks(cfg, outer),
        params={"c_y": p.c_y, "a_lat": p.a_lat, "a_outer": _outer_a(cfg), "D": p.D_min,
                "omega0": p.omega0, "K": p.K, "outer_lateral_form": cfg.tuning.outer_lateral_form},
    )


def pairs(ev: np.ndarray) -> list[list[float]]:
    return [[float(e.real), float(e.imag)] for e in ev]


def to_json(r: TuneResult) -> dict:
    return {
        "inner": {"eigenvalues": pairs(r.inner)},
        "inner_filtered": {"eigenvalues": pairs(r.inner_filtered)},
        "outer": {"eigenvalues": pairs(r.outer)},
        "closed_loop": {"eigenvalues": pairs(r.closed_loop)},
        "closed_loop_sampled": {"eigenvalues": pairs(r.closed_loop_sampled)},
        "p_control": {"open_loop_poles": pairs(r.open_loop_poles), "stability_boundary_kp": r.stability_boundary_kp},
        "checks": r.checks,
        "params": r.params,
    }


PAPER = {  # Sec. 5.1 and 5.2.3, as printed
    "inner": [-88.9, -5.0],
    "inner_filtered": [-67.1, -40.7, -4.9],
    "outer": [-4.5, -2.0],
    "closed_loop": [-66.5, -41.0, -4.4, -3.7, -0.5],
    "open_loop_slow": [-4.5, -1.73],
    "stability_boundary_kp": 18605.0,
}
