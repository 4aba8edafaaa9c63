"""The coupled closed loop of the vehicle: both wheel carriers on the rollers, both running
directions, the controllers as implemented and the speed schedule (issue 18; docs/vehicle.md).

Plant, per carrier c in the set ``carriers`` (each with its own parameters, ``cfg.plant.carrier(c)``):

    ẏ_f = a_f (y_f − y_r) + c̄_y,f v ψ_f,   a_f = c̄_y,f v / (2 l0_f)            (2a)
    ẏ_r = a_r (y_f − y_r) + c̄_y,r v ψ_r,   a_r = c̄_y,r v / (2 l0_r)            (2b)
    ψ̈_c = −ω0,c² ψ_c − 2 D_c ω0,c ψ̇_c + K_c ω0,c² Δu_c                        (6), linear part

A carrier not in the set is held at y ≡ 0 (lifted: the paper's set-up has the front lifted,
and then this is model (10) of the rear carrier). Offsets, forces and the hysteresis are
inputs or nonlinear: not in A. The yaw dynamics (6) are taken as speed- and
direction-independent (ESTIMATE: the paper identified them at v = +1 m/s only).

Controller per controlled carrier in contact: the configured law's own description
(:class:`rig_runtime.control.DiscreteLaw`, from ``control.law_of``) — as implemented (the
sampled loop: the plant held over h (ZOH), the law's discrete form, u_k computed from the
samples of cycle k) and as designed (the continuous loop: the law's continuous form). Nothing
of a law's arithmetic is written here: :func:`close` wires any law's matrices to the plant
(:func:`rig_runtime.analysis.sampled_closed_loop` is this loop with the front lifted). A
carrier in contact that is not controlled has Δu = 0.

THE SCHEDULE LAW (docs/vehicle.md implements it): g = v_d / v with
v_d = ``schedule.v_design`` (else ``plant.v``), sign included, on the outer PI only. Without a
schedule g = 1 and the loop runs at ``plant.v`` only. Speeds with |v| < ``schedule.v_min``
are held (the lateral loop open by design) and not analysed.

numpy only: this module is imported where gains are judged (preflight, ``rig tune``, the
``rig ctl`` server), never by the loop.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Mapping, Optional

import numpy as np

from . import control
from .config import RigConfig
from .control import DiscreteLaw
from .damping import YawDamping

GRID_STEP = 0.05        # m/s: the largest spacing of the analysed speeds over schedule.v_range


# --------------------------------------------------------------------------- the set-up
def applies(cfg: RigConfig) -> bool:
    """Whether the config is a vehicle one (a second carrier in contact or a speed schedule):
    ``rig tune`` then reports the coupled analysis; the paper's set-up has neither."""
    return cfg.plant.front_contact or cfg.controller.schedule is not None


def design_speed(cfg: RigConfig) -> float:
    """v_d of the schedule law: ``schedule.v_design``, else ``plant.v``."""
    s = cfg.controller.schedule
    return cfg.plant.v if s is None or s.v_design is None else s.v_design


def gain_factor(cfg: RigConfig, v: float) -> float:
    """g = v_d / v (sign included) with a schedule; 1 without one."""
    return 1.0 if cfg.controller.schedule is None else design_speed(cfg) / v


def speeds(cfg: RigConfig) -> tuple[tuple[float, ...], Optional[tuple[float, float]]]:
    """(the analysed speeds, the held band (−v_min, v_min) or None).

    With a schedule: a grid over ``v_range`` of spacing at most ``GRID_STEP`` plus the range
    ends, ±v_design and ±v_min where they lie in the range, all with |v| >= v_min. Without
    one: ``plant.v`` alone (the loop's gains are fixed and so is the speed)."""
    s = cfg.controller.schedule
    if s is None:
        return (cfg.plant.v,), None
    lo, hi = s.v_range
    n = max(2, int(math.ceil((hi - lo) / GRID_STEP - 1e-9)) + 1)
    vd = design_speed(cfg)
    pts = set(np.linspace(lo, hi, n).tolist()) | {lo, hi, vd, -vd, s.v_min, -s.v_min}
    out = sorted({round(v, 9) for v in pts if lo - 1e-12 <= v <= hi + 1e-12 and abs(v) >= s.v_min - 1e-12})
    band = (-s.v_min, s.v_min) if lo < s.v_min and hi > -s.v_min else None
    return tuple(out), band


