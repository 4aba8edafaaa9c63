"""Controllers of Sec. 5: the cascaded PI-PD law (11)–(14) and the P baseline of Sec. 5.1,
plus open-loop input generators for identification experiments.

Each law is written once, as its gains and its arithmetic (:class:`PIPDLaw`, :class:`PLaw`):
the runtime controllers (:class:`PIPDController`, :class:`PController`) step it with plain
floats every cycle, and :meth:`PIPDLaw.discrete` evaluates the very same arithmetic on linear
forms to give its discrete state-space form (:class:`DiscreteLaw`), from which the sampled
analysis, the coupled analysis and the stability gate build their closed loops
(:mod:`rig_runtime.coupled`). A new law written here is analysed for free.

Discretisation (h = 5 ms): Tustin (bilinear) for the outer integrator (14) and for the
differentiator G(s) = s/(T_f s + 1) of (12). Tustin maps the stable left half plane onto
the unit disc for any h, so the filter stays stable and well damped even for T_f close to
h, and it matches the continuous frequency response best up to a few Hz where the loop's
eigenvalues (< 70 1/s ≈ 11 Hz) live. The derivative acts on the error e_ψ = ψ_ref − ψ, so
the D term sees ψ̇_ref as in (11) without measuring ẏ.

The step is pure-Python scalar arithmetic: it runs every 5 ms inside the loop (no numpy here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Mapping, Sequence

from .config import DECOUPLED_GAINS, PIPD_GAINS, DecoupledGains, PIPDGains
from .config import Controller as ControllerConfig
from .damping import InputDamping, YawDamping

Matrix = tuple[tuple[float, ...], ...]


# --------------------------------------------------------------------------- the description
@dataclass(frozen=True)
class DiscreteLaw:
    """A control law's linear state-space form, as implemented, at the schedule's gain factor g:

        x⁺ = A x + B w,   out = C x + D w

    w: the inputs of this step (by name, ``inputs``), x: the states as the previous step left
    them, x⁺: as this step leaves them (``states``: the names the runtime logs them under),
    out: the outputs of this step (``outputs``). ``h`` the sample time (0: a continuous law,
    ẋ = A x + B w). ``scheduled``: the gains the schedule's factor g multiplies (already in the
    matrices). Saturation, the ψ_ref limit, anti-windup and the standstill hold are not
    linear: the runtime adds them around the same arithmetic; the analysis, like the paper's,
    is of the linear loop."""

    law: str
    h: float
    g: float
    inputs: tuple[str, ...]
    states: tuple[str, ...]
    outputs: tuple[str, ...]
    A: Matrix
    B: Matrix
    C: Matrix
    D: Matrix
    scheduled: tuple[str, ...] = ()


class _Form:
    """A linear form over named basis symbols (a row of coefficients): the law's arithmetic
    evaluated on these instead of floats gives its matrices, entry by entry with the same
    floating-point operations as the runtime's step."""

    __slots__ = ("v",)

    def __init__(self, v: list[float]):
        self.v = v

    def __add__(self, o: "_Form") -> "_Form":
        return _Form([a + b for a, b in zip(self.v, o.v)])

    def __sub__(self, o: "_Form") -> "_Form":
        return _Form([a - b for a, b in zip(self.v, o.v)])

    def __rmul__(self, k: float) -> "_Form":
        return _Form([k * a for a in self.v])

    def __truediv__(self, k: float) -> "_Form":
        return _Form([a / k for a in self.v])


def _basis(n: int) -> list[_Form]:
    return [_Form([1.0 if j == i else 0.0 for j in range(n)]) for i in range(n)]


def _describe(law: str, h: float, g: float, inputs: tuple[str, ...], states: tuple[str, ...],
              outputs: tuple[str, ...], new: Sequence[_Form], out: Sequence[_Form],
              scheduled: tuple[str, ...]) -> DiscreteLaw:
    """Split the forms of the new states and the outputs (over [states, inputs]) into A, B, C, D."""
    ns = len(states)
    return DiscreteLaw(law, h, g, inputs, states, outputs,
                       tuple(tuple(f.v[:ns]) for f in new), tuple(tuple(f.v[ns:]) for f in new),
                       tuple(tuple(f.v[:ns]) for f in out), tuple(tuple(f.v[ns:]) for f in out), scheduled)


def _without(law: DiscreteLaw, *names: str) -> DiscreteLaw:
    """``law`` without states that no output and no other kept state depends on."""
    for state in names:
        law = _without1(law, state)
    return law


def _without1(law: DiscreteLaw, state: str) -> DiscreteLaw:
    """``law`` without a state that no output and no other state depends on."""
    i = law.states.index(state)
    keep = [j for j in range(len(law.states)) if j != i]
    cut = lambda M: tuple(tuple(row[j] for j in keep) for row in M)     # noqa: E731
    return replace(law, states=tuple(law.states[j] for j in keep), A=cut(tuple(law.A[j] for j in keep)),
                   B=tuple(law.B[j] for j in keep), C=cut(law.C))


LAW_INPUTS = ("y_ref", "y", "psi")      # what a carrier's law reads each step


