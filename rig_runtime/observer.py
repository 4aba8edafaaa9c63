"""The lateral-displacement observer of one carrier: a steady-state discrete Kalman filter on
the linear model of Sec. 4, run every cycle as a stage of the carrier's lane.

State ``x = (y, ψ, ψ̇)`` of the carrier, input the differential current ``u`` held over the
period (and the other carrier's ``y`` where both are in contact, as a known input):

    (2b)  ẏ = −a y + c̄_y v ψ + a y_other + (v/2l0) y_off + |v|/(2 c22) F_y    (a = c̄_y v/(2 l0))
    (6)   ψ̈ = −2Dω0 ψ̇ − ω0² ψ + Kω0² u + ω0² ψ_off              (hysteresis: process noise)

with ``F_y`` the carrier's lateral force as its F/T sensors measure it (the sum of the two
sides' Fy: the same force the plant applies, docs/plant-model.md §3), a known input like u —
a force pulse or side wind moves y without moving ψ first, which the model would otherwise
take for a lateral laser disagreeing; held over h (``A``, ``B``, ``E``, ``F``, ``c``), with
three measurements

    lateral:  y from the lateral lasers (Sec. 2 geometry)   — used only when they are fit
    yaw:      ψ from the yaw lasers
    (4)       Δω = Γvb/(2r0²) y + b/(2r0) ψ̇ + |v| k_τ/(r0² c̄11) u   — carries y through Δω

(each carrier with its own plant values; the input term of (4) has |v|, as the plant's:
docs/vehicle/plant.md).

The gains are the steady-state Kalman gains of the predictor/corrector pair for two
measurement sets (all three; yaw and Δω only when a lateral laser is not fit in this cycle),
designed at configure time from the configured sensor noise by the discrete Riccati
equation (``rig_runtime.app.observer_design``): this module gets plain floats, keeps
preallocated state and does scalar arithmetic only (no numpy, no scipy in the cycle).

Health (analytical redundancy): each measurement's innovation ``ν`` normalised by its
steady-state standard deviation ``√S``; over the last ``window`` cycles the statistic
``T = (Σ ν/√S)² / N`` is χ²(1) while the sensors agree with the model and with each other,
and grows with N·(bias/√S)² when one of them carries a bias. The supervisor judges it
(``safety.innovation_*``); the observer only computes it.

Speed (a ``controller.schedule``): the design carries a table of designs over a grid of
speeds (``SpeedTable``); :meth:`Observer.select` switches to the grid point nearest the
measured speed — a reference swap, nothing allocated, nothing interpolated (each grid point
is one consistent Riccati solution: model, gains, innovation variances and outage table
belong together; docs/observer.md, "vehicle").

Outage: the gains are steady-state, so the error covariance of ŷ while no lateral laser is
used grows deterministically with the cycles since the last lateral update (from the full
filter's steady state towards the yaw-and-Δω filter's); the design tabulates that growth
(``sigma_y_outage``) and the observer reports ``sigma_y`` from it every cycle. Whether it is
too large is the supervisor's rule (``safety.degraded_covariance``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

MEASUREMENTS = ("lat", "psi", "dw")       # the filter's measurements, in gain-column order
LOG_FIELDS = ("y_hat", "psi_hat", "psi_rate_hat", "nu_lat", "nu_psi", "nu_dw",
              "T_lat", "T_psi", "T_dw", "lat_used", "degraded", "sigma_y")


@dataclass(frozen=True)
class ObserverDesign:
    """A carrier's filter as plain numbers (row-major tuples), made at configure time.

    ``A`` (3×3), ``B``/``E``/``F``/``c`` (3): the model held over h for input u, the other
    carrier's y, the lateral force F_y (N) and the offsets; ``dw_row`` = (∂Δω/∂y, ∂Δω/∂ψ̇, ∂Δω/∂u) of (4);
    ``K_full`` (3×3: state × (lat, psi, dw)), ``K_nolat`` (3×2: state × (psi, dw));
    ``S_full`` (3), ``S_nolat`` (2): the steady-state innovation variances; ``window``:
    cycles of the health statistic; ``lateral_lasers``/``yaw_lasers``/``encoders``: the
    devices behind each measurement (for the supervisor's finding); ``ft_sensors``: the F/T
    sensors whose Fy sum to the carrier's lateral force (empty: no force input);
    ``sigma_y_outage``: the standard deviation of ŷ's error (m) after k cycles without a
    lateral update, k = 0, 1, …, up to where it has converged (its last value holds from
    there on; empty: not tabulated, ``sigma_y`` NaN)."""

    carrier: str
    A: tuple[float, ...]
    B: tuple[float, float, float]
    E: tuple[float, float, float]
    F: tuple[float, float, float]
    c: tuple[float, float, float]
    dw_row: tuple[float, float, float]
    K_full: tuple[float, ...]
    K_nolat: tuple[float, ...]
    S_full: tuple[float, float, float]
    S_nolat: tuple[float, float]
    window: int
    lateral_lasers: tuple[str, ...]
    lateral_weights: tuple[float, ...]       # ∂y/∂(laser reading) of the geometry, same order
    yaw_lasers: tuple[str, ...]
    encoders: tuple[str, ...]
    ft_sensors: tuple[str, ...] = ()
    sigma_y_outage: tuple[float, ...] = ()
    v: float = math.nan                       # the speed the design is for (m/s)
    table: Optional["SpeedTable"] = None      # designs over the schedule's speeds (None: this one only)

    @property
    def channels(self) -> tuple[str, ...]:
        """The supervisor channels behind the filter's measurements."""
        return self.lateral_lasers + self.yaw_lasers + self.encoders


@dataclass(frozen=True)
class SpeedTable:
    """A carrier's designs over a grid of speeds, made at configure time: grid index k is the
    speed ±``v_ref``·``ratio``ᵏ, k = ``k_lo`` … ``k_hi``; ``forward``/``backward`` hold the
    designs at +/− those speeds, in k order. The lowest grid speed lies inside the standstill
    band; below it, and beyond the highest, the end design is used."""

    v_ref: float
    ratio: float
    k_lo: int
    k_hi: int
    forward: tuple[ObserverDesign, ...]
    backward: tuple[ObserverDesign, ...]


class Observer:
    """One carrier's filter and health statistics, updated in place by :meth:`step`."""

    __slots__ = ("d", "carrier", "started", "y", "psi", "rate", "nu_lat", "nu_psi", "nu_dw",
                 "T_lat", "T_psi", "T_dw", "lat_used", "_ring", "_sum", "_i", "_n", "_N",
                 "_is", "_is_nl", "mean_lat", "mean_dw", "degraded", "outage", "sigma_y", "_sig",
                 "_fw", "_bw", "_lref", "_ilr", "_klo", "_khi")

    def __init__(self, design: ObserverDesign):
        self.d = design
        self.carrier = design.carrier
        self.started = False
        self.y = self.psi = self.rate = 0.0
        self.nu_lat = self.nu_psi = self.nu_dw = 0.0
        self.T_lat = self.T_psi = self.T_dw = 0.0
        self.mean_lat = self.mean_dw = 0.0      # window means of the innovations (m, rad/s)
        self.lat_used = 0.0
        self.degraded = 0.0                     # 1: the lane runs on this estimate (set by the loop)
        self.outage = 0                         # cycles since the last update with the lateral lasers
        self._sig = design.sigma_y_outage
        self.sigma_y = self._sig[0] if self._sig else math.nan   # σ of ŷ's error after that outage (m)
        N = design.window
        self._N = N
        self._ring = [[0.0] * N for _ in MEASUREMENTS]     # normalised innovations per measurement
        self._sum = [0.0, 0.0, 0.0]
        self._i = 0
        self._n = 0                              # samples in the window so far (up to N)
        self._is, self._is_nl = _inverse_stds(design)
        # the speed table, ready to swap in: (design, 1/√S_full, 1/√S_nolat, σ table) per grid point
        t = design.table
        self._fw = self._bw = None
        if t is not None:
            self._fw = tuple((e,) + _inverse_stds(e) + (e.sigma_y_outage,) for e in t.forward)
            self._bw = tuple((e,) + _inverse_stds(e) + (e.sigma_y_outage,) for e in t.backward)
            self._lref, self._ilr = math.log(t.v_ref), 1.0 / math.log(t.ratio)
            self._klo, self._khi = t.k_lo, t.k_hi

    def select(self, v: float) -> None:
        """Use the design of the grid speed nearest the measured speed ``v`` (a schedule's
        table only; nothing for v = 0 or NaN: the last design stays). Below the grid's lowest
        speed — inside the standstill band — that speed's design of v's sign."""
        fw = self._fw
        if fw is None or v == 0.0 or v != v:
            return
        k = round((math.log(v if v > 0.0 else -v) - self._lref) * self._ilr)
        k = self._klo if k < self._klo else self._khi if k > self._khi else k
        ch = (fw if v > 0.0 else self._bw)[k - self._klo]
        if ch[0] is not self.d:
            self.d, self._is, self._is_nl, self._sig = ch

    def reset(self) -> None:
        """Forget the estimate and the health window (the next step starts afresh)."""
        self.started = False
        for r in self._ring:
            for k in range(self._N):
                r[k] = 0.0
        self._sum[0] = self._sum[1] = self._sum[2] = 0.0
        self._i = self._n = 0
        self.T_lat = self.T_psi = self.T_dw = 0.0
        self.outage = 0
        self.sigma_y = self._sig[0] if self._sig else math.nan

    def step(self, y_meas: float, psi_meas: float, dw_meas: float, u_held: float, y_other: float,
             lat_ok: bool, f_lat: float = 0.0) -> None:
        """One cycle: predict over h with the current held since the last cycle (``u_held``),
        the other carrier's y and the measured lateral force ``f_lat`` (N), then correct with this cycle's measurements (the lateral
        one only if ``lat_ok``), and update the health window."""
        d = self.d
        if not self.started:                    # first cycle: start on the measurements
            self.started = True
            self.y = y_meas if lat_ok else 0.0
            self.psi = psi_meas
            self.rate = 0.0
            return
        A, B, E, F, c = d.A, d.B, d.E, d.F, d.c
        y, p, r = self.y, self.psi, self.rate
        yp = A[0] * y + A[1] * p + A[2] * r + B[0] * u_held + E[0] * y_other + F[0] * f_lat + c[0]
        pp = A[3] * y + A[4] * p + A[5] * r + B[1] * u_held + E[1] * y_other + F[1] * f_lat + c[1]
        rp = A[6] * y + A[7] * p + A[8] * r + B[2] * u_held + E[2] * y_other + F[2] * f_lat + c[2]
        gy, gr, gu = d.dw_row
        n_psi = psi_meas - pp
        n_dw = dw_meas - (gy * yp + gr * rp + gu * u_held)
        n_lat = y_meas - yp
        self.nu_psi, self.nu_dw = n_psi, n_dw
        if lat_ok:
            K = d.K_full
            self.y = yp + K[0] * n_lat + K[1] * n_psi + K[2] * n_dw
            self.psi = pp + K[3] * n_lat + K[4] * n_psi + K[5] * n_dw
            self.rate = rp + K[6] * n_lat + K[7] * n_psi + K[8] * n_dw
            self.nu_lat = n_lat
            self.lat_used = 1.0
            inv = self._is
            z_lat = n_lat * inv[0]
            z_psi, z_dw = n_psi * inv[1], n_dw * inv[2]
            self.outage = 0
        else:
            K = d.K_nolat
            self.y = yp + K[0] * n_psi + K[1] * n_dw
            self.psi = pp + K[2] * n_psi + K[3] * n_dw
            self.rate = rp + K[4] * n_psi + K[5] * n_dw
            self.nu_lat = math.nan
            self.lat_used = 0.0
            inv = self._is_nl
            z_lat = 0.0                         # not in the update: no evidence this cycle
            z_psi, z_dw = n_psi * inv[0], n_dw * inv[1]
            self.outage += 1
        sig = self._sig
        if sig:
            k = self.outage
            self.sigma_y = sig[k] if k < len(sig) else sig[-1]
        self._window(z_lat, z_psi, z_dw)

    def _window(self, z_lat: float, z_psi: float, z_dw: float) -> None:
        i, N, ring, s = self._i, self._N, self._ring, self._sum
        r0, r1, r2 = ring
        s[0] += z_lat - r0[i]
        s[1] += z_psi - r1[i]
        s[2] += z_dw - r2[i]
        r0[i], r1[i], r2[i] = z_lat, z_psi, z_dw
        self._i = i + 1 if i + 1 < N else 0
        if self._n < N:
            self._n += 1
        if self._n == N:
            invN = 1.0 / N
            self.T_lat = s[0] * s[0] * invN
            self.T_psi = s[1] * s[1] * invN
            self.T_dw = s[2] * s[2] * invN
            # sizes of the disagreement: the window's mean innovation in the measurement's unit
            self.mean_lat = s[0] * invN * math.sqrt(self.d.S_full[0])
            self.mean_dw = s[2] * invN * math.sqrt(self.d.S_full[2])

    @property
    def window_full(self) -> bool:
        return self._n == self._N

    def log_values(self) -> tuple[float, ...]:
        """This cycle's values in ``LOG_FIELDS`` order."""
        return (self.y, self.psi, self.rate, self.nu_lat, self.nu_psi, self.nu_dw,
                self.T_lat, self.T_psi, self.T_dw, self.lat_used, self.degraded, self.sigma_y)


def _inverse_stds(d: ObserverDesign) -> tuple[tuple[float, ...], tuple[float, ...]]:
    return tuple(1.0 / math.sqrt(s) for s in d.S_full), tuple(1.0 / math.sqrt(s) for s in d.S_nolat)


def dw_row_at(p, v: float) -> tuple[float, float, float]:
    """(∂Δω/∂y, ∂Δω/∂ψ̇, ∂Δω/∂u) of relation (4) for plant values ``p`` (a config Plant: a
    carrier's, ``cfg.plant.carrier(c)``) at speed ``v``: Δω = Γvb/(2r0²)·y + b/(2r0)·ψ̇ +
    |v| k_τ/(r0² c̄11)·u (the kinematic term keeps v's sign, the creep term of the input has |v|:
    docs/vehicle/plant.md)."""
    return (p.Gamma * v * p.b / (2 * p.r0 ** 2), p.b / (2 * p.r0), abs(v) * p.k_tau / (p.r0 ** 2 * p.c11))


def dw_row(cfg) -> tuple[float, float, float]:
    """:func:`dw_row_at` for the configured common plant at plant.v (``cfg``: a RigConfig)."""
    return dw_row_at(cfg.plant, cfg.plant.v)

