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

The running gear (both carriers controlled, docs/observer.md "One filter for the running
gear"): :class:`JointObserver` holds both carriers and their coupling in one 6-state filter,
each lateral laser a measurement of its own (one laser measures a combination of y_f and
y_r), a precomputed gain set per lost laser; each lane holds a :class:`CarrierView` of it that
reads like an :class:`Observer`; its health statistics are the bias test of each measurement.

Outage: the gains are steady-state, so the error covariance of ŷ while no lateral laser is
used grows deterministically with the cycles since the last lateral update (from the full
filter's steady state towards the yaw-and-Δω filter's); the design tabulates that growth
(``sigma_y_outage``) and the observer reports ``sigma_y`` from it every cycle. Whether it is
too large is the supervisor's rule (``safety.degraded_covariance``).
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from typing import Optional

from .damping import damping
from .hysteresis import zmap

MEASUREMENTS = ("lat", "psi", "dw")       # the filter's measurements, in gain-column order
LOG_FIELDS = ("y_hat", "psi_hat", "psi_rate_hat", "nu_lat", "nu_psi", "nu_dw",
              "T_lat", "T_psi", "T_dw", "lat_used", "degraded", "sigma_y")


@dataclass(frozen=True)
class YawModel:
    """The plant's yaw non-linearities of Sec. 4.3.3–4.3.4 (sim_backend/plant.py: (7) and (9)),
    which the linear model (6) leaves out, as plain numbers for a known nonlinear input computed
    from the estimate (docs/observer.md, "The hysteresis and the damping in the model"):

    - hysteresis: the restoring term of (9) is ω0²(a ψ + (1 − a) z), (6) has ω0² ψ; the
      difference ω0²(1 − a)(ψ − z) enters as the equivalent current ``gain``·(ψ̂ − ẑ),
      ``gain`` = (1 − a)/K, with ẑ the Bouc-Wen state driven by ψ̂ (n = 1, the exact map);
      ``gain`` 0: no hysteresis. ẑ moves only once ψ̂ has moved by ``dead`` since its last
      move (4 σ of the yaw measurement): the map's unloading branch is 70× steeper than ψ at a
      saturated z, so every reversal of ψ̂'s measurement jitter would ratchet ẑ towards 0 —
      the plant's ψ does not jitter;
    - damping law (7): D from the input's filter residual (udot = residual/τ), exactly as the
      plant computes it from the same held current; the damping beyond the model's ``D0``
      decays the predicted yaw rate by exp(−2ω0 (D − D0) h) (split off the linear step: D
      reaches 100, 2ω0·100·h = 19 — an explicit input would not be stable)."""

    gain: float          # (1 − a)/K, A/rad
    A: float
    beta: float
    gamma: float
    w0: float            # ω0, rad/s
    D0: float            # the damping of the linear model
    D_min: float
    D_max: float
    irc: float           # 1/(τ c_udot_max): |residual| → ρ = |udot|/c_udot_max
    ef: float            # exp(−h/τ): the filter residual's decay over a period
    mid: float           # exp(−h/(2τ)): ρ at mid-period
    h: float
    dead: float = 0.0    # rad: ψ̂'s motion that moves ẑ (its jitter does not)


class _YawState:
    """The non-linearities' own state of one carrier: ẑ, the estimate's ψ̂ it last followed, the
    filter residual, the last current (and, once :meth:`bind` has been given the model, its
    constants as plain floats: the cycle reads them here instead of on the model)."""

    __slots__ = ("z", "psi", "e", "u", "acc", "_m", "_gain", "_ef", "_irm", "_kmin", "_c", "_dead")

    def __init__(self) -> None:
        self.z = self.psi = self.e = self.u = self.acc = 0.0
        self._m = None

    def bind(self, m: YawModel) -> None:
        """The model's constants, unpacked (the same for every speed of a table: they do not
        depend on v)."""
        if m is self._m:
            return
        self._m = m
        self._gain, self._ef, self._irm = m.gain, m.ef, m.irc * m.mid
        self._c = 2.0 * m.w0 * m.h
        self._kmin = math.exp(-self._c * (m.D_min - m.D0))    # D = D_min (the input moves)
        self._dead = m.dead

    def start(self, psi: float, u: float) -> None:
        self.z, self.e, self.u = psi, 0.0, u     # at rest: z = ψ (the plant's rest state), filter settled
        self.psi = psi
        self.acc = 0.0

    def inputs(self, m: YawModel, psi: float, u: float) -> tuple[float, float]:
        """The prediction's known inputs from the estimate ``psi`` (ψ̂ at the period's start):
        first ẑ follows ψ̂'s change since the last call (the last period's correction) once it
        is past the dead band; then (the equivalent current of the hysteresis term, the yaw
        rate's extra decay) over the period ahead, with the current ``u`` held over it (advances
        the filter residual)."""
        if m is not self._m:
            self.bind(m)
        g = self._gain
        if g != 0.0:
            a = self.acc + (psi - self.psi)
            self.psi = psi
            if a >= self._dead or -a >= self._dead:
                self.z = zmap(self.z, a, m.A, m.beta, m.gamma)
                a = 0.0
            self.acc = a
        r = self.e + (u - self.u)
        self.u = u
        self.e = r * self._ef
        rho = (r if r >= 0.0 else -r) * self._irm
        if rho >= 1.0:
            return g * (psi - self.z), self._kmin
        x = self._c * (damping(rho, m.D_min, m.D_max) - m.D0)
        return g * (psi - self.z), (math.exp(-x) if x < 40.0 else 0.0)


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
    yaw: Optional[YawModel] = None            # the hysteresis and damping law as a known input (None: not modelled)

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
                 "_fw", "_bw", "_lref", "_ilr", "_klo", "_khi", "_ys", "lead")

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
        self._ys = _YawState()
        self.lead = None                        # the rules judge in their order (JointObserver's views decide)
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
            self._ys.start(psi_meas, u_held)
            return
        A, B, E, F, c = d.A, d.B, d.E, d.F, d.c
        y, p, r = self.y, self.psi, self.rate
        ym, ue, decay = d.yaw, u_held, 1.0
        if ym is not None:                      # the hysteresis and damping law: a known input
            dh, decay = self._ys.inputs(ym, p, u_held)
            ue = u_held + dh
        yp = A[0] * y + A[1] * p + A[2] * r + B[0] * ue + E[0] * y_other + F[0] * f_lat + c[0]
        pp = A[3] * y + A[4] * p + A[5] * r + B[1] * ue + E[1] * y_other + F[1] * f_lat + c[1]
        rp = (A[6] * y + A[7] * p + A[8] * r + B[2] * ue + E[2] * y_other + F[2] * f_lat + c[2]) * decay
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