def all_damping_cases(cfg: RigConfig, carriers: tuple[str, ...]) -> list[dict[str, float]]:
    """Every combination of the carriers' D_min and D_max (each its own): the damping of (6)
    varies with the input (7), D_max only while |u̇| < c_udot_max (a quasi-static input)."""
    per = [dict.fromkeys((cfg.plant.carrier(c).D_min, cfg.plant.carrier(c).D_max)) for c in carriers]
    return [dict(zip(carriers, combo)) for combo in itertools.product(*per)]


def lateral_open_loop_stable(cfg: RigConfig, v: float, lay: "Layout") -> bool:
    """Whether the lateral dynamics of the carriers in contact, ψ held at 0, are asymptotically
    stable at v: the paper's set-up at v > 0 (the rear's pole −c̄_y v/(2 l0)); not with both
    carriers in contact (the double pole at 0 of (2a)/(2b)) nor a single leading carrier."""
    A, _ = plant_matrices(cfg, v, d_min(cfg, lay.carriers), lay)
    n = len(lay.carriers)
    return bool(np.all(np.linalg.eigvals(A[:n, :n]).real < -1e-9))


def damping_cases(cfg: RigConfig, v: float, lay: "Layout") -> list[dict[str, float]]:
    """The damping cases the gate checks at speed v (the rule, written once):

    - a vehicle config (:func:`applies`): every combination of the carriers' D_min and D_max
      (:func:`all_damping_cases`). (7) gives D_max only while a carrier's current is still, and
      any combination can occur; a law that knows its damping (``D_sched``, D̂ of (7) from its own
      commanded current: control.PIPDLaw) is analysed with the gains it has at each;
    - the paper's set-up: its carrier at D_min — always (the damping a loop that moves its input
      runs at, Sec. 4.3.3) — and at D_max where its lateral dynamics are stable open loop
      (:func:`lateral_open_loop_stable`: v > 0, plant (10) at D_min, then D_max, as before)."""
    if applies(cfg):
        return all_damping_cases(cfg, lay.carriers)
    lo = {c: cfg.plant.carrier(c).D_min for c in lay.carriers}
    hi = {c: cfg.plant.carrier(c).D_max for c in lay.carriers}
    return [lo] if hi == lo or not lateral_open_loop_stable(cfg, v, lay) else [lo, hi]


def d_min(cfg: RigConfig, carriers: tuple[str, ...]) -> dict[str, float]:
    """Each carrier's D_min: the damping the analysis reports (the tuning damping of Sec. 5)."""
    return {c: cfg.plant.carrier(c).D_min for c in carriers}


# --------------------------------------------------------------------------- the plant
@dataclass(frozen=True)
class Layout:
    """Where each carrier's quantities are in the state vector."""

    carriers: tuple[str, ...]          # in contact (lateral state and yaw)
    controlled: tuple[str, ...]        # controlled and in contact
    n_plant: int

    def y(self, c: str) -> int:
        return self.carriers.index(c)

    def psi(self, c: str) -> int:
        return len(self.carriers) + 2 * self.carriers.index(c)

    def dpsi(self, c: str) -> int:
        return self.psi(c) + 1


def layout(cfg: RigConfig, carriers: Optional[tuple[str, ...]] = None) -> Layout:
    cs = cfg.plant.in_contact if carriers is None else carriers
    return Layout(cs, tuple(c for c in cs if c in cfg.controlled), 3 * len(cs))


