"""Plant model of the 1:5 IRDW roller rig and its integrator (paper Sec. 4, eqs. (2)-(9)).

Both wheel carriers c in {f, r}. Per carrier the yaw part has the states

    psi   yaw angle between carrier and frame (the paper's psi_af / psi_ar), rad
    p     yaw rate psi_dot, rad/s
    z     Bouc-Wen state z_hyst of (9), rad   (frozen at 0 for the linear model)
    ue    residual du - uf of the low-pass filtered input uf used by the damping law (7), A
          (stored as the residual: it decays to exactly 0 instead of losing digits in du - uf)

and there are the lateral displacements y_f, y_r (m) and, with ``wheel_dynamics="dynamic"``,
the differential wheel speeds dw_f, dw_r (rad/s) of (3).  Equations, disturbance model,
integrator and its measured error: docs/plant-model.md.

Yaw, per carrier (Delta u held over the step, M_z the disturbance yaw moment):

    psi'' = -2 D omega0 psi' - omega0^2 (a psi + (1-a) z) + K omega0^2 du + omega0^2 psi_off + M_z/J_z
    z'    = A psi' - beta |psi'| |z|^(n-1) z - gamma psi' |z|^n                (a = a_Bouc)
    uf'   = (du - uf)/tau,  tau = 1/(2 pi u_filter_hz);   udot = uf' = (du - uf)/tau = ue/tau
          (with du held: ue' = -ue/tau; ue jumps by the change of du at a step boundary)
    D     = D_min if |udot| >= c_udot_max else D_max - |udot|/c_udot_max (D_max - D_min)

Lateral (2a)/(2b) with the offset of Sec. 4.1.2 and a lateral force as creep velocity, each
carrier c with its own values (``params.carrier(c)``) and a_c = cy_c v/(2 l0_c):

    y_f' = +a_f y_f - a_f y_r + cy_f v psi_af + v/(2 l0_f) y_off_f + |v| F_y_f/(2 c22_f)
    y_r' = -a_r y_r + a_r y_f + cy_r v psi_ar + v/(2 l0_r) y_off_r + |v| F_y_r/(2 c22_r)

(eigenvalues 0 and a_f - a_r; a Jordan block at 0 for equal carriers). The speed v is held
over a step and changed between steps by ``set_speed`` (through 0 and negative).

With ``front_contact`` false the front carrier is lifted: y_f == 0, its yaw still follows its own
yaw dynamics, its wheels have no rolling contact (dw_f = 0); ``rear_contact`` false is the same
for the rear (the mirrored set-up of the front's identification, v < 0).

``rear_lifted`` (a ``LiftedCarrier``) lifts the rear carrier off the rollers, the set-up of the
free-response experiment (Sec. 4.3.2): its yaw follows (6) with the contact-free damping and
offset of ``LiftedCarrier`` and no hysteresis, y_r stays where it is, dw_r = 0;
``front_lifted`` is its mirror for the front. docs/vehicle.md has the vehicle's part.

The integrator (``Plant.step``) is pure-Python scalar code: an exact solution of the yaw
oscillator linearised about the (sub)step start (D frozen at its exact average over the
(sub)step, Bouc-Wen stiffness as the secant slope of the exact z(psi) map, iterated), the
exact Bouc-Wen map z(psi) for n = 1, the exact filter update, and exponential (exact for a
cubic Hermite forcing) updates of the lateral and wheel-speed ODEs.  ``Plant.rhs`` is the same
model as a vectorised numpy right-hand side for the stiff reference solver.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from math import ceil, cos, exp, expm1, log, sin, sqrt
from typing import Any, Callable, Optional, Sequence

import numpy as np

from rig_runtime.config import Plant as PlantParams
from rig_runtime.damping import damping
from rig_runtime.hysteresis import zmap

__all__ = ["PlantState", "Plant", "LiftedCarrier", "WHEEL_LOAD_N", "STATE_NAMES"]

#: ESTIMATE: static vertical load per wheel, N. A full-scale low-floor IRW wheel carries about
#: 60 kN; scaled 1:5 with mass ~ 1/5^3 that is 480 N. Only in the F/T loads (``ft_loads``):
#: more than an FT 300 measures (±300 N rated, ±327.67 N in its registers), which is why the
#: sensors are zeroed at rest (``ft_readings``).
WHEEL_LOAD_N = 480.0

#: Layout of the state vector used by ``Plant.rhs`` / ``Plant.state_vector`` (the last two only
#: with ``wheel_dynamics="dynamic"``).
STATE_NAMES = ("y_f", "y_r", "psi_af", "psi_rate_f", "z_f", "ue_f",
               "psi_ar", "psi_rate_r", "z_r", "ue_r", "dw_f", "dw_r")
_I_YF, _I_YR = 0, 1
_I_F, _I_R = 2, 6          # offsets of (psi, p, z, ue) of the front / rear carrier
_I_DW = 10

# Integrator tolerances (adaptive mode). Measured effect: docs/plant-model.md.
_TOL_D = 0.03        # max relative change of D within one sub-step (log ratio)
_TOL_NL = 0.005      # max relative change of the Bouc-Wen stiffness within one sub-step
_TOL_K = 1e-13       # secant iteration: accepted yaw-angle change caused by the slope update, rad
_MAX_SUB = 4096      # hard cap on sub-steps per call


@dataclass(frozen=True)
class LiftedCarrier:
    """Yaw parameters of a carrier lifted off the rollers (Sec. 4.3.2, Table 3 first row):
    no wheel-roller contact, so a constant damping ``D`` and no hysteresis; ``omega0`` and
    ``K`` are those of the plant. ``psi_off`` is the lifted carrier's own offset (rad)."""

    D: float = 0.28
    psi_off: float = 1.7e-3


@dataclass(frozen=True, slots=True)
class PlantState:
    """A snapshot of the plant (SI units). ``ue_*`` = du - uf, the residual of the input filter
    of the damping law (udot = ue/tau); ``du_*`` the inputs held since the last step."""

    t: float = 0.0
    y_f: float = 0.0
    y_r: float = 0.0
    psi_af: float = 0.0
    psi_ar: float = 0.0
    psi_rate_f: float = 0.0
    psi_rate_r: float = 0.0
    z_f: float = 0.0
    z_r: float = 0.0
    ue_f: float = 0.0
    ue_r: float = 0.0
    dw_f: float = 0.0
    dw_r: float = 0.0
    du_f: float = 0.0      # inputs held since the last step
    du_r: float = 0.0
    v: Optional[float] = None   # roller speed, m/s (None: not recorded)