# ---------------------------------------------------------------------- the running gear's filter
#: the joint filter's measurements, in gain-column order: both lateral lasers (less b0), each
#: carrier's ψ and Δω
JOINT_MEASUREMENTS = ("b_f", "b_r", "psi_f", "psi_r", "dw_f", "dw_r")
#: the measurement sets by index 2·(b_f not fit) + (b_r not fit): the measurements used
JOINT_SETS = ((0, 1, 2, 3, 4, 5), (0, 2, 3, 4, 5), (1, 2, 3, 4, 5), (2, 3, 4, 5))
#: each joint measurement's carrier view and the kind of its statistic there
JOINT_LEAD = (("front", "lat"), ("rear", "lat"), ("front", "psi"), ("rear", "psi"), ("front", "dw"), ("rear", "dw"))
#: the bias statistic beyond which the drift test is computed and published instead (χ²(1):
#: p = 0.003 per window without a fault; far below any innovation_chi2 that makes sense): the
#: drift test costs ~10 µs, the bias test ~2, and it only has to name what is found
DRIFT_GATE = 9.0
#: cycles past the gate the same fault must explain the innovations best before the views name it (a drift's
#: onset inside the window fits neither hypothesis well: a lateral laser's looked like a yaw pair's
#: for ~0.1 s; b_f and b_r count as one — a lateral finding isolates both)
LEAD_CONFIRM = 40


@dataclass(frozen=True)
class CarrierPart:
    """What the supervisor's rules and the lane read of one carrier in the joint filter (the
    names an :class:`ObserverDesign` gives them)."""

    carrier: str
    lateral_lasers: tuple[str, ...]
    lateral_weights: tuple[float, ...]
    yaw_lasers: tuple[str, ...]
    encoders: tuple[str, ...]
    ft_sensors: tuple[str, ...]
    dw_row: tuple[float, float, float]
    yaw: Optional[YawModel] = None           # the carrier's hysteresis and damping law (None: not modelled)

    @property
    def channels(self) -> tuple[str, ...]:
        return self.lateral_lasers + self.yaw_lasers + self.encoders