@dataclass(frozen=True)
class PIPDLaw:
    """The cascaded PI-PD law (11)–(14) with its gains, discretised at h (Tustin):

        e_y = y_ref − y,   x_I⁺ = x_I + (h/2) g (e_y + e_y,prev),   ψ_ref = g K_P,y e_y + K_I,y x_I⁺
        e_ψ = κ ψ_ref − ψ,  ê_ψ⁺ = a ê_ψ + b (e_ψ − e_ψ,prev),      u = σ K_P,ψ e_ψ + K_D,ψ ê_ψ⁺

    with a = (2T_f − h)/(2T_f + h), b = 2/(2T_f + h) (Tustin of s/(T_f s + 1)) — computed here
    once. g is the speed schedule's factor on the outer PI (the integrator integrates g·e_y, so
    its share of ψ_ref does not jump when g changes). :meth:`outer` and :meth:`inner` are the
    arithmetic, in floats for the runtime and in linear forms for :meth:`discrete`.

    σ = κ = 1 but with the damping schedule (``D_sched`` > 0; docs/vehicle.md §5): the law knows
    the damping D̂ of (7) its own commanded current gives (:class:`rig_runtime.damping.InputDamping`:
    the same filter and (7) as the plant) and schedules the yaw loop on it. At D̂ = D_min σ = κ = 1;
    above, σ = 1 + D_sched (σ₁ − 1), σ₁ the raise of K_P,ψ that keeps the yaw loop's slow pole in
    its first-order estimate ω0² (1 + K σK_P,ψ)/(2 D̂ ω0 + K ω0² K_D,ψ) at its D_min value (the
    estimate is low at D_min, where the loop is not far overdamped: D_sched = 2 puts the coupled
    loop at D_max where it is at D_min, docs/vehicle.md §5), and κ keeps the yaw loop's static
    gain K σK_P,ψ κ/(1 + K σK_P,ψ) at D_min's. D̂ is a
    schedule variable like g: the description is at a frozen D̂ (``D`` of :meth:`discrete`), and the
    analysis takes the plant's D there. The yaw parameters are the carrier's (``yaw``)."""

    K_P_y: float
    K_I_y: float
    K_P_psi: float
    K_D_psi: float
    T_f_psi: float
    h: float
    D_sched: float = 0.0
    yaw: YawDamping | None = None     # the carrier's yaw parameters (needed with D_sched > 0)
    half_h: float = field(init=False)
    a: float = field(init=False)
    b: float = field(init=False)

    STATES = ("x_I", "e_y", "e_psi", "de_psi")      # after a step; e_y, e_psi: the previous samples
    SCHEDULED = ("K_P_y", "K_I_y")
    #: the law's signals, by name (SI unit): each controlled carrier's log columns ``{carrier}_{name}``,
    #: the live panel, telemetry and ``rig log plot`` show these (the runtime's record, PIPDInternals)
    SIGNALS = MappingProxyType({"e_y": "m", "x_I": "m s", "psi_ref": "rad", "e_psi": "rad",
                                "de_psi": "rad/s", "u_unsat": "A"})

    def __post_init__(self):
        den = 2.0 * self.T_f_psi + self.h
        object.__setattr__(self, "half_h", 0.5 * self.h)
        object.__setattr__(self, "a", (2.0 * self.T_f_psi - self.h) / den)
        object.__setattr__(self, "b", 2.0 / den)
        if self.D_sched and self.yaw is None:
            raise ValueError("D_sched > 0 needs the carrier's yaw parameters (yaw)")

    @classmethod
    def of(cls, gains: PIPDGains, h: float, yaw: YawDamping | None = None) -> "PIPDLaw":
        """The law with ``gains``; without the carrier's ``yaw`` the law at D_min (no damping schedule)."""
        return cls(gains.K_P_y, gains.K_I_y, gains.K_P_psi, gains.K_D_psi, gains.T_f_psi, h,
                   gains.D_sched if yaw is not None else 0.0, yaw if gains.D_sched else None)

    @property
    def scheduled_on_damping(self) -> bool:
        """Whether the yaw loop is scheduled on D̂ (D_sched > 0)."""
        return bool(self.D_sched)

    def yaw_gains(self, D: float | None) -> tuple[float, float]:
        """(σ K_P,ψ, κ) at D̂ = D; (K_P,ψ, 1) without the schedule, for D = None and D <= D_min."""
        m = self.yaw
        if not self.D_sched or D is None or D <= m.D_min:
            return self.K_P_psi, 1.0
        kk = m.K * self.K_P_psi
        kd = m.K * m.omega0 ** 2 * self.K_D_psi
        full = ((1.0 + kk) * (2.0 * D * m.omega0 + kd) / (2.0 * m.D_min * m.omega0 + kd) - 1.0) / kk
        sigma = 1.0 + self.D_sched * (full - 1.0)
        return self.K_P_psi * sigma, (1.0 + kk * sigma) / ((1.0 + kk) * sigma)

    def psi_ref(self, g, e_y, x_I):
        """The outer PI's output from the error and the integrator's (updated) state."""
        return self.K_P_y * g * e_y + self.K_I_y * x_I

    def seed(self, g: float, e_y: float, psi_ref: float) -> float:
        """The integrator state for which the outer PI gives ``psi_ref`` at error e_y (bumpless
        start, resume, gain change); 0 without integral action."""
        return (psi_ref - self.K_P_y * g * e_y) / self.K_I_y if self.K_I_y else 0.0

    def outer(self, g, e_y, e_y_prev, x_I_prev):
        """The outer PI's step: (the integration done, x_I⁺, ψ_ref)."""
        dI = self.half_h * g * (e_y + e_y_prev)
        x_I = x_I_prev + dI
        return dI, x_I, self.psi_ref(g, e_y, x_I)

    def inner(self, psi_ref, psi, e_psi_prev, de_prev, D=None):
        """The inner PD's step on e_ψ with the Tustin differentiator at D̂ = D: (e_ψ, ê_ψ⁺, u)."""
        if D is None:
            e_psi = psi_ref - psi
            kp = self.K_P_psi
        else:
            kp, kappa = self.yaw_gains(D)
            e_psi = kappa * psi_ref - psi
        de = self.a * de_prev + self.b * (e_psi - e_psi_prev)
        return e_psi, de, kp * e_psi + self.K_D_psi * de

    DAMPING_SIGNAL = MappingProxyType({"D_hat": "1"})   # D̂ of (7), the yaw gains' (with D_sched > 0)

    @property
    def signals(self) -> Mapping[str, str]:
        """The signals this law (with these gains) computes: ``SIGNALS`` (and D̂ with the damping schedule)."""
        return MappingProxyType({**self.SIGNALS, **self.DAMPING_SIGNAL}) if self.D_sched else self.SIGNALS

    def discrete(self, g: float = 1.0, D: float | None = None) -> DiscreteLaw:
        """The linear law as the runtime steps it (:class:`DiscreteLaw`), at factor g and at
        D̂ = D (None: D_min)."""
        x_I, e_y0, e_psi0, de0, y_ref, y, psi = _basis(7)
        e_y = y_ref - y
        _, x_I1, psi_ref = self.outer(g, e_y, e_y0, x_I)
        e_psi, de, u = self.inner(psi_ref, psi, e_psi0, de0, D)
        return _describe("pipd", self.h, g, LAW_INPUTS, self.STATES, ("u",),
                         (x_I1, e_y, e_psi, de), (u,), self.SCHEDULED)

    def continuous(self, g: float = 1.0, D: float | None = None) -> DiscreteLaw:
        """The law as designed (11)–(14), continuous (h = 0): states x_I (ẋ_I = g e_y) and the
        differentiator's x_f (ê_ψ = (e_ψ − x_f)/T_f = ẋ_f); at D̂ = D."""
        x_I, x_f, y_ref, y, psi = _basis(5)
        e_y = y_ref - y
        kp, kappa = self.yaw_gains(D)
        e_psi = kappa * self.psi_ref(g, e_y, x_I) - psi
        de = (e_psi - x_f) / self.T_f_psi
        u = kp * e_psi + self.K_D_psi * de
        return _describe("pipd", 0.0, g, LAW_INPUTS, ("x_I", "x_f"), ("u",), (g * e_y, de), (u,),
                         self.SCHEDULED)