# --------------------------------------------------------------------------- helpers
def _osc_coef(c: float, w: float, h: float) -> tuple[float, float, float]:
    """Exact step of x'' + c x' + w x = f (f constant) from x(0) = 0, x'(0) = p0.

    Returns (e12, e22, g1) with x(h) = e12 p0 + g1 f and x'(h) = e22 p0 + e12 f.
    Robust for over-, under- and critically damped cases and for w -> 0 (c > 0).
    """
    hc = 0.5 * c
    q2 = hc * hc - w
    if q2 * h * h > 1e-6:                       # overdamped: two real poles
        q = sqrt(q2)
        l2 = -(hc + q)                          # fast pole
        l1 = w / l2                             # slow pole (l1 l2 = w), no cancellation
        m1 = expm1(l1 * h)
        m2 = expm1(l2 * h)
        inv = 0.5 / q                           # 1/(l1 - l2)
        e12 = (m1 - m2) * inv
        e22 = (l1 * m1 - l2 * m2 + (l1 - l2)) * inv
        phi1 = m1 / l1 if l1 != 0.0 else h
        g1 = (phi1 - m2 / l2) * inv
        return e12, e22, g1
    ea = exp(-hc * h)
    if q2 * h * h < -1e-6:                      # underdamped
        mu = sqrt(-q2)
        cs = cos(mu * h)
        sn = sin(mu * h) / mu
    else:                                       # (nearly) critically damped: series
        u = q2 * h * h
        cs = 1.0 + u * (0.5 + u / 24.0)
        sn = h * (1.0 + u * (1.0 / 6.0 + u / 120.0))
    e12 = ea * sn
    e22 = ea * (cs - hc * sn)
    if w * h * h > 1e-4:
        g1 = (1.0 - ea * (cs + hc * sn)) / w
    else:
        g1 = h * h * (0.5 - c * h / 6.0 + (c * c - w) * h * h / 24.0)
    return e12, e22, g1


def _hermite_weights(lam: float, h: float) -> tuple[float, float, float, float, float]:
    """Exact step of y' = -lam y + g(t) over [0, h] with g the cubic Hermite interpolant of
    (g0, g0', g1, g1'):  y(h) = phi y0 + w0 g0 + w1 g0' + w2 g1 + w3 g1'.

    Uses J_j = int_0^1 exp(-x (1-s)) s^j ds, x = lam h (``_exp_ints``).  Pure math, cheap
    enough to redo whenever dt or the speed changes (cost: docs/vehicle.md).
    """
    x = lam * h
    (J0, J1, J2, J3), _ = _exp_ints(x)
    return (exp(-x), h * (J0 - 3.0 * J2 + 2.0 * J3), h * h * (J1 - 2.0 * J2 + J3),
            h * (3.0 * J2 - 2.0 * J3), h * h * (J3 - J2))