@dataclass(frozen=True)
class JointDesign:
    """Both carriers in one filter as plain numbers (docs/observer.md, "One filter for the
    running gear"): state (y_f, ψ_f, ψ̇_f, y_r, ψ_r, ψ̇_r); ``A`` 6×6, ``Bu`` 6×2 (u_f, u_r),
    ``BF`` 6×2 (F_f, F_r), ``c`` 6, row-major; ``laser_rows``: ∂(b − b0)/∂(y_f, y_r) of b_f and
    b_r; ``K[s]`` the steady-state gain (6×6, state × ``JOINT_MEASUREMENTS``, an unused
    measurement's column 0) and ``S[s]`` the innovation variances (unused: 1) of measurement set
    s (``JOINT_SETS``); ``sigma_y[s]`` = (front, rear) σ of ŷ's error after k cycles on set s
    (set 0: the steady state)."""

    A: tuple[float, ...]
    Bu: tuple[float, ...]
    BF: tuple[float, ...]
    c: tuple[float, ...]
    laser_rows: tuple[tuple[float, float], tuple[float, float]]
    b0: float
    K: tuple[tuple[float, ...], ...]
    S: tuple[tuple[float, ...], ...]
    sigma_y: tuple[tuple[tuple[float, ...], tuple[float, ...]], ...]
    window: int
    front: CarrierPart
    rear: CarrierPart
    v: float = math.nan
    table: Optional["SpeedTable"] = None
    #: 6×6, row j: the weights w_j of the bias test on measurement j over the window's summed
    #: innovations (all lasers in use; observer_design._isolation_weights)
    isolation: tuple[float, ...] = ()
    #: 6×15, row j: the drift test on measurement j (observer_design._ramp_weights): u_j (6),
    #: l_j (6) and the inverse information matrix (M⁻¹₁₁, M⁻¹₁₂, M⁻¹₂₂) of (β0, ρ)
    drift: tuple[float, ...] = ()

    @property
    def lateral_lasers(self) -> tuple[str, str]:
        return ("b_f", "b_r")

    def part(self, carrier: str) -> CarrierPart:
        return self.front if carrier == "front" else self.rear


@dataclass(frozen=True)
class JointCarrier:
    """A carrier's share of the running gear's filter: what a lane is given (``make_observers``
    builds one :class:`JointObserver` per ``joint`` and a :class:`CarrierView` per carrier)."""

    carrier: str
    joint: JointDesign

    @property
    def lateral_lasers(self) -> tuple[str, ...]:
        return self.joint.part(self.carrier).lateral_lasers

    @property
    def ft_sensors(self) -> tuple[str, ...]:
        return self.joint.part(self.carrier).ft_sensors