@dataclass(frozen=True)
class DecoupledLaw(PIPDLaw):
    """The decoupled PI-PD of the vehicle (``law: decoupled``; docs/vehicle.md §5): the PI-PD of
    :class:`PIPDLaw` per carrier, its yaw reference lowered by a feed term w read across the
    carriers, and an integral term on the yaw error:

        ψ_ref = g K_P,y e_y + K_I,y x_I⁺ − w,   w = g K_P,y (1 − b_y) y_ref + K_x,y (d + T_x,y d̂') [− K_t,y |g| d]
        d = y_f − y_r,   d̂'⁺ = a d̂' + b (d − d_prev)  (the PD's Tustin differentiator, on d)
        u = K_P,ψ e_ψ + K_D,ψ ê_ψ⁺ + K_I,ψ x_Iψ⁺,   x_Iψ⁺ = x_Iψ + (h/2)(e_ψ + e_ψ,prev)

    * setpoint weighting b_y: a reference step moves ψ_ref by g K_P,y b_y Δy_ref, not
      g K_P,y Δy_ref (the integrator still removes the error: the step does not kick the current);
    * decoupling K_x,y: (2a)/(2b) drive each carrier by a_c (y_f − y_r) with a_c = c̄_y,c v/(2 l0,c);
      a yaw angle −(y_f − y_r)/(2 l0,c) cancels it at every speed and direction (a_c / c̄_y,c v does
      not depend on v), leaving each carrier a pure integrator under its own PI-PD; T_x,y leads
      the term by the yaw loop's lag (ψ follows ψ_ref with ~0.2 s: (15)'s slow pole);
    * K_I,ψ: the yaw loop's own integrator, so that ψ reaches ψ_ref (the PD alone holds ψ at
      K K_P,ψ/(1 + K K_P,ψ) ≈ 0.2 of it, and the hysteresis of (6) moves that) — then
      K_x,y = 1/(2 l0) decouples exactly and the outer loop is not left to fight the yaw's statics;
    * K_t,y (the bracket: on the trailing carrier only — the rear where g > 0, the front where
      g < 0, g's sign being the running direction): the trailing carrier follows the leading one.
      The leading carrier's lateral mode is unstable open loop (ẏ = a (y_f − y_r), a > 0 for it);
      where its own yaw is slow (D_max: ψ follows ψ_ref at ~0.1 1/s) only the trailing carrier's
      yaw can hold y_f − y_r, and without this term no gains of the law keep the loop stable at
      every D_min/D_max combination (docs/vehicle.md §5). Scaled by |g| like the outer PI: the
      loop gain c̄_y v K_t,y |g| does not depend on the speed.

    With b_y = 1, K_x,y = 0 and K_I,ψ = 0 it is the PI-PD. It reads both carriers' y (inputs
    ``y.front``, ``y.rear``): in the runtime through the lanes' one cross-lane stage
    (:class:`rig_runtime.lanes.LateralPair`)."""

    b_y: float = 1.0
    K_x_y: float = 0.0
    K_I_psi: float = 0.0
    T_x_y: float = 0.0
    K_t_y: float = 0.0
    carrier: str | None = None     # "front"/"rear": which carrier's law (K_t,y acts on the trailing one)

    SCHEDULED = ("K_P_y", "K_I_y")
    INPUTS = LAW_INPUTS + ("y.front", "y.rear")
    STATES = PIPDLaw.STATES + ("x_I_psi", "d_y", "dd_y")
    #: the PI-PD's signals plus w (the feed term ψ_ref is lowered by), w_cross (its cross-carrier
    #: part K_x,y (d + T_x,y d̂') − K_t,y |g| d on the trailing carrier) and x_I_psi (the yaw integrator; only with K_I,ψ > 0)
    SIGNALS = MappingProxyType({**PIPDLaw.SIGNALS, "w": "rad", "w_cross": "rad", "x_I_psi": "rad s"})

    @property
    def signals(self) -> Mapping[str, str]:
        """``SIGNALS``; without x_I_psi when K_I,ψ = 0 (then no part of the law, as in :meth:`discrete`);
        with D̂ under the damping schedule."""
        own = {n: u for n, u in self.SIGNALS.items() if self.K_I_psi or n != "x_I_psi"}
        return MappingProxyType({**own, **(self.DAMPING_SIGNAL if self.D_sched else {})})

    @classmethod
    def of(cls, gains: DecoupledGains, h: float, carrier: str | None = None,
           yaw: YawDamping | None = None) -> "DecoupledLaw":
        return cls(gains.K_P_y, gains.K_I_y, gains.K_P_psi, gains.K_D_psi, gains.T_f_psi, h,
                   gains.D_sched if yaw is not None else 0.0, yaw if gains.D_sched else None, b_y=gains.b_y, K_x_y=gains.K_x_y, K_I_psi=gains.K_I_psi, T_x_y=gains.T_x_y,
                   K_t_y=gains.K_t_y, carrier=carrier)

    def trailing(self, g) -> bool:
        """Whether this carrier trails at the direction g's sign says (the rear where g > 0)."""
        return self.carrier == ("rear" if g > 0 else "front")

    def cross(self, y_front, y_rear, d_prev, dd_prev):
        """The carriers' difference d = y_f − y_r and its filtered derivative's step: (d, d̂'⁺)."""
        d = y_front - y_rear
        return d, self.a * dd_prev + self.b * (d - d_prev)

    def feed(self, g, y_ref, d, dd):
        """w: what ψ_ref is lowered by (setpoint weight, decoupling, the trailing carrier's following)."""
        w = self.K_P_y * g * (1.0 - self.b_y) * y_ref + self.K_x_y * (d + self.T_x_y * dd)
        return w - self.K_t_y * abs(g) * d if self.K_t_y and self.trailing(g) else w

    def inner_i(self, psi_ref, psi, e_psi_prev, de_prev, x_Ip_prev, D=None):
        """The inner PID's step at D̂ = D: (e_ψ, ê_ψ⁺, the integration done, x_Iψ⁺, u)."""
        e_psi, de, u = self.inner(psi_ref, psi, e_psi_prev, de_prev, D)
        dIp = self.half_h * (e_psi + e_psi_prev)
        x_Ip = x_Ip_prev + dIp
        return e_psi, de, dIp, x_Ip, u + self.K_I_psi * x_Ip

    def discrete(self, g: float = 1.0, D: float | None = None) -> DiscreteLaw:
        x_I, e_y0, e_psi0, de0, x_Ip, d0, dd0, y_ref, y, psi, yf, yr = _basis(12)
        e_y = y_ref - y
        _, x_I1, psi_ref = self.outer(g, e_y, e_y0, x_I)
        d, dd = self.cross(yf, yr, d0, dd0)
        e_psi, de, _, x_Ip1, u = self.inner_i(psi_ref - self.feed(g, y_ref, d, dd), psi, e_psi0, de0, x_Ip, D)
        law = _describe("decoupled", self.h, g, self.INPUTS, self.STATES, ("u",),
                        (x_I1, e_y, e_psi, de, x_Ip1, d, dd), (u,), self.SCHEDULED)
        # K_I,ψ = 0: the yaw integrator acts on nothing (a pole at z = 1 that no output sees): not part of the law
        return law if self.K_I_psi else _without(law, "x_I_psi")

    def continuous(self, g: float = 1.0, D: float | None = None) -> DiscreteLaw:
        x_I, x_f, x_Ip, x_d, y_ref, y, psi, yf, yr = _basis(9)
        e_y = y_ref - y
        d = yf - yr
        dd = (d - x_d) / self.T_f_psi                  # s/(T_f s + 1) d, as the PD's differentiator
        kp, kappa = self.yaw_gains(D)
        e_psi = kappa * (self.psi_ref(g, e_y, x_I) - self.feed(g, y_ref, d, dd)) - psi
        de = (e_psi - x_f) / self.T_f_psi
        u = kp * e_psi + self.K_D_psi * de + self.K_I_psi * x_Ip
        law = _describe("decoupled", 0.0, g, self.INPUTS, ("x_I", "x_f", "x_I_psi", "x_d"), ("u",),
                        (g * e_y, de, e_psi, dd), (u,), self.SCHEDULED)
        return law if self.K_I_psi else _without(law, "x_I_psi")