def _exp_ints(x: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """J_j = int_0^1 exp(-x (1-s)) s^j ds and K_j = (J_j - 1/(j+1))/(-x) for j = 0..3
    (K_j at x = 0 is 1/((j+1)(j+2))); K is what is left of J once its x = 0 value is taken out,
    computed without cancellation: for |x| < 0.5 the series of K_3 and the stable backward
    recursion K_{j-1} = (1/(j+1) - x K_j)/j, else J by its forward recursion."""
    if abs(x) < 0.5:
        acc, term, m = 0.0, 1.0 / 20.0, 1               # K_3 = sum_{m>=1} (-x)^(m-1) 3!/(m+4)!
        while True:
            acc += term
            m += 1
            term *= -x / (m + 4)
            if abs(term) <= 1e-17 * abs(acc) or m > 40:
                break
        K3 = acc
        K2 = (0.25 - x * K3) / 3.0
        K1 = (1.0 / 3.0 - x * K2) / 2.0
        K0 = 0.5 - x * K1
        return (1.0 - x * K0, 0.5 - x * K1, 1.0 / 3.0 - x * K2, 0.25 - x * K3), (K0, K1, K2, K3)
    J0 = -expm1(-x) / x
    J1 = (1.0 - J0) / x
    J2 = (1.0 - 2.0 * J1) / x
    J3 = (1.0 - 3.0 * J2) / x
    return (J0, J1, J2, J3), ((1.0 - J0) / x, (0.5 - J1) / x, (1.0 / 3.0 - J2) / x, (0.25 - J3) / x)


def _hermite_weights_coupled(a_f: float, h: float, a_r: Optional[float] = None) -> tuple:
    """Exact step of (2a)/(2b) with both carriers in contact, Y = (y_f, y_r), Y' = M Y + G(t),
    M = [[a_f, -a_f], [a_r, -a_r]], G cubic Hermite over [0, h] (``a_r`` None: equal carriers).

    M has the eigenvalues 0 and mu = a_f - a_r and M^2 = mu M, so e^{Mt} = I + (e^{mu t} - 1)/mu M:
    for equal carriers (mu = 0) a Jordan block at 0, e^{Mt} = I + M t. With the Hermite basis
    functions H_k: W_k = int_0^h e^{M(h-s)} H_k(s) ds = c_k I + d_k M, c_k = int H_k and
    d_k = int (e^{mu (h-s)} - 1)/mu H_k(s) ds (for mu = 0: int (h - s) H_k(s) ds).

    Returns (Phi, (W0, W1, W2, W3)) as nested lists: Y(h) = Phi Y0 + W0 G0 + W1 G0' + W2 G1 + W3 G1'.
    int_0^h G = h/2 (G0 + G1) + h^2/12 (G0' - G1');
    int_0^h (h - t) G = h^2 (7/20 G0 + 3/20 G1) + h^3 (1/20 G0' - 1/30 G1').
    """
    if a_r is None:
        a_r = a_f
    mu = a_f - a_r
    h2 = h * h
    c = (h / 2, h2 / 12, h / 2, -h2 / 12)                                  # int H_k, for G0, G0', G1, G1'
    if mu == 0.0:
        s = h
        d = (0.35 * h2, h ** 3 / 20, 0.15 * h2, -h ** 3 / 30)
    else:
        (J0, _, _, _), (K0, K1, K2, K3) = _exp_ints(-mu * h)
        s = h * J0                                                         # (e^{mu h} - 1)/mu
        h3 = h2 * h
        d = (h2 * (K0 - 3.0 * K2 + 2.0 * K3), h3 * (K1 - 2.0 * K2 + K3),
             h2 * (3.0 * K2 - 2.0 * K3), h3 * (K3 - K2))
    phi = [[1.0 + s * a_f, -(s * a_f)], [s * a_r, 1.0 - s * a_r]]          # I + s M
    W = [[[ck + dk * a_f, -(dk * a_f)], [dk * a_r, ck - dk * a_r]] for ck, dk in zip(c, d)]   # c_k I + d_k M
    return phi, W


def _select(cond: bool, a: float, b: float) -> float:
    return a if cond else b


class _Carrier:
    """Yaw dynamics (6)-(9) of one wheel carrier: constants and state, advanced in place."""

    __slots__ = ("w0", "w02", "K", "psi_off", "inv_Jw2", "a", "oma", "A", "beta", "gamma", "n",
                 "hyst", "tau", "cmax", "Dmin", "Dmax", "dD", "fixed_sub",
                 "psi", "p", "z", "e", "du", "M", "vl",
                 "_ck", "_cv", "nsub_last")

    def __init__(self, P: PlantParams, fixed_sub: Optional[int]):
        self.w0 = P.omega0
        self.w02 = P.omega0 ** 2
        self.K = P.K
        self.psi_off = P.psi_off
        J_z = P.b * P.k_tau / (P.r0 * P.K * P.omega0 ** 2)
        self.inv_Jw2 = 1.0 / (J_z * self.w02)
        bw = P.bouc_wen
        self.hyst = bw is not None and bw.a < 1.0
        if bw is None:
            self.a, self.A, self.beta, self.gamma, self.n = 1.0, 1.0, 0.0, 0.0, 1
        else:
            self.a, self.A, self.beta, self.gamma, self.n = bw.a, bw.A, bw.beta, bw.gamma, bw.n
        self.oma = 1.0 - self.a
        self.tau = 1.0 / (2.0 * math.pi * P.u_filter_hz)
        self.cmax = P.c_udot_max
        self.Dmin, self.Dmax = P.D_min, P.D_max
        self.dD = P.D_max - P.D_min
        self.fixed_sub = fixed_sub
        self.psi = self.p = self.z = self.e = self.du = self.M = self.vl = 0.0
        self._ck = None
        self._cv = (0.0, 0.0, 0.0)
        self.nsub_last = 0

    # -- model pieces ------------------------------------------------------------
    def damping(self) -> float:
        """D of (7) for the current filter state and held input."""
        rho = abs(self.e) / (self.tau * self.cmax)
        return damping(rho, self.Dmin, self.Dmax)

    def accel(self, D: float) -> float:
        """psi'' at the current state with damping D (held input and moment)."""
        w02 = self.w02
        ueq = self.K * self.du + self.psi_off + self.M * self.inv_Jw2
        R = self.psi - self.oma * (self.psi - self.z)
        return -2.0 * D * self.w0 * self.p + w02 * (ueq - R)

    def zmap(self, z: float, dpsi: float) -> float:
        """Exact Bouc-Wen state after a monotone change dpsi of psi (z'(psi) = A - kappa z, n = 1)."""
        if dpsi == 0.0:
            return z
        if self.n != 1:
            return self._zmap_general(z, dpsi)
        return zmap(z, dpsi, self.A, self.beta, self.gamma)

    def _zmap_general(self, z: float, dpsi: float) -> float:
        """Bouc-Wen for n != 1: RK4 in psi with sub-steps small against the local stiffness."""
        A, beta, gamma, n = self.A, self.beta, self.gamma, self.n
        s = 1.0 if dpsi > 0.0 else -1.0

        def g(zz: float) -> float:
            az = abs(zz)
            return A - beta * s * az ** (n - 1) * zz - gamma * az ** n

        zs = max(abs(z), (abs(A) / (beta + abs(gamma))) ** (1.0 / n))
        stiff = (beta + abs(gamma)) * n * zs ** (n - 1)
        m = max(1, min(100000, ceil(abs(dpsi) * stiff / 0.05)))
        hs = dpsi / m
        for _ in range(m):
            k1 = g(z)
            k2 = g(z + 0.5 * hs * k1)
            k3 = g(z + 0.5 * hs * k2)
            k4 = g(z + hs * k3)
            z += hs * (k1 + 2 * k2 + 2 * k3 + k4) / 6.0
        return z

    def slope(self, z: float, s: float) -> float:
        """dz/dpsi of (9) at z when psi moves in direction s (+1 / -1)."""
        if z == 0.0:
            return self.A
        az = abs(z)
        if self.n == 1:
            return self.A - self.beta * s * z - self.gamma * az
        return self.A - self.beta * s * az ** (self.n - 1) * z - self.gamma * az ** self.n

    def _mean_D(self, rho: float, ta: float, tb: float) -> float:
        """Exact time average of D(t) over [ta, tb]; |udot(t)|/c_max = rho exp(-t/tau)."""
        tau = self.tau
        t1 = tau * log(rho) if rho > 1.0 else 0.0   # D leaves D_min at t1
        if t1 >= tb:
            return self.Dmin
        acc = 0.0
        ts = ta
        if t1 > ta:
            acc = self.Dmin * (t1 - ta)
            ts = t1
        acc += self.Dmax * (tb - ts) - self.dD * rho * tau * (exp(-ts / tau) - exp(-tb / tau))
        return acc / (tb - ta)

    # -- integration -------------------------------------------------------------
    def _coef(self, c: float, w: float, h: float) -> tuple[float, float, float]:
        key = (c, w, h)
        if key == self._ck:
            return self._cv
        v = _osc_coef(c, w, h)
        self._ck = key
        self._cv = v
        return v

    def _sub(self, h: float, c: float, ueq: float) -> float:
        """Advance (psi, p, z) over h with constant damping coefficient c = 2 D omega0.

        Returns the relative change of the Bouc-Wen stiffness seen over the sub-step
        (0 for the linear model), which the caller uses to refine the sub-steps.
        """
        psi, p, z = self.psi, self.p, self.z
        oma = self.oma
        f = self.w02 * (ueq - (psi - oma * (psi - z)))
        if not self.hyst:
            e12, e22, g1 = self._coef(c, self.w02, h)
            self.psi = psi + e12 * p + g1 * f
            self.p = e22 * p + e12 * f
            return 0.0
        a = self.a
        w02 = self.w02
        ap = a / oma                               # a/(1-a): stiffness floor in units of k
        s = 1.0 if (p > 0.0 or (p == 0.0 and f >= 0.0)) else -1.0
        n1 = self.n == 1
        if n1:                                     # dz/dpsi = A - kappa z (inlined slope())
            sig = 1.0 if z > 0.0 else (-1.0 if z < 0.0 else s)
            kap = self.beta * s + self.gamma * sig
            k0 = self.A - kap * z
        else:
            k0 = self.slope(z, s)
        k = k0
        # predict the secant slope over the expected motion (last velocity) -> usually one solve
        xe = self.vl * h
        if n1 and xe * s > 0.0:
            kx = kap * xe
            if kx != 0.0:
                k = -k0 * expm1(-kx) / kx
        nl = -1.0
        x = z1 = 0.0
        for it in range(10):
            e12, e22, g1 = _osc_coef(c, w02 * (a + oma * k), h)
            x = e12 * p + g1 * f
            if x == 0.0:
                z1 = z
                break
            if x * s < 0.0 and it == 0:            # moves the other way: restart with that slope
                s = -s
                k = k0 = self.slope(z, s)
                continue
            z1 = self.zmap(z, x)
            ks = (z1 - z) / x
            kmin = k0 if k0 < ks else ks
            if kmin < 0.0:
                kmin = 0.0
            if nl < 0.0:                           # tangent vs secant: Bouc-Wen curvature over h
                nl = abs(ks - k0) / (ap + kmin)
            kmin = k if k < ks else ks
            if kmin < 0.0:
                kmin = 0.0
            if abs(ks - k) * oma * abs(x) <= _TOL_K * (a + oma * kmin):
                break
            k = ks
        self.psi = psi + x
        self.p = e22 * p + e12 * f
        self.z = z1
        self.vl = x / h
        return nl if nl > 0.0 else 0.0

    def advance(self, h: float, ef: float, du: float, M: float) -> None:
        """Advance the carrier's yaw states over h with input du and moment M held."""
        r = self.e + (du - self.du)               # filter residual just after the input change
        self.du = du
        self.M = M
        self.e = r * ef
        ueq = self.K * du + self.psi_off + M * self.inv_Jw2
        rho = abs(r) / (self.tau * self.cmax)
        w0 = self.w0
        if rho * ef >= 1.0:                        # |udot| >= c_max through the whole step
            vary = False
            D = self.Dmin
        elif rho * self.dD <= 1e-12 * self.Dmax:   # D == D_max to 12 digits
            vary = False
            D = self.Dmax
        else:
            vary = True
            D = 0.0
        n = self.fixed_sub
        if n is None:
            n = 1
            if vary:
                d0 = damping(rho, self.Dmin, self.Dmax)
                d1 = damping(rho * ef, self.Dmin, self.Dmax)
                n = max(1, min(_MAX_SUB, ceil(log(d1 / d0) / _TOL_D)))
        if not self.hyst and not vary and n == 1:  # fast path: linear, constant damping
            self._sub(h, 2.0 * D * w0, ueq)
            self.nsub_last = 1
            return
        adaptive = self.fixed_sub is None and self.hyst
        hs = h / n
        count = 0
        for j in range(n):
            t = j * hs
            if adaptive:
                count += self._piece(t, hs, rho, vary, D, ueq)
            else:
                self._sub(hs, self._c(rho, vary, D, t, t + hs), ueq)
                count += 1
        self.nsub_last = count

    def _c(self, rho: float, vary: bool, D: float, ta: float, tb: float) -> float:
        """Damping coefficient 2 D omega0 with D averaged exactly over [ta, tb]."""
        return 2.0 * self.w0 * (self._mean_D(rho, ta, tb) if vary else D)

    def _piece(self, t: float, hh: float, rho: float, vary: bool, D: float, ueq: float) -> int:
        """Advance over [t, t + hh] with the hysteresis: split at a reversal of psi' (the map
        z(psi) is exact for monotone psi) and refine where the Bouc-Wen stiffness changes much."""
        saved = (self.psi, self.p, self.z, self.vl)
        c = 2.0 * self.w0 * (self._mean_D(rho, t, t + hh) if vary else D)
        nl = self._sub(hh, c, ueq)
        p0 = saved[1]
        if p0 * self.p < 0.0:
            ts = self._reversal_time(saved, c, ueq, hh)
            self.psi, self.p, self.z, self.vl = saved
            return (self._refined(t, ts, rho, vary, D, ueq, None)
                    + self._refined(t + ts, hh - ts, rho, vary, D, ueq, None))
        if nl > _TOL_NL:
            self.psi, self.p, self.z, self.vl = saved
            return self._refined(t, hh, rho, vary, D, ueq, nl)
        return 1

    def _refined(self, t: float, hh: float, rho: float, vary: bool, D: float, ueq: float,
                 nl: Optional[float]) -> int:
        """Advance over [t, t + hh] in m equal sub-steps, m from the Bouc-Wen curvature
        ``nl`` of one trial sub-step (computed here when not given)."""
        if nl is None:
            saved = (self.psi, self.p, self.z, self.vl)
            nl = self._sub(hh, self._c(rho, vary, D, t, t + hh), ueq)
            if nl <= _TOL_NL:
                return 1
            self.psi, self.p, self.z, self.vl = saved
        m = min(_MAX_SUB, ceil(nl / _TOL_NL))
        hm = hh / m
        for i in range(m):
            self._sub(hm, self._c(rho, vary, D, t + i * hm, t + (i + 1) * hm), ueq)
        return m

    def _reversal_time(self, saved: tuple, c: float, ueq: float, hh: float) -> float:
        """Time in (0, hh) at which psi' of the linearised solution from ``saved`` crosses 0
        (Illinois regula falsi on the exact solution; stiffness of the initial direction)."""
        psi, p0, z = saved[0], saved[1], saved[2]
        k0 = self.slope(z, 1.0 if p0 > 0.0 else -1.0)
        w = self.w02 * (self.a + self.oma * k0)
        f = self.w02 * (ueq - (psi - self.oma * (psi - z)))
        ta, pa = 0.0, p0
        e12, e22, _ = _osc_coef(c, w, hh)
        tb, pb = hh, e22 * p0 + e12 * f
        if pa * pb >= 0.0:                          # not bracketed by the linearisation
            return hh * p0 / (p0 - self.p)
        for _ in range(40):
            tm = (ta * pb - tb * pa) / (pb - pa)
            if not (min(ta, tb) < tm < max(ta, tb)):
                tm = 0.5 * (ta + tb)
            e12, e22, _ = _osc_coef(c, w, tm)
            pm = e22 * p0 + e12 * f
            if pm * pb < 0.0:
                ta, pa = tb, pb
            else:
                pa *= 0.5                           # Illinois modification
            tb, pb = tm, pm
            if abs(tb - ta) <= 1e-9 * hh or pm == 0.0:
                break
        return min(max(tb, 1e-12 * hh), hh * (1.0 - 1e-12))


# --------------------------------------------------------------------------- the plant
_LAT_NONE, _LAT_REAR, _LAT_FRONT, _LAT_BOTH = 0, 1, 2, 3     # which carriers roll (lateral update)


class Plant:
    """Both wheel carriers of the rig: lateral (2), wheel speeds (4) or (3), yaw (6)-(9).

    Each carrier has its own parameters, ``params.carrier("front"|"rear")`` (the common values
    with that carrier's overrides). ``step(dt, du_f, du_r, ...)`` advances by dt with inputs,
    disturbances and the roller speed held (ZOH); ``set_speed(v)`` changes the speed between
    steps. ``wheel_dynamics``: "static" uses the algebraic relation (4); "dynamic" integrates
    (3) exactly (its pole -c11 r0^2/(J_x v) is about -5.6e4 1/s; only for a fixed v > 0).
    ``substeps``: None = adaptive (default; meets the documented accuracy), an int = that many
    equal yaw sub-steps per call with no adaptation (faster, less accurate when D varies or the
    hysteresis flips). ``rear_lifted`` / ``front_lifted`` (a ``LiftedCarrier``) lift that
    carrier off the rollers for its free response (Sec. 4.3.2); the other carrier must be out
    of contact then (``front_contact`` / ``rear_contact`` false).
    """

    def __init__(self, params: PlantParams, wheel_dynamics: str = "static",
                 substeps: Optional[int] = None, rear_lifted: Optional[LiftedCarrier] = None,
                 front_lifted: Optional[LiftedCarrier] = None):
        if wheel_dynamics not in ("static", "dynamic"):
            raise ValueError(f"wheel_dynamics: expected 'static' or 'dynamic', got {wheel_dynamics!r}")
        if substeps is not None and (not isinstance(substeps, int) or substeps < 1):
            raise ValueError(f"substeps: expected None or an int >= 1, got {substeps!r}")
        if wheel_dynamics == "dynamic" and not params.v > 0:
            raise ValueError("wheel_dynamics='dynamic' needs v > 0: the creep pole "
                             "-c11 r0^2/(J_x v) of (3) is unstable/undefined otherwise")
        if rear_lifted is not None and params.front_contact and front_lifted is None:
            raise ValueError("rear_lifted needs the front carrier lifted too (front_contact: false): "
                             "the identification set-up of Sec. 4.1.1 has no carrier on the rollers then")
        if front_lifted is not None and params.rear_contact and rear_lifted is None:
            raise ValueError("front_lifted needs the rear carrier out of contact too (rear_contact: false): "
                             "the mirrored identification set-up has no carrier on the rollers then")
        P = params
        self.params = P
        self.wheel_dynamics = wheel_dynamics
        self.dynamic = wheel_dynamics == "dynamic"
        self.substeps = substeps
        self.n_states = 12 if self.dynamic else 10
        self.rear_lifted = rear_lifted
        self.front_lifted = front_lifted
        self.front_contact = P.front_contact and front_lifted is None     # rolling contact
        self.rear_contact = P.rear_contact and rear_lifted is None
        self._lat_mode = ((_LAT_FRONT if self.front_contact else _LAT_NONE)
                          + (_LAT_REAR if self.rear_contact else _LAT_NONE))
        Pf, Pr = P.carrier("front"), P.carrier("rear")
        self.carrier_params = {"front": Pf, "rear": Pr}
        # speed-independent constants per carrier (_f, _r)
        self._cy_f, self._cy_r = Pf.c_y, Pr.c_y
        self._l0_f, self._l0_r = Pf.l0, Pr.l0
        self._c22_f, self._c22_r = Pf.c11, Pr.c11                # ESTIMATE: c22 ~ c11
        self._b2r_f, self._b2r_r = Pf.b / (2.0 * Pf.r0), Pr.b / (2.0 * Pr.r0)
        # per unit speed: (c̄_y/(2 l0), 1/(2 l0) y_off, 1/(2 c22), Γ b/(2 r0²), k_τ/(r0² c̄11), 1/r0)
        self._per_v = tuple((Pc.c_y / (2 * Pc.l0), Pc.y_off / (2.0 * Pc.l0), 1.0 / (2.0 * Pc.c11),
                             Pc.Gamma * Pc.b / (2.0 * Pc.r0 ** 2), Pc.k_tau / (Pc.r0 ** 2 * Pc.c11), 1.0 / Pc.r0)
                            for Pc in (Pf, Pr))
        # public constants of the rear carrier (the paper's); per carrier: carrier_params
        self.cy = Pr.c_y
        self.Gamma = Pr.Gamma
        self.c22 = Pr.c11
        self.J_z = Pr.b * Pr.k_tau / (Pr.r0 * Pr.K * Pr.omega0 ** 2)
        self._front = _Carrier(Pf if front_lifted is None else
                               replace(Pf, D_min=front_lifted.D, D_max=front_lifted.D, bouc_wen=None,
                                       psi_off=front_lifted.psi_off), substeps)
        self._rear = _Carrier(Pr if rear_lifted is None else
                              replace(Pr, D_min=rear_lifted.D, D_max=rear_lifted.D, bouc_wen=None,
                                      psi_off=rear_lifted.psi_off), substeps)
        self._h = None
        self._v = None
        self.set_speed(P.v)
        self.reset()
        self._ft_rest = self.ft_rest_loads()     # the contact set-up is fixed for the plant's life

    # ---------------------------------------------------------------- the roller speed
    def set_speed(self, v: float) -> None:
        """Set the roller speed v (m/s, sign = direction) for the following steps; the
        speed-dependent constants are recomputed only when v changes (cost: docs/vehicle.md).

        Which terms scale with v: the lateral pole and input gain c̄_y v (2), the offset
        v y_off/(2 l0), the lateral creep of a force |v|/(2 c22), the kinematic terms of (4)
        (Γ v b/(2 r0²) y, the nominal wheel speed v/r0) and the creep term of the input in (4),
        |v| k_τ/(r0² c̄11) (a creep slip needs |v|, the paper's v > 0 form writes v). The yaw (6)
        has none: the v and 1/v terms of (5) cancel against (4) (docs/vehicle.md).
        ``wheel_dynamics="dynamic"`` keeps its fixed v: the creep pole -c̄11 r0²/(J_x v) of (3)
        is unstable for v < 0 as the paper writes it and unbounded at v = 0."""
        v = float(v)
        if v == self._v:
            return
        if self.dynamic and self._v is not None:
            raise ValueError(f"set_speed: wheel_dynamics='dynamic' runs at its fixed v = {self._v} "
                             f"(the creep pole of (3) is -c11 r0^2/(J_x v): unbounded at v = 0, "
                             f"unstable for v < 0), got {v}")
        self._v = v
        av = abs(v)
        (af, of, ff, gf, kf, wf), (ar, o_r, fr, gr, kr, wr) = self._per_v
        self._a_f, self._a_r = af * v, ar * v
        self._cyv_f, self._cyv_r = self._cy_f * v, self._cy_r * v
        self._off_f, self._off_r = of * v, o_r * v            # paper Sec. 4.1.2: (v/(2 l0)) y_off
        self._fy_f, self._fy_r = ff * av, fr * av              # lateral creep velocity per N
        self._gvb_f, self._gvb_r = gf * v, gr * v
        self._vk_f, self._vk_r = kf * av, kr * av
        self._w_nom_f, self._w_nom_r = wf * v, wr * v
        if self.dynamic:
            Pf, Pr = self.carrier_params["front"], self.carrier_params["rear"]
            self._lam_f = Pf.c11 * Pf.r0 ** 2 / (Pf.J_x * v)
            self._lam_r = Pr.c11 * Pr.r0 ** 2 / (Pr.J_x * v)
        else:
            self._lam_f = self._lam_r = 0.0
        if self._h is not None:
            self._prepare_lateral(self._h)

    v = property(lambda self: self._v, doc="roller speed now, m/s (sign = direction)")
    a_lat = property(lambda self: self._a_r, doc="rear lateral coefficient c̄_y,r v/(2 l0_r), 1/s")
    a_f = property(lambda self: self._a_f, doc="front lateral coefficient a_f = c̄_y,f v/(2 l0_f), 1/s")
    a_r = property(lambda self: self._a_r, doc="rear lateral coefficient a_r = c̄_y,r v/(2 l0_r), 1/s")

    # ---------------------------------------------------------------- state handling
    def reset(self, *, t: float = 0.0, y_f: Optional[float] = None, y_r: Optional[float] = None,
              psi_af: Optional[float] = None, psi_ar: Optional[float] = None,
              psi_rate_f: float = 0.0, psi_rate_r: float = 0.0,
              z_f: Optional[float] = None, z_r: Optional[float] = None,
              du_f: float = 0.0, du_r: float = 0.0) -> None:
        """Set the state (the speed stays); no disturbance is held afterwards.

        Defaults give a rest state: filters settled on du, psi = K du + psi_off (the linear
        equilibrium), z = psi (then a psi + (1-a) z = psi, so it is an equilibrium of the
        hysteretic model too), and y at its lateral equilibrium for that psi (where there is
        one): rear only in contact, y_r = (c_y v psi_ar + v y_off/(2 l0))/a_r (y_f = 0 always);
        front only (the mirrored set-up), y_f = -(c_y v psi_af + v y_off/(2 l0))/a_f (y_r = 0
        always); both in contact, y_r = 0 and y_f = y_r - g_r/a_r (an equilibrium of the pair
        only if the two carriers' forcing agree, g_f/a_f = g_r/a_r, otherwise (2a)/(2b) have
        none and y drifts). A lifted carrier's y stays where it is set (default: where it
        would rest if it rolled alone).
        """
        for car, psi, rate, z, du in ((self._front, psi_af, psi_rate_f, z_f, du_f),
                                      (self._rear, psi_ar, psi_rate_r, z_r, du_r)):
            car.psi = car.K * du + car.psi_off if psi is None else float(psi)
            car.p = float(rate)
            car.z = (car.psi if z is None else float(z)) if car.hyst else 0.0
            car.du = float(du)
            car.e = 0.0
            car.M = 0.0
            car.vl = car.p
        self._t = float(t)
        a_f, a_r = self._a_f, self._a_r
        g_f = self._cyv_f * self._front.psi + self._off_f
        g_r = self._cyv_r * self._rear.psi + self._off_r
        mode = self._lat_mode
        rest_r = g_r / a_r if a_r != 0.0 else 0.0           # rear alone: y_r' = -a_r y_r + g_r
        rest_f = -g_f / a_f if a_f != 0.0 else 0.0          # front alone: y_f' = a_f y_f + g_f
        if mode == _LAT_BOTH:
            self._y_r = 0.0 if y_r is None else float(y_r)
            if y_f is not None:
                self._y_f = float(y_f)
            else:
                self._y_f = self._y_r - g_r / a_r if a_r != 0.0 else self._y_r
        else:                                               # at most one carrier rolls
            self._y_f = ((rest_f if y_f is None else float(y_f))
                         if (self.front_contact or self.front_lifted) else 0.0)
            self._y_r = ((rest_r if y_r is None else float(y_r))
                         if (self.rear_contact or self.rear_lifted) else 0.0)
        self._F_f = self._F_r = 0.0
        self._dw_f, self._dw_r = self._dw_static()

    @property
    def state(self) -> PlantState:
        f, r = self._front, self._rear
        return PlantState(self._t, self._y_f, self._y_r, f.psi, r.psi, f.p, r.p, f.z, r.z,
                          f.e, r.e, self._dw_f, self._dw_r, f.du, r.du, self._v)

    def _y_kept(self, y_f: float, y_r: float) -> tuple[float, float]:
        """(y_f, y_r) as the contact set-up allows: a carrier out of contact by configuration
        has y = 0, a rolling or lifted one keeps its value."""
        return (y_f if (self.front_contact or self.front_lifted) else 0.0,
                y_r if (self.rear_contact or self.rear_lifted) else 0.0)

    def set_state(self, s: PlantState) -> None:
        """Restore a snapshot taken with ``state`` (disturbances are reset to zero; the speed is
        restored when the snapshot has one)."""
        if s.v is not None:
            self.set_speed(s.v)
        f, r = self._front, self._rear
        self._t = s.t
        self._y_f, self._y_r = self._y_kept(s.y_f, s.y_r)
        f.psi, r.psi, f.p, r.p = s.psi_af, s.psi_ar, s.psi_rate_f, s.psi_rate_r
        f.z, r.z = (s.z_f if f.hyst else 0.0), (s.z_r if r.hyst else 0.0)
        f.e, r.e, f.du, r.du = s.ue_f, s.ue_r, s.du_f, s.du_r
        f.M = r.M = 0.0
        f.vl, r.vl = f.p, r.p
        self._F_f = self._F_r = 0.0
        self._dw_f, self._dw_r = (s.dw_f, s.dw_r) if self.dynamic else self._dw_static()

    def state_vector(self) -> np.ndarray:
        """The state in the layout of ``rhs`` (``STATE_NAMES``)."""
        f, r = self._front, self._rear
        x = [self._y_f, self._y_r, f.psi, f.p, f.z, f.e, r.psi, r.p, r.z, r.e]
        if self.dynamic:
            x += [self._dw_f, self._dw_r]
        return np.array(x)

    def set_state_vector(self, x: Sequence[float], t: Optional[float] = None) -> None:
        f, r = self._front, self._rear
        x = [float(v) for v in x]
        self._y_f, self._y_r = self._y_kept(x[0], x[1])
        f.psi, f.p, f.z, f.e = x[2:6]
        r.psi, r.p, r.z, r.e = x[6:10]
        f.vl, r.vl = f.p, r.p
        if not f.hyst:
            f.z = 0.0
        if not r.hyst:
            r.z = 0.0
        if t is not None:
            self._t = float(t)
        self._dw_f, self._dw_r = (x[10], x[11]) if self.dynamic else self._dw_static()

    # ---------------------------------------------------------------- outputs
    t = property(lambda self: self._t, doc="simulated time, s")
    y_f = property(lambda self: self._y_f, doc="front lateral displacement, m (0 if out of contact)")
    y_r = property(lambda self: self._y_r, doc="rear lateral displacement, m (0 if out of contact)")
    dw_f = property(lambda self: self._dw_f, doc="front wheel-speed difference omega_fl - omega_fr, rad/s")
    dw_r = property(lambda self: self._dw_r, doc="rear wheel-speed difference omega_rl - omega_rr, rad/s")
    psi_af = property(lambda self: self._front.psi, doc="front carrier yaw angle psi_af, rad")
    psi_ar = property(lambda self: self._rear.psi, doc="rear carrier yaw angle psi_ar, rad")
    psi_rate_f = property(lambda self: self._front.p, doc="front yaw rate, rad/s")
    psi_rate_r = property(lambda self: self._rear.p, doc="rear yaw rate, rad/s")
    z_f = property(lambda self: self._front.z, doc="front Bouc-Wen state (0 if linear)")
    z_r = property(lambda self: self._rear.z, doc="rear Bouc-Wen state (0 if linear)")
    D_f = property(lambda self: self._front.damping(), doc="front damping D of (7) now")
    D_r = property(lambda self: self._rear.damping(), doc="rear damping D of (7) now")
    uf_f = property(lambda self: self._front.du - self._front.e, doc="front filtered input uf, A")
    uf_r = property(lambda self: self._rear.du - self._rear.e, doc="rear filtered input uf, A")
    udot_f = property(lambda self: self._front.e / self._front.tau,
                      doc="filtered input derivative used by (7), front, A/s")
    udot_r = property(lambda self: self._rear.e / self._rear.tau,
                      doc="filtered input derivative used by (7), rear, A/s")
    omega_fl = property(lambda self: self._w_nom_f + 0.5 * self._dw_f, doc="front-left wheel speed, rad/s")
    omega_fr = property(lambda self: self._w_nom_f - 0.5 * self._dw_f, doc="front-right wheel speed, rad/s")
    omega_rl = property(lambda self: self._w_nom_r + 0.5 * self._dw_r, doc="rear-left wheel speed, rad/s")
    omega_rr = property(lambda self: self._w_nom_r - 0.5 * self._dw_r, doc="rear-right wheel speed, rad/s")
    substeps_last = property(lambda self: (self._front.nsub_last, self._rear.nsub_last),
                             doc="yaw sub-steps used by the last step (front, rear)")

    def rolling(self, carrier: str) -> bool:
        """Whether ``carrier`` ("front" / "rear") is in rolling contact with the rollers."""
        return self.front_contact if carrier == "front" else self.rear_contact

    def _dw_static(self) -> tuple[float, float]:
        """Relation (4) per carrier in contact (a carrier out of contact has no rolling contact: 0)."""
        f, r = self._front, self._rear
        dwr = (self._gvb_r * self._y_r + self._b2r_r * r.p + self._vk_r * r.du) if self.rear_contact else 0.0
        dwf = (self._gvb_f * self._y_f + self._b2r_f * f.p + self._vk_f * f.du) if self.front_contact else 0.0
        return dwf, dwr

    def ft_loads(self) -> dict[str, tuple[float, float, float, float, float, float]]:
        """Loads (Fx, Fy, Fz, Mx, My, Mz) through each wheel side's force-torque sensor.

        Model (estimates, docs/plant-model.md): the held disturbance of a carrier passes half
        through each side (Fy = F_y/2, Mz = M_z/2); a carrier in contact adds the static
        wheel load Fz = WHEEL_LOAD_N and the longitudinal reaction of the differential motor
        torque, Fx = +-k_tau du/(2 r0) (left +, right -); Mx = My = 0.
        """
        out = {}
        for name, car, F, contact, Pc in (
                ("f", self._front, self._F_f, self.front_contact, self.carrier_params["front"]),
                ("r", self._rear, self._F_r, self.rear_contact, self.carrier_params["rear"])):
            fx = Pc.k_tau * car.du / (2.0 * Pc.r0) if contact else 0.0
            fz = WHEEL_LOAD_N if contact else 0.0
            out[name + "l"] = (fx, 0.5 * F, fz, 0.0, 0.0, 0.5 * car.M)
            out[name + "r"] = (-fx, 0.5 * F, fz, 0.0, 0.0, 0.5 * car.M)
        return out

    def ft_rest_loads(self) -> dict[str, tuple[float, float, float, float, float, float]]:
        """:meth:`ft_loads` of the rig at rest (no current, no disturbance) with its carriers'
        contact as configured: what the sensors are zeroed on (the static wheel load)."""
        return {k: (0.0, 0.0, fz, 0.0, 0.0, 0.0) for k, (_, _, fz, _, _, _) in self.ft_loads().items()}

    def ft_readings(self) -> dict[str, tuple[float, float, float, float, float, float]]:
        """Simulated force-torque sensor values (Fx, Fy, Fz, Mx, My, Mz) per wheel side: the
        sensors are zeroed (tared) at rest before the run, as on the rig, so each reads
        :meth:`ft_loads` minus :meth:`ft_rest_loads` — the static wheel load is tared out and
        Fz is its change (0 in this model, which has no vertical dynamics)."""
        rest = self._ft_rest
        return {k: tuple(a - b for a, b in zip(v, rest[k])) for k, v in self.ft_loads().items()}

    # ---------------------------------------------------------------- integration
    def _prepare(self, h: float) -> None:
        """Per-dt constants: filter decays, lateral and wheel-speed Hermite weights (a few µs)."""
        self._h = h
        self._ef_f = exp(-h / self._front.tau)
        self._ef_r = exp(-h / self._rear.tau)
        self._prepare_lateral(h)
        if self.dynamic:
            self._wh_f = self._wheel_weights(self._lam_f, h)
            self._wh_r = self._wheel_weights(self._lam_r, h)

    @staticmethod
    def _wheel_weights(lam: float, h: float) -> tuple:
        phi, *w = _hermite_weights(lam, h)
        return (phi,) + tuple(lam * x for x in w)             # forcing of (3) is lam * (4)

    def _prepare_lateral(self, h: float) -> None:
        """The lateral Hermite weights for the speed now (per v and dt)."""
        mode = self._lat_mode
        if mode == _LAT_BOTH:
            self._lat2 = _hermite_weights_coupled(self._a_f, h, self._a_r)
        elif mode == _LAT_REAR:
            self._lat1 = _hermite_weights(self._a_r, h)
        elif mode == _LAT_FRONT:
            self._lat1 = _hermite_weights(-self._a_f, h)       # y_f' = +a_f y_f + g_f (y_r = 0)

    def step(self, dt: float, du_f: float, du_r: float, F_y_f: float = 0.0, F_y_r: float = 0.0,
             M_z_f: float = 0.0, M_z_r: float = 0.0) -> None:
        """Advance by dt (s) with the differential currents du_f, du_r (A), lateral forces
        F_y_* (N), yaw moments M_z_* (N m) and the speed (``set_speed``) held over the step."""
        if dt != self._h:
            if not dt > 0.0:
                raise ValueError(f"dt: expected a positive step, got {dt!r}")
            self._prepare(dt)
        f, r = self._front, self._rear
        psi_f0, p_f0, psi_r0, p_r0 = f.psi, f.p, r.psi, r.p
        if self.dynamic:
            start = (psi_f0, p_f0, f.z, f.e + (du_f - f.du), psi_r0, p_r0, r.z, r.e + (du_r - r.du),
                     self._y_f, self._y_r)
        # yaw (exact / sub-stepped); skip an untouched front carrier resting exactly at equilibrium
        if (p_f0 != 0.0 or du_f != f.du or f.e != 0.0 or M_z_f != f.M or f.K * du_f + f.psi_off
                + M_z_f * f.inv_Jw2 != f.psi - f.oma * (f.psi - f.z)):
            f.advance(dt, self._ef_f, du_f, M_z_f)
        else:
            f.nsub_last = 0
        r.advance(dt, self._ef_r, du_r, M_z_r)
        self._F_f, self._F_r = F_y_f, F_y_r
        # lateral: exponential update, forcing = cubic Hermite of psi over the step
        mode = self._lat_mode
        if mode == _LAT_BOTH:
            (P0, P1), W = self._lat2
            cyf, cyr = self._cyv_f, self._cyv_r
            yf0, yr0 = self._y_f, self._y_r
            cf = self._off_f + self._fy_f * F_y_f
            cr = self._off_r + self._fy_r * F_y_r
            gf0, gr0 = cyf * psi_f0 + cf, cyr * psi_r0 + cr
            gf1, gr1 = cyf * f.psi + cf, cyr * r.psi + cr
            hf0, hr0, hf1, hr1 = cyf * p_f0, cyr * p_r0, cyf * f.p, cyr * r.p
            W0, W1, W2, W3 = W
            self._y_f = (P0[0] * yf0 + P0[1] * yr0 + W0[0][0] * gf0 + W0[0][1] * gr0 + W1[0][0] * hf0
                        + W1[0][1] * hr0 + W2[0][0] * gf1 + W2[0][1] * gr1 + W3[0][0] * hf1 + W3[0][1] * hr1)
            self._y_r = (P1[0] * yf0 + P1[1] * yr0 + W0[1][0] * gf0 + W0[1][1] * gr0 + W1[1][0] * hf0
                        + W1[1][1] * hr0 + W2[1][0] * gf1 + W2[1][1] * gr1 + W3[1][0] * hf1 + W3[1][1] * hr1)
        elif mode == _LAT_REAR:
            phi, w00, w10, w01, w11 = self._lat1
            cyv = self._cyv_r
            cr = self._off_r + self._fy_r * F_y_r
            yr0 = self._y_r
            self._y_r = (phi * yr0 + w00 * (cyv * psi_r0 + cr) + w10 * (cyv * p_r0)
                        + w01 * (cyv * r.psi + cr) + w11 * (cyv * r.p))
        elif mode == _LAT_FRONT:
            phi, w00, w10, w01, w11 = self._lat1
            cyv = self._cyv_f
            cf = self._off_f + self._fy_f * F_y_f
            yf0 = self._y_f
            self._y_f = (phi * yf0 + w00 * (cyv * psi_f0 + cf) + w10 * (cyv * p_f0)
                        + w01 * (cyv * f.psi + cf) + w11 * (cyv * f.p))
        self._t += dt
        # wheel speeds
        if not self.dynamic:
            if self.rear_contact:
                self._dw_r = self._gvb_r * self._y_r + self._b2r_r * r.p + self._vk_r * du_r
            else:
                self._dw_r = 0.0
            if self.front_contact:
                self._dw_f = self._gvb_f * self._y_f + self._b2r_f * f.p + self._vk_f * du_f
        else:
            self._wheel_dynamic(dt, start)

    def _lateral_rates(self, yf: float, yr: float, psi_f: float, psi_r: float) -> tuple[float, float]:
        """(y_f', y_r') of (2a)/(2b) with the held forces (0 for a carrier out of contact)."""
        a_f, a_r = self._a_f, self._a_r
        if not self.front_contact:
            yf = 0.0
        if not self.rear_contact:
            yr = 0.0
        d_f = (a_f * yf - a_f * yr + self._cyv_f * psi_f + (self._off_f + self._fy_f * self._F_f)
               if self.front_contact else 0.0)
        d_r = (-a_r * yr + a_r * yf + self._cyv_r * psi_r + (self._off_r + self._fy_r * self._F_r)
               if self.rear_contact else 0.0)
        return d_f, d_r

    def _wheel_dynamic(self, dt: float, start: tuple) -> None:
        """Exact exponential update of (3): Delta-omega relaxes to the static value (4) with the
        pole -lam; (4) over the step is taken as the cubic Hermite interpolant of its end values
        and end derivatives (only the last ~1/lam of the step matters)."""
        f, r = self._front, self._rear
        fpsi0, fp0, fz0, fe0, rpsi0, rp0, rz0, re0, yf0, yr0 = start
        yf1, yr1 = self._y_f, self._y_r
        yf_d0, yr_d0 = self._lateral_rates(yf0, yr0, fpsi0, rpsi0)
        yf_d1, yr_d1 = self._lateral_rates(yf1, yr1, f.psi, r.psi)
        if self.rear_contact:
            self._dw_r = self._dw_update(r, self._wh_r, self._gvb_r, self._b2r_r, self._vk_r,
                                         rpsi0, rp0, rz0, re0, yr0, yr1, yr_d0, yr_d1, self._dw_r)
        else:
            self._dw_r = 0.0
        if self.front_contact:
            self._dw_f = self._dw_update(f, self._wh_f, self._gvb_f, self._b2r_f, self._vk_f,
                                         fpsi0, fp0, fz0, fe0, yf0, yf1, yf_d0, yf_d1, self._dw_f)

    @staticmethod
    def _dw_update(car: _Carrier, wh: tuple, gvb: float, b2r: float, vk: float, psi0: float, p0: float,
                   z0: float, e0: float, y0: float, y1: float, yd0: float, yd1: float, dw: float) -> float:
        phi, w00, w10, w01, w11 = wh
        du = car.du
        rho0 = abs(e0) / (car.tau * car.cmax)               # right limit at the step start
        D0 = damping(rho0, car.Dmin, car.Dmax)
        ueq = car.K * du + car.psi_off + car.M * car.inv_Jw2
        acc0 = -2.0 * D0 * car.w0 * p0 + car.w02 * (ueq - (psi0 - car.oma * (psi0 - z0)))
        acc1 = car.accel(car.damping())
        s0 = gvb * y0 + b2r * p0 + vk * du
        s1 = gvb * y1 + b2r * car.p + vk * du
        return phi * dw + w00 * s0 + w10 * (gvb * yd0 + b2r * acc0) + w01 * s1 + w11 * (gvb * yd1 + b2r * acc1)

    # ---------------------------------------------------------------- reference model
    def rhs(self, t: float, x: np.ndarray, inputs: Any) -> np.ndarray:
        """The same model as a vectorised right-hand side (x of shape (n,) or (n, m)) at the
        speed set now (``set_speed``).

        ``inputs`` = (du_f, du_r, F_y_f, F_y_r, M_z_f, M_z_r), held constant over the
        integration interval (the model's input is zero-order hold).  Where du changes, the
        filter residual ue of the state jumps by the same amount: see ``input_jump``.
        """
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:       # scalar path (the implicit solver's Newton iterations): plain floats
            return np.array(self._rhs(x.tolist(), inputs, abs, _select))
        out = np.empty_like(x)
        for i, r in enumerate(self._rhs(list(x), inputs, np.abs, np.where)):
            out[i] = r
        return out

    def _rhs(self, x: list, inputs: Any, absf: Callable, select: Callable) -> list:
        du_f, du_r, Fyf, Fyr, Mzf, Mzr = (float(v) for v in inputs)
        a_f, a_r = self._a_f, self._a_r
        yf, yr = x[_I_YF], x[_I_YR]
        dx = [0.0] * self.n_states
        if not self.front_contact:
            yf = 0.0 if not self.front_lifted else yf
        if not self.rear_contact:
            yr = 0.0 if not self.rear_lifted else yr
        yf_c = yf if self.front_contact else 0.0          # what the other carrier's (2) sees
        yr_c = yr if self.rear_contact else 0.0
        if self.front_contact:
            dx[_I_YF] = a_f * yf - a_f * yr_c + self._cyv_f * x[_I_F] + self._off_f + self._fy_f * Fyf
        if self.rear_contact:
            dx[_I_YR] = -a_r * yr + a_r * yf_c + self._cyv_r * x[_I_R] + self._off_r + self._fy_r * Fyr
        for car, i, du, M in ((self._front, _I_F, du_f, Mzf), (self._rear, _I_R, du_r, Mzr)):
            psi, p, z, ue = x[i], x[i + 1], x[i + 2], x[i + 3]
            udot = ue / car.tau
            rho = absf(udot) / car.cmax
            D = damping(rho, car.Dmin, car.Dmax, select)
            if car.hyst:
                R = car.a * psi + car.oma * z
                az = absf(z)
                n = car.n
                if n == 1:
                    dx[i + 2] = car.A * p - car.beta * absf(p) * z - car.gamma * p * az
                else:
                    dx[i + 2] = car.A * p - car.beta * absf(p) * az ** (n - 1) * z - car.gamma * p * az ** n
            else:
                R = psi
            dx[i] = p
            dx[i + 1] = (-2.0 * D * car.w0 * p - car.w02 * R
                         + car.w02 * (car.K * du + car.psi_off + M * car.inv_Jw2))
            dx[i + 3] = -udot
        if self.dynamic:
            if self.rear_contact:
                dx[_I_DW + 1] = self._lam_r * (self._gvb_r * yr + self._b2r_r * x[_I_R + 1]
                                               + self._vk_r * du_r - x[_I_DW + 1])
            else:
                dx[_I_DW + 1] = -self._lam_r * x[_I_DW + 1]
            if self.front_contact:
                dx[_I_DW] = self._lam_f * (self._gvb_f * yf + self._b2r_f * x[_I_F + 1]
                                           + self._vk_f * du_f - x[_I_DW])
            else:
                dx[_I_DW] = -self._lam_f * x[_I_DW]
        return dx

    @staticmethod
    def input_jump(x: np.ndarray, old: Sequence[float], new: Sequence[float]) -> np.ndarray:
        """State vector just after the held inputs change from ``old`` to ``new`` (ue += d du)."""
        x = np.array(x, dtype=float)
        x[_I_F + 3] += new[0] - old[0]
        x[_I_R + 3] += new[1] - old[1]
        return x