def plant_matrices(cfg: RigConfig, v: float, D: Mapping[str, float], lay: Layout) -> tuple[np.ndarray, np.ndarray]:
    """A, B of (2a)/(2b)+(6) for the carriers of ``lay`` (states [y_c…, (ψ_c, ψ̇_c)…],
    inputs Δu_c in the order of ``lay.carriers``); a carrier not in the set has y ≡ 0."""
    n = lay.n_plant
    A = np.zeros((n, n))
    B = np.zeros((n, len(lay.carriers)))
    for j, c in enumerate(lay.carriers):
        p = cfg.plant.carrier(c)
        cv = p.c_y * v
        a = cv / (2 * p.l0)
        if "front" in lay.carriers:
            A[lay.y(c), lay.y("front")] += a
        if "rear" in lay.carriers:
            A[lay.y(c), lay.y("rear")] -= a
        A[lay.y(c), lay.psi(c)] = cv
        w2 = p.omega0 ** 2
        A[lay.psi(c), lay.dpsi(c)] = 1.0
        A[lay.dpsi(c), lay.psi(c)] = -w2
        A[lay.dpsi(c), lay.dpsi(c)] = -2 * D[c] * p.omega0
        B[lay.dpsi(c), j] = p.K * w2
    return A, B


def expm(M: np.ndarray) -> np.ndarray:
    """e^M by scaling and squaring of a 14-term Taylor series (||M/2^s||_inf <= 1/4: truncation
    below 1e-16). For the small matrices here (ZOH over h, ||M h|| up to ~20 at D_max) it agrees
    with scipy.linalg.expm to 1e-12 (tests/test_coupled.py) at about a thirtieth of its cost
    here, which matters: the gate evaluates ~50–110 of them on every run and ``rig ctl set``."""
    nrm = float(np.max(np.sum(np.abs(M), axis=1))) if M.size else 0.0
    if not math.isfinite(nrm):
        raise ArithmeticError("expm: a matrix with non-finite entries")
    s = max(0, math.ceil(math.log2(nrm / 0.25))) if nrm > 0 else 0
    A = M / 2.0 ** s
    E = np.eye(len(M))
    T = np.eye(len(M))
    for k in range(1, 15):
        T = T @ A / k
        E = E + T
    for _ in range(s):
        E = E @ E
    return E


def held(cfg: RigConfig, v: float, D: Mapping[str, float], lay: Layout) -> tuple[np.ndarray, np.ndarray]:
    """The plant held over h (zero-order hold): A_d, B_d."""
    A, B = plant_matrices(cfg, v, D, lay)
    n, m = B.shape
    M = expm(np.block([[A, B], [np.zeros((m, n + m))]]) * cfg.controller.h)
    return M[:n, :n], M[:n, n:]


# --------------------------------------------------------------------------- the loops
def law_at(cfg: RigConfig, carrier: str, v: float, continuous: bool = False,
           D: Optional[float] = None) -> DiscreteLaw:
    """The carrier's configured law (:mod:`rig_runtime.control`) at the schedule's factor for
    speed v and at the carrier's damping D (a law that knows its damping, D̂ of (7) from its own
    current, is at D̂ = D there; None: D_min): as implemented (sampled), or as designed
    (``continuous``)."""
    law = law_of(cfg, carrier)
    g = gain_factor(cfg, v)
    return law.continuous(g, D) if continuous else law.discrete(g, D)


def law_of(cfg: RigConfig, carrier: str):
    """The carrier's configured law with its gains and its yaw parameters."""
    return control.law_of(cfg.controller, carrier, YawDamping.of(cfg.plant.carrier(carrier)))


@dataclass(frozen=True)
class Loop:
    """A closed loop with its references: z⁺ = M z + R r (sampled; ż = M z + R r continuous),
    the carriers' inputs u = U z + U_r r. ``refs``/``inputs``: the carriers of r's and u's entries."""

    M: np.ndarray
    R: np.ndarray
    U: np.ndarray
    U_r: np.ndarray
    refs: tuple[str, ...]
    inputs: tuple[str, ...]


def _signal(name: str, car: str) -> tuple[str, str]:
    """A law's signal name as (quantity, carrier): ``y`` is its own carrier's y, ``y.front``
    the front's (a law across carriers names them)."""
    q, _, c = name.partition(".")
    return q, (c or car)