@dataclass(frozen=True)
class PLaw:
    """The P law of Sec. 5.1: u = g K_P (y_ref − y); no states."""

    K_P: float
    h: float

    SIGNALS = MappingProxyType({"e_y": "m", "u_unsat": "A"})     # see PIPDLaw.SIGNALS

    @property
    def signals(self) -> Mapping[str, str]:
        return self.SIGNALS

    def u(self, g, e):
        return self.K_P * g * e

    def discrete(self, g: float = 1.0, D: float | None = None) -> DiscreteLaw:
        """At factor g (the law has no yaw loop: D plays no part)."""
        y_ref, y, psi = _basis(3)
        return _describe("p", self.h, g, LAW_INPUTS, (), ("u",), (), (self.u(g, y_ref - y),), ("K_P",))

    def continuous(self, g: float = 1.0, D: float | None = None) -> DiscreteLaw:
        return replace(self.discrete(g), h=0.0)


def law_of(cfg: ControllerConfig, carrier: str | None = None, yaw: YawDamping | None = None) -> "PIPDLaw | PLaw":
    """The configured law (``controller.law``) with its gains (with ``carrier``: that carrier's;
    ``yaw``: that carrier's yaw parameters, which a law scheduled on its damping needs)."""
    if cfg.law == "p":
        return PLaw(cfg.K_P, cfg.h)
    if cfg.law == "decoupled":
        return DecoupledLaw.of(cfg.decoupled, cfg.h, carrier, yaw)
    return PIPDLaw.of(cfg.gains(carrier) if carrier is not None else cfg.pipd, cfg.h, yaw)