class CarrierView:
    """One carrier of the joint filter, by the names the supervisor, the lane and the log read
    of an :class:`Observer`: what the rules read every cycle (the statistics, ``lat_used``,
    ``sigma_y``, ``lead``) the joint filter writes here every step; the estimate and the
    innovations (the log's, and ŷ for a DEGRADED lane) and what only a finding's message reads
    (the window means, the outage's length) are read from the joint filter when asked."""

    __slots__ = ("joint", "carrier", "d", "T_lat", "T_psi", "T_dw", "lat_used", "degraded", "sigma_y",
                 "window_full", "started", "lead", "_o", "_m")

    def __init__(self, joint: "JointObserver", carrier: str):
        self.joint = joint
        self.carrier = carrier
        self.d = joint.d.part(carrier)
        self._o = 0 if carrier == "front" else 3      # its first state in the joint filter's x
        self._m = 0 if carrier == "front" else 1      # its lateral laser's innovation (ψ: +2, Δω: +4)
        self.T_lat = self.T_psi = self.T_dw = 0.0
        self.lat_used = 0.0
        self.degraded = 0.0
        self.sigma_y = 0.0
        self.window_full = False
        self.started = False
        #: the kind ("lat", "psi", "dw") of this carrier's measurement whose fault explains the
        #: joint filter's innovations best, "" when it is the other carrier's, None: not decided
        #: (a laser out: each statistic on its own; the rules then judge in their order)
        self.lead: Optional[str] = None

    @property
    def y(self) -> float:
        return self.joint.x[self._o]

    @property
    def psi(self) -> float:
        return self.joint.x[self._o + 1]

    @property
    def rate(self) -> float:
        return self.joint.x[self._o + 2]

    @property
    def nu_lat(self) -> float:
        """Its lateral laser's innovation (NaN when the step did not use that laser)."""
        j = self.joint
        return j._raw[self._m][j._i - 1] if self.lat_used else math.nan

    @property
    def nu_psi(self) -> float:
        j = self.joint
        return j._raw[self._m + 2][j._i - 1]

    @property
    def nu_dw(self) -> float:
        j = self.joint
        return j._raw[self._m + 4][j._i - 1]

    @property
    def mean_lat(self) -> float:
        """The window mean of its lateral laser's innovation (m; read once the window is full)."""
        return self.joint._rsum[self._m] * (1.0 / self.joint._N)

    @property
    def mean_dw(self) -> float:
        """The window mean of its Δω innovation (rad/s; read once the window is full)."""
        return self.joint._rsum[self._m + 4] * (1.0 / self.joint._N)

    @property
    def outage(self) -> int:
        return self.joint.outage

    def select(self, v: float) -> None:
        self.joint.select(v)

    def reset(self) -> None:
        self.joint.reset()

    def log_values(self) -> tuple[float, ...]:
        j, o, m = self.joint, self._o, self._m
        x, q, i = j.x, j._raw, j._i - 1          # the latest innovations: the window's newest samples
        return (x[o], x[o + 1], x[o + 2], q[m][i] if self.lat_used else math.nan, q[m + 2][i], q[m + 4][i],
                self.T_lat, self.T_psi, self.T_dw, self.lat_used, self.degraded, self.sigma_y)


def _joint_plan(d: JointDesign) -> tuple:
    """What the step reads of a design, resolved once per design (not per cycle): the held
    model's entries the step uses (the yaw rows' structural zeros left out, JointDesign), the
    laser rows, b0, each carrier's Δω row — one flat tuple the step unpacks —, the gain sets,
    the bias test's weights, each set's inverse innovation standard deviations, the outage
    tables and the yaw models."""
    A, Bu, BF, c = d.A, d.Bu, d.BF, d.c
    (ff, fr), (rf, rr) = d.laser_rows
    model = ((ff, fr, rf, rr, d.b0)
             + tuple(A[k] for k in (0, 1, 2, 3, 4, 5, 7, 8, 13, 14, 18, 19, 20, 21, 22, 23, 28, 29, 34, 35))
             + tuple(Bu[k] for k in (0, 1, 2, 4, 6, 7, 9, 11)) + (BF[0], BF[1], BF[6], BF[7]) + c
             + d.front.dw_row + d.rear.dw_row)
    inv = tuple(tuple(1.0 / math.sqrt(s) for s in S) for S in d.S)
    return d, model, d.K, d.isolation, inv, d.sigma_y, d.front.yaw, d.rear.yaw