def closed_loop(A: np.ndarray, B: np.ndarray, lay: Layout, laws: Mapping[str, DiscreteLaw]) -> Loop:
    """The closed loop of the plant (A, B over ``lay``: held over h, or continuous) and the laws
    (``laws``: by the carrier they belong to, or by any name for a law whose signals name their
    carriers; sampled, or continuous): states [plant, each law's states]. A law reads ``y``,
    ``psi`` (its carrier's, or ``y.front`` …) and ``y_ref`` (a reference: a column of R) and
    drives ``u`` (its carrier's input, or ``u.rear`` …). Nothing of a law is written here: its
    matrices come from its description (:class:`~rig_runtime.control.DiscreteLaw`)."""
    n = lay.n_plant
    N = n + sum(len(L.states) for L in laws.values())
    refs = tuple(c for c in lay.carriers if c in lay.controlled)
    M = np.zeros((N, N))
    R = np.zeros((N, len(refs)))
    U = np.zeros((len(lay.carriers), N))
    U_r = np.zeros((len(lay.carriers), len(refs)))
    M[:n, :n] = A
    off = n
    for car, L in laws.items():
        cols, rcols = [], []
        for i, name in enumerate(L.inputs):
            q, c = _signal(name, car)
            if q == "y_ref":
                rcols.append((i, refs.index(c)))
            elif c in lay.carriers:
                cols.append((i, lay.y(c) if q == "y" else lay.psi(c)))
        ns = len(L.states)
        for r in range(ns):
            M[off + r, off:off + ns] = L.A[r]
            for i, col in cols:
                M[off + r, col] += L.B[r][i]
            for i, col in rcols:
                R[off + r, col] += L.B[r][i]
        for o, oname in enumerate(L.outputs):
            _, c = _signal(oname, car)
            if c not in lay.carriers:
                continue
            u = np.zeros(N)
            ur = np.zeros(len(refs))
            for i, col in cols:
                u[col] += L.D[o][i]
            for i, col in rcols:
                ur[col] += L.D[o][i]
            u[off:off + ns] = L.C[o]
            j = lay.carriers.index(c)
            M[:n] += np.outer(B[:, j], u)
            R[:n] += np.outer(B[:, j], ur)
            U[j] += u
            U_r[j] += ur
        off += ns
    return Loop(M, R, U, U_r, refs, lay.carriers)


def close(A: np.ndarray, B: np.ndarray, lay: Layout, laws: Mapping[str, DiscreteLaw]) -> np.ndarray:
    """The closed loop's matrix alone (y_ref = 0): :func:`closed_loop`'s M."""
    return closed_loop(A, B, lay, laws).M


def continuous_matrix(cfg: RigConfig, v: float, D: Mapping[str, float],
                      lay: Optional[Layout] = None) -> np.ndarray:
    """The continuous closed loop at speed v: states [plant, each controlled carrier's law
    as designed (PI-PD: x_I, the differentiator's x_f; P: none)]."""
    lay = layout(cfg) if lay is None else lay
    A, B = plant_matrices(cfg, v, D, lay)
    return close(A, B, lay, {c: law_at(cfg, c, v, continuous=True, D=D[c]) for c in lay.controlled})


def sampled_matrix(cfg: RigConfig, v: float, D: Mapping[str, float],
                   lay: Optional[Layout] = None) -> np.ndarray:
    """The sampled closed loop at speed v, as implemented: states [plant, each controlled
    carrier's law states (PI-PD: x_I, e_y, e_ψ, ê_ψ)]; z_{k+1} = Φ z_k."""
    lay = layout(cfg) if lay is None else lay
    Ad, Bd = held(cfg, v, D, lay)
    return close(Ad, Bd, lay, {c: law_at(cfg, c, v, D=D[c]) for c in lay.controlled})


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class SpeedResult:
    """The coupled loop at one speed: continuous eigenvalues at each carrier's D_min, and the
    sampled loop's spectral radius, the largest over the gate's damping cases (and, reported
    only, over the other D_min/D_max combinations)."""

    v: float
    g: float                         # the schedule's gain factor at v
    eigenvalues: np.ndarray          # continuous, 1/s, sorted by real part (slowest last)
    spectral_radius: float           # sampled, max over damping_cases (what the gate judges)
    radius_D: dict                   # the damping case of that radius
    ungated_radius: Optional[float] = None   # sampled, max over the other D_min/D_max cases (reported)
    rightmost: complex = complex(math.nan)   # continuous: the pole with the largest real part over every
    rightmost_D: Optional[dict] = None       # D_min/D_max combination (reported), and its damping case

    @property
    def every_damping_radius(self) -> float:
        """The sampled loop's largest |z| over every D_min/D_max combination (gated or not)."""
        return max(self.spectral_radius, self.ungated_radius or 0.0)

    @property
    def stable(self) -> bool:
        return bool(np.all(self.eigenvalues.real < 0))

    @property
    def sampled_stable(self) -> bool:
        return bool(self.spectral_radius < 1.0)

    @property
    def least_damped(self) -> complex:
        """The pole with the largest real part (the slowest decay: the one that decides stability)."""
        return complex(self.eigenvalues[-1])

    @property
    def zeta_min(self) -> float:
        """The smallest damping ratio −Re λ/|λ| of any pole (−1 … 1; 1 for a real stable pole)."""
        ev = self.eigenvalues[np.abs(self.eigenvalues) > 1e-12]
        return float(np.min(-ev.real / np.abs(ev))) if len(ev) else 1.0