# --------------------------------------------------------------------------- the runtime
#: s: how long D̂ of (7) must stay above D_min before the damping schedule's gains follow it. In
#: closed loop the current moves by more than (7)'s ~0.5 µA a cycle nearly always; a cycle in which
#: it does not (measured: 2 of 14400 carrier-cycles of a lockstep run) is a blip of D̂ that the
#: gains need not follow — followed, the P term kept across the blip turned one cycle's ψ noise,
#: times σ, into a lasting ψ_ref offset (a held carrier moved 17 % of the other's step). Still
#: currents that last (saturation, a still loop) are followed; the frozen analysis is unaffected.
DAMPING_PERSIST_S = 0.1


@dataclass(slots=True)
class PIPDInternals:
    """What one step computed, for the recorder."""

    e_y: float = 0.0
    x_I: float = 0.0
    psi_ref: float = 0.0
    e_psi: float = 0.0
    de_psi: float = 0.0      # filtered derivative of e_ψ
    u_unsat: float = 0.0
    u: float = 0.0


class PIPDController:
    """Steps :class:`PIPDLaw` every cycle, with the nonlinear parts around it: the ψ_ref
    limit, saturation and anti-windup, bumpless start, the standstill hold.

    ``step(y_ref, y, psi)`` returns the saturated current command; ``limit_feedback(u)``
    tells the controller what was actually applied after the safety limits, so that the
    outer integrator does not wind up against a limit it did not impose itself.

    The speed schedule (docs/vehicle.md) acts through two calls between steps:
    ``set_gain_factor(g)`` makes the outer PI's gains K_P_y·g and K_I_y·g (the integrator
    integrates g·e_y, so its share of ψ_ref does not jump when g changes: it holds the yaw
    angle the offsets need, which does not depend on the speed); ``hold(ramp_s)`` freezes
    the integrator and ramps ψ_ref linearly to 0 over ``ramp_s`` while the inner PD keeps
    ψ at ψ_ref; ``resume()`` re-seeds the integrator at the next step so that ψ_ref goes on
    from where the hold left it. With g = 1 and no hold the law is the paper's, bit for bit.
    """

    def __init__(self, cfg: ControllerConfig, u_max: float, psi_ref_max: float | None = None,
                 gains: PIPDGains | None = None, yaw: YawDamping | None = None):
        self.law = PIPDLaw.of(gains if gains is not None else cfg.pipd, cfg.h, yaw)
        self._yaw = yaw
        self._damp = InputDamping(yaw, cfg.h) if self.law.scheduled_on_damping else None   # D̂ of (7) from u
        self._D = None          # the D̂ the last step's yaw gains were at (None: D_min, no schedule)
        self._above = 0         # cycles D̂ has been above D_min in a row
        self._persist = max(1, round(DAMPING_PERSIST_S / cfg.h))
        self._psi_target = None     # ψ_ref the next re-seed continues from (None: the last step's)
        self.h = cfg.h
        self.u_max = u_max
        self.psi_ref_max = psi_ref_max
        self.st = PIPDInternals()
        self._e_y_prev = 0.0
        self._e_psi_prev = 0.0
        self._dI = 0.0          # integration done in the last step (undone on limit feedback)
        self._started = False
        self.g = 1.0            # the schedule's gain factor on K_P_y, K_I_y (1: fixed gains)
        self.held = False       # the lateral loop holds (standstill band)
        self._reseed = False    # resumed: the next step re-seeds x_I (ψ_ref continuous)
        self._psi_hold = 0.0    # ψ_ref when the hold began
        self._hold_n = 1        # steps of the ramp to 0
        self._hold_k = 0        # steps held so far
        self._w = 0.0           # what ψ_ref is lowered by (the decoupled law's feed term; 0 here)

    kpy = property(lambda self: self.law.K_P_y)
    kiy = property(lambda self: self.law.K_I_y)
    kpp = property(lambda self: self.law.K_P_psi)
    kdp = property(lambda self: self.law.K_D_psi)
    tf = property(lambda self: self.law.T_f_psi)

    def reset(self) -> None:
        """Forget all history; the next step starts bumplessly."""
        self.st = PIPDInternals()
        self._e_y_prev = self._e_psi_prev = self._dI = 0.0
        self._psi_target = None
        self._started = False
        self.held = self._reseed = False

    def set_gain_factor(self, g: float) -> None:
        """The schedule's factor on the outer PI's gains from the next step on (sign included)."""
        self.g = g

    def hold(self, ramp_s: float) -> None:
        """Enter the hold: integrator frozen, ψ_ref from its latest value linearly to 0 over
        ``ramp_s`` (at least one step); the inner PD keeps running."""
        if not self.held:
            self.held = True
            self._reseed = False
            self._psi_hold = self.st.psi_ref
            self._hold_n = max(1, round(ramp_s / self.h))
            self._hold_k = 0

    def resume(self) -> None:
        """Leave the hold: the next step re-seeds x_I so that ψ_ref is continuous (bumpless)."""
        if self.held:
            self.held = False
            self._reseed = True
            self._psi_target = None

    def start(self, y_ref: float, y: float, psi: float, u0: float = 0.0) -> None:
        """Bumpless start: choose x_I so that ψ_ref = ψ (no proportional jump) and seed the
        differentiator with the current error (no derivative kick)."""
        e_y = y_ref - y
        if self._damp is not None:          # D̂ = D_min for the first command (damping.InputDamping.start)
            self._damp.start(u0)
            self._D = self._damp.now
            self._above = 0
        kpp, kappa = self.law.yaw_gains(self._D)
        psi_ref = (psi + u0 / kpp) / kappa
        x_I = self.law.seed(self.g, e_y, psi_ref + self._w)
        self.st = PIPDInternals(e_y=e_y, x_I=x_I, psi_ref=psi_ref, u=u0, u_unsat=u0)
        self._e_y_prev = e_y
        self._e_psi_prev = u0 / kpp
        self._started = True
        self.held = self._reseed = False
        self._psi_target = None

    def step(self, y_ref: float, y: float, psi: float) -> float:
        if not self._started:
            self.start(y_ref, y, psi)
        st = self.st
        law = self.law
        e_y = y_ref - y
        g = self.g
        if self._damp is not None:
            D = self._damp.now
            if D > law.yaw.D_min:
                self._above += 1
                if self._above < self._persist:   # a blip of (7) (one still cycle): the gains stay
                    D = law.yaw.D_min
            else:
                self._above = 0
            if D != self._D:
                self._rescale(*law.yaw_gains(self._D), D)
        if self.held:                       # standstill: integrator frozen, ψ_ref ramps to 0
            dI = 0.0
            x_I = st.x_I
            k = self._hold_k = self._hold_k + 1
            psi_ref = self._psi_hold * (1.0 - k / self._hold_n) if k < self._hold_n else 0.0
        elif self._reseed:                  # resumed: ψ_ref goes on from the held value
            self._reseed = False
            target = st.psi_ref if self._psi_target is None else self._psi_target
            x_I = law.seed(g, e_y, target + self._w)
            dI = 0.0
            if self._psi_target is not None:    # the yaw gains moved (D̂): integrate on as usual
                dI = law.half_h * g * (e_y + self._e_y_prev)
                x_I += dI
            self._psi_target = None
            psi_ref = law.psi_ref(g, e_y, x_I) - self._w
        else:
            dI, x_I, psi_ref = law.outer(g, e_y, self._e_y_prev, st.x_I)
            psi_ref -= self._w
        lim = self.psi_ref_max
        if lim is not None and (psi_ref > lim or psi_ref < -lim):
            clipped = lim if psi_ref > 0 else -lim
            if (dI > 0) == (psi_ref > 0):   # clamp: integrate only out of the limit
                x_I -= dI
                dI = 0.0
            psi_ref = clipped
        e_psi, de, u_unsat = self._inner(law, psi_ref, psi)
        u = u_unsat
        if u > self.u_max:
            u = self.u_max
        elif u < -self.u_max:
            u = -self.u_max
        if u != u_unsat and (dI > 0) == (u_unsat > 0) and dI != 0.0:
            x_I -= dI   # conditional integration: do not integrate further into saturation
            dI = 0.0
        st.e_y, st.x_I, st.psi_ref, st.e_psi, st.de_psi, st.u_unsat, st.u = e_y, x_I, psi_ref, e_psi, de, u_unsat, u
        self._dI = dI
        self._e_y_prev = e_y
        self._e_psi_prev = e_psi
        if self._damp is not None:
            self._damp.hold(u)              # D̂ of the next step, from what this one commanded
        return u

    GAIN_NAMES = PIPD_GAINS
    law_name = "PI-PD"

    @property
    def D_hat(self) -> float:
        """The damping D̂ of (7) the last step's yaw gains were at (the law's signal ``D_hat``)."""
        return self._D if self._D is not None else math.nan

    def _inner(self, law, psi_ref, psi):
        """The inner loop's step on this cycle's ψ_ref at D̂: (e_ψ, ê_ψ, u before saturation)."""
        return law.inner(psi_ref, psi, self._e_psi_prev, self.st.de_psi, self._D)

    def _rescale(self, kp0: float, kappa0: float, D: float) -> None:
        """The yaw gains move from (kp0, κ0) to those at D̂ = D between two steps: the last step's
        ψ (κ0 ψ_ref − e_ψ) and its P term kp0 e_ψ are kept — the next step re-seeds x_I so that
        ψ_ref continues from there, as a resume does (no jump of the current from the schedule
        itself). In the hold ψ_ref ramps on; only the yaw error's memory is rescaled."""
        st = self.st
        kp1, kappa1 = self.law.yaw_gains(D)
        psi = kappa0 * st.psi_ref - st.e_psi
        e1 = kp0 * st.e_psi / kp1
        self._e_psi_prev = e1
        self._D = D
        if self._started and not self.held and self.law.K_I_y:
            self._psi_target = (psi + e1) / kappa1
            self._reseed = True

    def gains(self) -> dict[str, float]:
        """The gains in force, by their config names."""
        return {n: getattr(self.law, n) for n in self.GAIN_NAMES}

    def set_gain(self, name: str, value: float) -> None:
        """Change one gain between two steps (the loop calls it at a cycle boundary; the
        change was checked by :func:`rig_runtime.tuning.check`).

        Bumpless where the law allows it:

        * ``K_P_y``, ``K_I_y`` (outer PI): x_I is rescaled/shifted so that ψ_ref =
          K_P_y e_y + K_I_y x_I computed from the last step's e_y and x_I is the same with
          the new gains: ψ_ref does not jump; from the next step on it moves as the new
          gains make it.
        * ``T_f_psi``: the differentiator's state (its output de_ψ and the last e_ψ) is kept,
          only its coefficients change: the D term does not jump.
        * ``K_P_psi``, ``K_D_psi`` (inner PD) are *not* bumpless: u = K_Pψ e_ψ + K_Dψ de_ψ
          steps by ΔK_Pψ e_ψ + ΔK_Dψ de_ψ (small near equilibrium, where e_ψ ≈ 0); the filter
          state is kept, and the supervisor's rate limit (limits.du_max) bounds the step on
          the wire.

        Before the first step (not started) only the gain changes; ``start`` then chooses
        x_I with it. Raises ValueError for a name that is not a gain of this law or a value
        that is not a finite positive number (limits are not gains: they cannot be set here).
        """
        if name not in self.GAIN_NAMES:
            raise ValueError(f"{name!r} is not a gain of the {self.law_name} law ({', '.join(self.GAIN_NAMES)})")
        v = _positive(name, value)
        new = replace(self.law, **{name: v})
        st = self.st
        if self._started and name in PIPDLaw.SCHEDULED and self.law.K_I_y:
            psi_ref = self.law.psi_ref(self.g, st.e_y, st.x_I)    # unclipped, as the last step made it
            st.x_I = new.seed(self.g, st.e_y, psi_ref)
        self.law = new

    def _schedule(self, fraction: float) -> None:
        """Set D_sched between two steps (bumpless as a D̂ change is: :meth:`_rescale`)."""
        if fraction and self._yaw is None:
            raise ValueError("D_sched: this controller was built without the carrier's yaw parameters")
        old = self.law.yaw_gains(self._D)
        self.law = replace(self.law, D_sched=fraction, yaw=self._yaw if fraction else None)
        if fraction and self._damp is None:
            self._damp = InputDamping(self._yaw, self.h, self.st.u)
        elif not fraction:
            self._damp = None
        D = self._damp.now if self._damp is not None else None
        self._rescale(*old, D)

    def limit_feedback(self, u_applied: float) -> None:
        """The safety layer applied ``u_applied`` instead of the last output: undo this
        cycle's integration if it pushed toward the limit."""
        st = self.st
        if self._damp is not None:
            self._damp.correct(u_applied)
        if u_applied != st.u and self._dI != 0.0 and (self._dI > 0) == (st.u > u_applied):
            st.x_I -= self._dI
            self._dI = 0.0