class JointObserver:
    """The running gear's filter, updated in place by :meth:`step`: scalar arithmetic on the
    design's precomputed gains (a lost laser switches to that set's gains), the health window
    of every measurement, and the two carriers' views."""

    def __init__(self, design: JointDesign):
        self.d = design
        self.x = [0.0] * 6
        self.started = False
        self.set = 0
        self.outage = 0
        N = design.window
        self._N = N
        self._raw = [[0.0] * N for _ in JOINT_MEASUREMENTS]     # the innovations themselves
        self._rsum = [0.0] * 6
        #: Σ k ν_k over the window (k = 0 oldest … N−1): what the drift test needs besides the
        #: sums; kept by a running update only while the drift test runs (``_kept``), summed
        #: afresh over the window when it starts (the bias test's gate opens)
        self._rsum1 = [0.0] * 6
        self._kept = False
        self._quiet = False                      # _calm has nothing to undo
        self._ks = tuple(float(k) for k in range(N))
        self.lead = -1                           # the measurement the drift test names (-1: none)
        self._lead_key = -1                      # its group (both lateral lasers: 0) and for how long
        self._lead_n = 0
        self._nfull = 0                          # cycles of the window on all lasers
        self._i = self._n = 0
        self._N_inv = 1.0 / N
        self._ys_f, self._ys_r = _YawState(), _YawState()
        self.front = CarrierView(self, "front")
        self.rear = CarrierView(self, "rear")
        self._plan = _joint_plan(design)
        t = design.table
        self._fw = self._bw = None
        self._lo = self._hi = 0.0                # the current grid point's speeds (select: nothing to do)
        if t is not None:
            self._fw = tuple(_joint_plan(e) for e in t.forward)
            self._bw = tuple(_joint_plan(e) for e in t.backward)
            self._lref, self._ilr = math.log(t.v_ref), 1.0 / math.log(t.ratio)
            self._klo, self._khi = t.k_lo, t.k_hi

    def view(self, carrier: str) -> CarrierView:
        return self.front if carrier == "front" else self.rear

    def select(self, v: float) -> None:
        """The design of the grid speed nearest ``v`` (as :meth:`Observer.select`); nothing to
        compute while v stays strictly inside the current grid point's interval."""
        if self._lo < v < self._hi:
            return
        fw = self._fw
        if fw is None or v == 0.0 or v != v:
            return
        k = round((math.log(v if v > 0.0 else -v) - self._lref) * self._ilr)
        k = self._klo if k < self._klo else self._khi if k > self._khi else k
        p = (fw if v > 0.0 else self._bw)[k - self._klo]
        # the speeds that round to k (a hair inside: at the boundary itself the rounding decides)
        lo = 0.0 if k == self._klo else math.exp(self._lref + (k - 0.5) / self._ilr) * (1.0 + 1e-9)
        hi = math.inf if k == self._khi else math.exp(self._lref + (k + 0.5) / self._ilr) * (1.0 - 1e-9)
        self._lo, self._hi = (lo, hi) if v > 0.0 else (-hi, -lo)
        e = p[0]
        if e is not self.d:
            self.d = e
            self._plan = p
            self.front.d, self.rear.d = e.front, e.rear

    def reset(self) -> None:
        self.started = False
        for r in self._raw:
            for k in range(self._N):
                r[k] = 0.0
        for k in range(6):
            self._rsum[k] = self._rsum1[k] = 0.0
        f, r = self.front, self.rear
        f.T_lat = r.T_lat = f.T_psi = r.T_psi = f.T_dw = r.T_dw = 0.0
        self._kept = self._quiet = False
        self.lead = self._lead_key = -1
        self._lead_n = 0
        self._nfull = 0
        self._i = self._n = 0
        self.outage = 0
        self.set = 0
        self.front.window_full = self.rear.window_full = False

    def _start(self, b_f: float, b_r: float, ok_f: bool, ok_r: bool, psi_f: float, psi_r: float,
               u_f: float, u_r: float) -> None:
        """The first cycle: the estimate starts on the measurements."""
        self.started = True
        d, x = self.d, self.x
        (ff, fr), (rf, rr) = d.laser_rows
        zf, zr = b_f - d.b0, b_r - d.b0
        det = ff * rr - fr * rf
        if ok_f and ok_r:
            x[0], x[3] = (rr * zf - fr * zr) / det, (ff * zr - rf * zf) / det
        else:
            x[0] = x[3] = 0.0
        x[1], x[4] = psi_f, psi_r
        x[2] = x[5] = 0.0
        self._ys_f.start(psi_f, u_f)
        self._ys_r.start(psi_r, u_r)
        self.set = (0 if ok_f else 2) + (0 if ok_r else 1)
        f, r = self.front, self.rear
        f.started = r.started = True
        f.lat_used = 1.0 if ok_f else 0.0
        r.lat_used = 1.0 if ok_r else 0.0
        f.sigma_y, r.sigma_y = (t[0] for t in d.sigma_y[self.set])
        if self.lead < 0:
            f.lead = r.lead = None

    def step(self, b_f: float, b_r: float, ok_f: bool, ok_r: bool, psi_f: float, psi_r: float,
             dw_f: float, dw_r: float, u_f: float, u_r: float, F_f: float = 0.0, F_r: float = 0.0) -> None:
        """One cycle: the lateral lasers' readings (m; used only where ``ok_*``), each carrier's
        measured ψ and Δω, the currents held since the last cycle and the measured lateral
        forces (N, 0: none). Predict, correct, the health window and the views, in one pass on
        locals (the design's numbers resolved once per design: ``_joint_plan``)."""
        if not self.started:
            self._start(b_f, b_r, ok_f, ok_r, psi_f, psi_r, u_f, u_r)
            return
        d, model, Ks, W, invs, sigmas, ymf, ymr = self._plan
        (ff, fr, rf, rr, b0, A0, A1, A2, A3, A4, A5, A7, A8, A13, A14, A18, A19, A20, A21, A22, A23, A28, A29,
         A34, A35, B0, B1, B2, B4, B6, B7, B9, B11, F0, F1, F6, F7, c0, c1, c2, c3, c4, c5,
         gf0, gf1, gf2, gr0, gr1, gr2) = model
        x = self.x
        x0, x1, x2, x3, x4, x5 = x
        # the hysteresis and damping law of each carrier: known inputs from the estimate
        ef, er, kf, kr = u_f, u_r, 1.0, 1.0
        if ymf is not None:
            hf, kf = self._ys_f.inputs(ymf, x1, u_f)
            ef = u_f + hf
        if ymr is not None:
            hr, kr = self._ys_r.inputs(ymr, x4, u_r)
            er = u_r + hr
        # predict: the yaw rows depend on their own carrier's ψ, ψ̇ and u only (the design's
        # block structure, exact zeros elsewhere: JointDesign)
        p0 = (A0 * x0 + A1 * x1 + A2 * x2 + A3 * x3 + A4 * x4 + A5 * x5
              + B0 * ef + B1 * er + F0 * F_f + F1 * F_r + c0)
        p1 = A7 * x1 + A8 * x2 + B2 * ef + c1
        p2 = (A13 * x1 + A14 * x2 + B4 * ef + c2) * kf
        p3 = (A18 * x0 + A19 * x1 + A20 * x2 + A21 * x3 + A22 * x4 + A23 * x5
              + B6 * ef + B7 * er + F6 * F_f + F7 * F_r + c3)
        p4 = A28 * x4 + A29 * x5 + B9 * er + c4
        p5 = (A34 * x4 + A35 * x5 + B11 * er + c5) * kr
        s = (0 if ok_f else 2) + (0 if ok_r else 1)
        n0 = (b_f - b0) - (ff * p0 + fr * p3) if ok_f else 0.0
        n1 = (b_r - b0) - (rf * p0 + rr * p3) if ok_r else 0.0
        n2 = psi_f - p1
        n3 = psi_r - p4
        n4 = dw_f - (gf0 * p0 + gf1 * p2 + gf2 * u_f)
        n5 = dw_r - (gr0 * p3 + gr1 * p5 + gr2 * u_r)
        (k0, k1, k2, k3, k4, k5,
         k6, k7, k8, k9, k10, k11,
         k12, k13, k14, k15, k16, k17,
         k18, k19, k20, k21, k22, k23,
         k24, k25, k26, k27, k28, k29,
         k30, k31, k32, k33, k34, k35) = Ks[s]
        x[0] = p0 + k0 * n0 + k1 * n1 + k2 * n2 + k3 * n3 + k4 * n4 + k5 * n5
        x[1] = p1 + k6 * n0 + k7 * n1 + k8 * n2 + k9 * n3 + k10 * n4 + k11 * n5
        x[2] = p2 + k12 * n0 + k13 * n1 + k14 * n2 + k15 * n3 + k16 * n4 + k17 * n5
        x[3] = p3 + k18 * n0 + k19 * n1 + k20 * n2 + k21 * n3 + k22 * n4 + k23 * n5
        x[4] = p4 + k24 * n0 + k25 * n1 + k26 * n2 + k27 * n3 + k28 * n4 + k29 * n5
        x[5] = p5 + k30 * n0 + k31 * n1 + k32 * n2 + k33 * n3 + k34 * n4 + k35 * n5
        self.set = s
        k = self.outage = 0 if s == 0 else self.outage + 1
        # the health window: the sums over the last N innovations of each measurement
        i, N = self._i, self._N
        q0, q1, q2, q3, q4, q5 = self._raw
        o0, o1, o2, o3, o4, o5 = q0[i], q1[i], q2[i], q3[i], q4[i], q5[i]
        rs = self._rsum
        if self._kept:                          # the time-weighted sums: every sample's k drops by 1
            r1, m = self._rsum1, N - 1
            r1[0] += m * n0 - rs[0] + o0
            r1[1] += m * n1 - rs[1] + o1
            r1[2] += m * n2 - rs[2] + o2
            r1[3] += m * n3 - rs[3] + o3
            r1[4] += m * n4 - rs[4] + o4
            r1[5] += m * n5 - rs[5] + o5
        rs[0] = a0 = rs[0] + (n0 - o0)
        rs[1] = a1 = rs[1] + (n1 - o1)
        rs[2] = a2 = rs[2] + (n2 - o2)
        rs[3] = a3 = rs[3] + (n3 - o3)
        rs[4] = a4 = rs[4] + (n4 - o4)
        rs[5] = a5 = rs[5] + (n5 - o5)
        q0[i] = n0
        q1[i] = n1
        q2[i] = n2
        q3[i] = n3
        q4[i] = n4
        q5[i] = n5
        self._i = i + 1 if i + 1 < N else 0
        nfull = self._nfull = self._nfull + 1 if s == 0 else 0
        f, r = self.front, self.rear
        n = self._n
        if n < N:
            n = self._n = n + 1
            if n == N:
                f.window_full = r.window_full = True
        if n == N:
            invN = self._N_inv
            if nfull >= N and W:
                # the whole window on all lasers: the bias test of each measurement (it tells a
                # lateral laser from a yaw laser and from the encoders; b_f from b_r it cannot)
                (v0, v1, v2, v3, v4, v5,
                 v6, v7, v8, v9, v10, v11,
                 v12, v13, v14, v15, v16, v17,
                 v18, v19, v20, v21, v22, v23,
                 v24, v25, v26, v27, v28, v29,
                 v30, v31, v32, v33, v34, v35) = W
                w0 = v0 * a0 + v1 * a1 + v2 * a2 + v3 * a3 + v4 * a4 + v5 * a5
                w1 = v6 * a0 + v7 * a1 + v8 * a2 + v9 * a3 + v10 * a4 + v11 * a5
                w2 = v12 * a0 + v13 * a1 + v14 * a2 + v15 * a3 + v16 * a4 + v17 * a5
                w3 = v18 * a0 + v19 * a1 + v20 * a2 + v21 * a3 + v22 * a4 + v23 * a5
                w4 = v24 * a0 + v25 * a1 + v26 * a2 + v27 * a3 + v28 * a4 + v29 * a5
                w5 = v30 * a0 + v31 * a1 + v32 * a2 + v33 * a3 + v34 * a4 + v35 * a5
                f.T_lat = t0 = w0 * w0 * invN
                r.T_lat = t1 = w1 * w1 * invN
                f.T_psi = t2 = w2 * w2 * invN
                r.T_psi = t3 = w3 * w3 * invN
                f.T_dw = t4 = w4 * w4 * invN
                r.T_dw = t5 = w5 * w5 * invN
                if max(t0, t1, t2, t3, t4, t5) > DRIFT_GATE and d.drift:
                    self._drift(f, r)
                elif not self._quiet:            # nothing found (and nothing to undo once quiet)
                    self._calm(f, r)
            else:                                # a laser out: each measurement's own statistic
                i0, i1, i2, i3, i4, i5 = invs[s]    # (normalised by this set's variances)
                a0, a1, a2, a3, a4, a5 = a0 * i0, a1 * i1, a2 * i2, a3 * i3, a4 * i4, a5 * i5
                f.T_lat, r.T_lat = a0 * a0 * invN, a1 * a1 * invN
                f.T_psi, r.T_psi = a2 * a2 * invN, a3 * a3 * invN
                f.T_dw, r.T_dw = a4 * a4 * invN, a5 * a5 * invN
                self._calm(f, r)
                self._quiet = False
                f.lead = r.lead = None
        f.lat_used = 1.0 if ok_f else 0.0
        r.lat_used = 1.0 if ok_r else 0.0
        tf, tr = sigmas[s]
        if k:
            f.sigma_y = tf[k] if k < len(tf) else tf[-1]
            r.sigma_y = tr[k] if k < len(tr) else tr[-1]
        else:
            f.sigma_y, r.sigma_y = tf[0], tr[0]

    def _calm(self, f: CarrierView, r: CarrierView) -> None:
        """The bias test names nothing: the drift test's state dropped, the views' lead "" (the
        bias test decides, and names nothing)."""
        self._kept = False
        self.lead = self._lead_key = -1
        self._lead_n = 0
        f.lead = r.lead = ""
        self._quiet = True

    def _drift(self, f: CarrierView, r: CarrierView) -> None:
        """The bias test passed its gate: the drift test's statistics published instead, and
        the measurement they name (once the same one has led for ``LEAD_CONFIRM`` cycles)."""
        if not self._kept:                       # the time-weighted sums, over the window as stored
            i, ks, r1 = self._i, self._ks, self._rsum1
            for j, q in enumerate(self._raw):
                r1[j] = sum(map(operator.mul, q[i:] + q[:i], ks))
            self._kept = True
        self._quiet = False
        T = self._drift_test()
        f.T_lat, r.T_lat, f.T_psi, r.T_psi, f.T_dw, r.T_dw = T
        j = T.index(max(T))
        key = 0 if j < 2 else j                  # counted only past the gate, where something is found
        if key == self._lead_key:
            self._lead_n += 1
        else:
            self._lead_key, self._lead_n = key, 1
        self.lead = j
        if self._lead_n < LEAD_CONFIRM:
            f.lead = r.lead = ""                  # not yet confirmed: no carrier's rule names it
        else:
            car, kind = JOINT_LEAD[j]
            f.lead, r.lead = (kind, "") if car == "front" else ("", kind)

    @property
    def nu(self) -> list[float]:
        """The latest innovation of each measurement (``JOINT_MEASUREMENTS`` order; 0 for a laser
        not used): the window's newest samples."""
        i = self._i - 1
        return [q[i] for q in self._raw]

    @property
    def T(self) -> list[float]:
        """The published statistic of each measurement (``JOINT_MEASUREMENTS`` order)."""
        f, r = self.front, self.rear
        return [f.T_lat, r.T_lat, f.T_psi, r.T_psi, f.T_dw, r.T_dw]

    def _drift_test(self) -> list[float]:
        """The drift test's statistic of every measurement (``JointDesign.drift``): a bias that
        grows over the window, as a drifting laser's does, is named by the measurement whose
        drift explains the innovations best (the bias test cannot tell a lateral laser's ramp
        from a yaw pair's bias: its lag term)."""
        D, s0, s1 = self.d.drift, self._rsum, self._rsum1
        a0, a1, a2, a3, a4, a5 = s0
        b0, b1, b2, b3, b4, b5 = s1
        T = [0.0] * 6
        for j in range(6):
            o = 15 * j
            u0, u1, u2, u3, u4, u5, l0, l1, l2, l3, l4, l5, i11, i12, i22 = D[o:o + 15]
            z1 = u0 * a0 + u1 * a1 + u2 * a2 + u3 * a3 + u4 * a4 + u5 * a5
            z2 = (u0 * b0 + u1 * b1 + u2 * b2 + u3 * b3 + u4 * b4 + u5 * b5
                  + l0 * a0 + l1 * a1 + l2 * a2 + l3 * a3 + l4 * a4 + l5 * a5)
            T[j] = i11 * z1 * z1 + 2.0 * i12 * z1 * z2 + i22 * z2 * z2
        return T


def make_observers(designs) -> dict:
    """The lanes' observers from their designs (carrier -> ObserverDesign or JointCarrier): an
    :class:`Observer` per carrier design, one :class:`JointObserver` shared by the carriers of a
    joint design (each lane gets its :class:`CarrierView`)."""
    out, joints = {}, {}
    for carrier, d in (designs or {}).items():
        if isinstance(d, JointCarrier):
            j = joints.get(id(d.joint))
            if j is None:
                j = joints[id(d.joint)] = JointObserver(d.joint)
            out[carrier] = j.view(carrier)
        elif isinstance(d, ObserverDesign):
            out[carrier] = Observer(d)
        else:
            out[carrier] = d                   # already built
    return out