@dataclass(frozen=True)
class CoupledResult:
    carriers: tuple[str, ...]        # in contact
    controlled: tuple[str, ...]      # controlled and in contact
    v_design: float
    band: Optional[tuple[float, float]]   # held: |v| < v_min
    points: tuple[SpeedResult, ...]


def _radius(Phi: np.ndarray) -> float:
    with np.errstate(all="ignore"):
        z = np.linalg.eigvals(Phi)
    r = float(np.max(np.abs(z))) if len(z) else 0.0
    return r if math.isfinite(r) else math.inf


def at_speed(cfg: RigConfig, v: float, lay: Optional[Layout] = None) -> SpeedResult:
    lay = layout(cfg) if lay is None else lay
    ev = np.linalg.eigvals(continuous_matrix(cfg, v, d_min(cfg, lay.carriers), lay))
    ev = ev[np.lexsort((ev.imag, ev.real))]
    worst, worst_D = -1.0, {}
    gated = damping_cases(cfg, v, lay)
    for D in gated:
        r = _radius(sampled_matrix(cfg, v, D, lay))
        if r > worst:
            worst, worst_D = r, D
    other = [_radius(sampled_matrix(cfg, v, D, lay)) for D in all_damping_cases(cfg, lay.carriers) if D not in gated]
    right, right_D = complex(-math.inf), None
    for D in all_damping_cases(cfg, lay.carriers):
        with np.errstate(all="ignore"):
            z = np.linalg.eigvals(continuous_matrix(cfg, v, D, lay))
        z = complex(z[np.argmax(z.real)]) if len(z) else complex(-math.inf)
        if not z.real <= right.real:                 # NaN (not computable) counts as the worst
            right, right_D = z, D
    return SpeedResult(v, gain_factor(cfg, v), ev, worst, worst_D, max(other) if other else None, right, right_D)


def analyse(cfg: RigConfig) -> CoupledResult:
    """The coupled loop at every analysed speed (:func:`speeds`)."""
    lay = layout(cfg)
    vs, band = speeds(cfg)
    return CoupledResult(lay.carriers, lay.controlled, design_speed(cfg), band,
                         tuple(at_speed(cfg, v, lay) for v in vs))


# --------------------------------------------------------------------------- the gate
@dataclass(frozen=True)
class Instability:
    """Where the sampled loop as implemented is not stable: the speed, the damping case and
    its worst pole (z; ln(z)/h in 1/s by :attr:`s`); z is NaN when it cannot be computed."""

    v: float
    D: dict
    z: complex
    h: float
    coupled: bool          # a vehicle config (named in the message) or the paper's set-up

    @property
    def s(self) -> complex:
        z = self.z
        return complex(np.log(complex(z)) / self.h) if z == z and z != 0 else complex(np.nan)

    def where(self) -> str:
        if not self.coupled:
            return f"plant (10) with D = {next(iter(self.D.values())):g}"
        Ds = ", ".join(f"D_{c} = {d:g}" for c, d in self.D.items())
        return f"coupled loop at v = {self.v:+g} m/s ({Ds})"