class DecoupledController(PIPDController):
    """Steps :class:`DecoupledLaw`: the PI-PD controller with ψ_ref lowered by the law's feed
    term w (setpoint weighting, decoupling), which it computes each step from the reference and
    both carriers' y as the lanes' cross-lane stage gives them (``couple``). Saturation,
    anti-windup, the ψ_ref limit, bumpless start, hold and resume are the PI-PD's (they act on
    ψ_ref with w included: a resume or a start continues the ψ_ref the carrier has)."""

    GAIN_NAMES = DECOUPLED_GAINS
    law_name = "decoupled"

    def __init__(self, cfg: ControllerConfig, u_max: float, psi_ref_max: float | None = None,
                 gains: DecoupledGains | None = None, carrier: str | None = None, yaw: YawDamping | None = None):
        super().__init__(cfg, u_max, psi_ref_max, cfg.pipd, yaw)
        self.law = DecoupledLaw.of(gains if gains is not None else cfg.decoupled, cfg.h, carrier, yaw)
        self._damp = InputDamping(yaw, cfg.h) if self.law.scheduled_on_damping else None
        self.pair = None          # the cross-lane stage (lanes.LateralPair); None: the other carrier at 0
        self._fed = (0.0, 0.0, 0.0)   # y_ref, d, d̂' of the last feed term
        self.d_y = self.dd_y = 0.0    # the carriers' difference (last step) and its filtered derivative
        self.x_I_psi = 0.0        # the yaw loop's integrator
        self._dIp = 0.0           # its integration in the last step (undone into saturation)

    def _inner(self, law, psi_ref, psi):
        e_psi, de, self._dIp, self.x_I_psi, u = law.inner_i(psi_ref, psi, self._e_psi_prev, self.st.de_psi,
                                                            self.x_I_psi, self._D)
        return e_psi, de, u

    def reset(self) -> None:
        super().reset()
        self.x_I_psi = self._dIp = 0.0

    def couple(self, pair) -> None:
        """Read the carriers' y through ``pair`` (``pair.y(carrier)``) from the next step on."""
        self.pair = pair

    def _feed(self, y_ref: float, seed: bool = False) -> None:
        p = self.pair
        yf, yr = (p.y("front"), p.y("rear")) if p is not None else (0.0, 0.0)
        if seed:                            # start: no derivative kick
            self.d_y, self.dd_y = yf - yr, 0.0
        self.d_y, self.dd_y = self.law.cross(yf, yr, self.d_y, self.dd_y)
        self._fed = (y_ref, self.d_y, self.dd_y)
        self._w = self.law.feed(self.g, *self._fed)

    def start(self, y_ref: float, y: float, psi: float, u0: float = 0.0) -> None:
        """As the PI-PD's (ψ_ref = ψ + u0/K_P,ψ: no jump), the yaw integrator at 0."""
        self._feed(y_ref, seed=True)
        self.x_I_psi = self._dIp = 0.0
        super().start(y_ref, y, psi, u0)

    def step(self, y_ref: float, y: float, psi: float) -> float:
        self._feed(y_ref)
        u = super().step(y_ref, y, psi)
        st = self.st
        if u != st.u_unsat and self._dIp != 0.0 and (self._dIp > 0) == (st.u_unsat > 0):
            self.x_I_psi -= self._dIp      # conditional integration, as the outer integrator
            self._dIp = 0.0
        return u

    def limit_feedback(self, u_applied: float) -> None:
        st = self.st
        if u_applied != st.u and self._dIp != 0.0 and (self._dIp > 0) == (st.u > u_applied):
            self.x_I_psi -= self._dIp
            self._dIp = 0.0
        super().limit_feedback(u_applied)

    # read-only accessors of the law's signals (DecoupledLaw.SIGNALS) that are not in the record ``st``
    @property
    def w(self) -> float:
        """The feed term ψ_ref was lowered by in the last step (rad; in the hold ψ_ref ramps without it)."""
        return self._w

    @property
    def w_cross(self) -> float:
        """The feed term's cross-carrier part of the last step (rad): K_x,y (d + T_x,y d̂'), and
        − K_t,y |g| d on the trailing carrier; the law's feed at y_ref = 0 (its setpoint part
        vanishes), on the last step's d, d̂'."""
        return self.law.feed(self.g, 0.0, self.d_y, self.dd_y)

    def set_gain(self, name: str, value: float) -> None:
        """As :meth:`PIPDController.set_gain`; a change of K_P_y, K_I_y, b_y, K_x_y, T_x_y or K_t_y keeps ψ_ref
        (with the last step's feed term) continuous by re-seeding x_I."""
        if name not in self.GAIN_NAMES:
            raise ValueError(f"{name!r} is not a gain of the decoupled law ({', '.join(self.GAIN_NAMES)})")
        v = _positive(name, value) if name != "b_y" else _unit(name, value)
        if name == "D_sched":
            self._schedule(v)
            return
        old, new = self.law, replace(self.law, **{name: v})
        st = self.st
        if name == "K_I_psi" and self._started and v:    # the integral term's share of u stays
            self.x_I_psi = old.K_I_psi * self.x_I_psi / v
        if self._started and name in ("K_P_y", "K_I_y", "b_y", "K_x_y", "T_x_y", "K_t_y") and old.K_I_y:
            psi_ref = old.psi_ref(self.g, st.e_y, st.x_I) - old.feed(self.g, *self._fed)
            self._w = new.feed(self.g, *self._fed)
            st.x_I = new.seed(self.g, st.e_y, psi_ref + self._w)
        self.law = new


class PController:
    """Steps :class:`PLaw`: u = K_P (y_ref − y), saturated. Scheduled, K_P·g; held, u = 0
    (the law has no yaw loop to keep ψ at 0 with)."""

    def __init__(self, cfg: ControllerConfig, u_max: float):
        self.law = PLaw(cfg.K_P, cfg.h)
        self.u_max = u_max
        self.st = PIPDInternals()
        self.g = 1.0
        self.held = False

    kp = property(lambda self: self.law.K_P)

    def reset(self) -> None:
        self.st = PIPDInternals()

    def start(self, y_ref: float, y: float, psi: float, u0: float = 0.0) -> None:
        self.reset()
        self.held = False

    def set_gain_factor(self, g: float) -> None:
        self.g = g

    def hold(self, ramp_s: float) -> None:
        self.held = True

    def resume(self) -> None:
        self.held = False

    def step(self, y_ref: float, y: float, psi: float) -> float:
        e = y_ref - y
        u = 0.0 if self.held else self.law.u(self.g, e)
        u_sat = min(self.u_max, max(-self.u_max, u))
        st = self.st
        st.e_y, st.u_unsat, st.u = e, u, u_sat
        return u_sat

    def gains(self) -> dict[str, float]:
        return {"K_P": self.law.K_P}

    def set_gain(self, name: str, value: float) -> None:
        """Change K_P between two steps. Not bumpless: the law has no state to absorb the
        change, u steps by ΔK_P (y_ref − y); the supervisor's rate limit bounds the step on
        the wire. ValueError for another name or a value that is not finite and positive."""
        if name != "K_P":
            raise ValueError(f"{name!r} is not a gain of the P law (K_P)")
        self.law = replace(self.law, K_P=_positive(name, value))

    def limit_feedback(self, u_applied: float) -> None:
        pass