def instability(cfg: RigConfig) -> Optional[Instability]:
    """The first (speed, damping case) at which the sampled closed loop as implemented has a
    pole with |z| >= 1 (or cannot be computed); None if stable at every analysed speed and
    damping case. Speeds are tried from v_design outwards (a gain set unstable at its own
    design speed is named there). The stability gate of every run and gain change."""
    lay = layout(cfg)
    vs, _ = speeds(cfg)
    vd = design_speed(cfg)
    coupled = applies(cfg)
    for v in sorted(vs, key=lambda x: (abs(x - vd), x)):
        try:
            with np.errstate(all="ignore"):
                cases = damping_cases(cfg, v, lay)
        except (ArithmeticError, ValueError):        # numbers so extreme the matrices overflow
            return Instability(v, d_min(cfg, lay.carriers), complex(np.nan), cfg.controller.h, coupled)
        for D in cases:
            try:
                with np.errstate(all="ignore"):
                    z = np.linalg.eigvals(sampled_matrix(cfg, v, D, lay))
            except (ArithmeticError, ValueError):    # (LinAlgError is a ValueError)
                return Instability(v, D, complex(np.nan), cfg.controller.h, coupled)
            if not len(z):
                continue
            worst = complex(z[np.argmax(np.abs(z))])
            if not abs(worst) < 1.0:                 # NaN (not computable) counts as unstable
                return Instability(v, D, worst, cfg.controller.h, coupled)
    return None


def pairs(ev: np.ndarray) -> list[list[float]]:
    return [[float(e.real), float(e.imag)] for e in ev]


def to_json(r: CoupledResult) -> dict:
    """``rig tune --json``'s ``coupled`` (continuous) and ``coupled_sampled`` lists, and what they cover."""
    return {
        "coupled": [{"v": p.v, "eigenvalues": pairs(p.eigenvalues), "stable": p.stable, "g": p.g,
                     "least_damped": [p.least_damped.real, p.least_damped.imag], "zeta_min": p.zeta_min}
                    for p in r.points],
        "coupled_sampled": [{"v": p.v, "spectral_radius": p.spectral_radius, "stable": p.sampled_stable,
                             "D": p.radius_D, "ungated_spectral_radius": p.ungated_radius} for p in r.points],
        "coupled_every_damping": [{"v": p.v, "rightmost": [p.rightmost.real, p.rightmost.imag], "D": p.rightmost_D,
                                   "spectral_radius": p.every_damping_radius} for p in r.points],
        "coupled_setup": {"carriers_in_contact": list(r.carriers), "controlled": list(r.controlled),
                          "v_design": r.v_design, "held_band": list(r.band) if r.band else None},
    }


# --------------------------------------------------------------------------- linear step responses
@dataclass(frozen=True)
class StepResponse:
    """The sampled loop's response to a unit reference step on ``stepped`` carriers (at k = 0)."""

    t: np.ndarray
    y: dict            # carrier -> lateral displacement per unit step
    u: dict            # carrier -> input (A per m of step)


def step_response(cfg: RigConfig, v: float, D: Mapping[str, float], stepped: tuple[str, ...],
                  t_end: float = 20.0, laws: Optional[Mapping[str, DiscreteLaw]] = None) -> StepResponse:
    """The linear sampled loop at speed v (damping ``D``) from rest, every carrier of ``stepped``
    given a unit reference step: each carrier's y and u (the linear model: no hysteresis, no
    limits). ``laws``: the laws to wire (default: the configured one per controlled carrier)."""
    lay = layout(cfg)
    Ad, Bd = held(cfg, v, D, lay)
    if laws is None:
        laws = {c: law_at(cfg, c, v, D=D[c]) for c in lay.controlled}
    L = closed_loop(Ad, Bd, lay, laws)
    r = np.array([1.0 if c in stepped else 0.0 for c in L.refs])
    n = int(round(t_end / cfg.controller.h)) + 1
    z = np.zeros(L.M.shape[0])
    Y = np.zeros((n, len(lay.carriers)))
    Uo = np.zeros((n, len(lay.carriers)))
    Rr = L.R @ r
    Ur = L.U_r @ r
    for k in range(n):
        Y[k] = [z[lay.y(c)] for c in lay.carriers]
        Uo[k] = L.U @ z + Ur
        z = L.M @ z + Rr
    t = np.arange(n) * cfg.controller.h
    return StepResponse(t, {c: Y[:, i] for i, c in enumerate(lay.carriers)},
                        {c: Uo[:, i] for i, c in enumerate(lay.carriers)})