def _positive(name: str, value: float) -> float:
    """A gain's new value as a float; ValueError unless finite and positive."""
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name}: {value!r} is not a finite positive number")
    return v


def _unit(name: str, value: float) -> float:
    """A weight's new value as a float; ValueError unless finite and in [0, 1]."""
    v = float(value)
    if not (math.isfinite(v) and 0.0 <= v <= 1.0):
        raise ValueError(f"{name}: {value!r} is not a number in [0, 1]")
    return v


def make_controller(cfg: ControllerConfig, u_max: float, psi_ref_max: float | None = None,
                    carrier: str | None = None, yaw: YawDamping | None = None):
    """The configured control law (with ``carrier``: that carrier's gains, ``cfg.gains``; ``yaw``:
    its yaw parameters, which the damping schedule needs)."""
    if cfg.law == "p":
        return PController(cfg, u_max)
    if cfg.law == "decoupled":
        return DecoupledController(cfg, u_max, psi_ref_max, carrier=carrier, yaw=yaw)
    return PIPDController(cfg, u_max, psi_ref_max, cfg.gains(carrier) if carrier is not None else None, yaw)


# --------------------------------------------------------------------------- open loop
class StepSequence:
    """Piecewise-constant input: ``[(t0, u0), (t1, u1), …]`` (Fig. 3 style); 0 before the
    first step (several steps at one time: the last one given with the largest u, as sorted).

    Each call moves an index from the step in force at the previous call's t: O(1) amortised
    while t does not decrease from call to call — the loop's run time (a restart after an
    operator's fault reset goes back once) — and still right for any t (it walks back)."""

    __slots__ = ("times", "values", "_i")

    def __init__(self, steps: Sequence[tuple[float, float]]):
        pts = sorted((float(t), float(u)) for t, u in steps)
        self.times = [t for t, _ in pts]
        self.values = [u for _, u in pts]
        self._i = -1            # the step in force at the previous call (-1: none yet)

    def __call__(self, t: float) -> float:
        times, i = self.times, self._i
        last = len(times) - 1
        while i < last and times[i + 1] <= t:
            i += 1
        while i >= 0 and times[i] > t:
            i -= 1
        self._i = i
        return self.values[i] if i >= 0 else 0.0


class Sinusoid:
    """``amplitude · sin(2π f t) + bias`` with f in mHz, as in Sec. 4.3.4 (4.8 / 2.4 mHz)."""

    def __init__(self, amplitude: float, freq_mhz: float, bias: float = 0.0, t0: float = 0.0):
        self.amplitude, self.w, self.bias, self.t0 = amplitude, 2 * math.pi * freq_mhz * 1e-3, bias, t0

    def __call__(self, t: float) -> float:
        if t < self.t0:
            return self.bias
        return self.bias + self.amplitude * math.sin(self.w * (t - self.t0))


class ZeroInput:
    """Δu = 0: free response."""

    def __call__(self, t: float) -> float:
        return 0.0
