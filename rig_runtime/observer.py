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
from dataclasses import dataclass
from typing import Optional

from .damping import damping

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


def zmap(z: float, dpsi: float, A: float, beta: float, gamma: float) -> float:
    """The Bouc-Wen state (9) (n = 1) after a monotone change ``dpsi`` of ψ: dz/dψ = A − κ z,
    κ = β sign(dψ) + γ sign(z), exact, through at most one zero crossing of z (the plant's map,
    sim_backend/plant.py, written again for the estimate: the core does not import the
    simulator)."""
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


class _YawState:
    """The non-linearities' own state of one carrier: ẑ, the filter residual, the last current
    (and, once :meth:`bind` has been given the model, its constants as plain floats: the cycle
    reads them here instead of on the model)."""

    __slots__ = ("z", "e", "u", "acc", "_m", "_gain", "_ef", "_irm", "_kmin", "_c")

    def __init__(self) -> None:
        self.z = self.e = self.u = self.acc = 0.0
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

    def start(self, psi: float, u: float) -> None:
        self.z, self.e, self.u = psi, 0.0, u     # at rest: z = ψ (the plant's rest state), filter settled
        self.acc = 0.0

    def inputs(self, m: YawModel, psi: float, u: float) -> tuple[float, float]:
        """(the equivalent current of the hysteresis term, the yaw rate's extra decay) over the
        period ahead, with the current ``u`` held over it (advances the filter residual)."""
        if m is not self._m:
            self.bind(m)
        r = self.e + (u - self.u)
        self.u = u
        self.e = r * self._ef
        rho = (r if r >= 0.0 else -r) * self._irm
        if rho >= 1.0:
            return self._gain * (psi - self.z), self._kmin
        x = self._c * (damping(rho, self._m.D_min, self._m.D_max) - self._m.D0)
        return self._gain * (psi - self.z), (math.exp(-x) if x < 40.0 else 0.0)

    def follow(self, m: YawModel, dpsi: float) -> None:
        """ẑ after the estimate's change of ψ over the period."""
        if m.gain != 0.0:
            a = self.acc + dpsi
            if a >= m.dead or -a >= m.dead:
                self.z = zmap(self.z, a, m.A, m.beta, m.gamma)
                a = 0.0
            self.acc = a


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
        if ym is not None:
            self._ys.follow(ym, self.psi - p)
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
    of an :class:`Observer` (the joint filter writes them every step)."""

    __slots__ = ("joint", "carrier", "d", "y", "psi", "rate", "nu_lat", "nu_psi", "nu_dw", "T_lat", "T_psi",
                 "T_dw", "lat_used", "mean_lat", "mean_dw", "degraded", "outage", "sigma_y", "window_full",
                 "started", "lead")

    def __init__(self, joint: "JointObserver", carrier: str):
        self.joint = joint
        self.carrier = carrier
        self.d = joint.d.part(carrier)
        self.y = self.psi = self.rate = 0.0
        self.nu_lat = self.nu_psi = self.nu_dw = 0.0
        self.T_lat = self.T_psi = self.T_dw = 0.0
        self.mean_lat = self.mean_dw = 0.0
        self.lat_used = 0.0
        self.degraded = 0.0
        self.outage = 0
        self.sigma_y = 0.0
        self.window_full = False
        self.started = False
        #: the kind ("lat", "psi", "dw") of this carrier's measurement whose fault explains the
        #: joint filter's innovations best, "" when it is the other carrier's, None: not decided
        #: (a laser out: each statistic on its own; the rules then judge in their order)
        self.lead: Optional[str] = None

    def select(self, v: float) -> None:
        self.joint.select(v)

    def reset(self) -> None:
        self.joint.reset()

    def log_values(self) -> tuple[float, ...]:
        return (self.y, self.psi, self.rate, self.nu_lat, self.nu_psi, self.nu_dw,
                self.T_lat, self.T_psi, self.T_dw, self.lat_used, self.degraded, self.sigma_y)


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
        self._rsum1 = [0.0] * 6                  # Σ k ν_k over the window (k = 0 oldest … N−1)
        self.lead = -1                           # the measurement the drift/bias test names (-1: none)
        self._lead_key = -1                      # its group (both lateral lasers: 0) and for how long
        self._lead_n = 0
        self._nfull = 0                          # cycles of the window on all lasers
        self._i = self._n = 0
        self.T = [0.0] * 6
        self.nu = [0.0] * 6
        self._inv = tuple(tuple(1.0 / math.sqrt(s) for s in S) for S in design.S)
        self._ys_f, self._ys_r = _YawState(), _YawState()
        self.front = CarrierView(self, "front")
        self.rear = CarrierView(self, "rear")
        t = design.table
        self._fw = self._bw = None
        if t is not None:
            self._fw = t.forward
            self._bw = t.backward
            self._invs = {id(e): tuple(tuple(1.0 / math.sqrt(s) for s in S) for S in e.S) for e in t.forward + t.backward}
            self._lref, self._ilr = math.log(t.v_ref), 1.0 / math.log(t.ratio)
            self._klo, self._khi = t.k_lo, t.k_hi

    def view(self, carrier: str) -> CarrierView:
        return self.front if carrier == "front" else self.rear

    def select(self, v: float) -> None:
        """The design of the grid speed nearest ``v`` (as :meth:`Observer.select`)."""
        fw = self._fw
        if fw is None or v == 0.0 or v != v:
            return
        k = round((math.log(v if v > 0.0 else -v) - self._lref) * self._ilr)
        k = self._klo if k < self._klo else self._khi if k > self._khi else k
        e = (fw if v > 0.0 else self._bw)[k - self._klo]
        if e is not self.d:
            self.d = e
            self._inv = self._invs[id(e)]
            self.front.d, self.rear.d = e.front, e.rear

    def reset(self) -> None:
        self.started = False
        for r in self._raw:
            for k in range(self._N):
                r[k] = 0.0
        for k in range(6):
            self._rsum[k] = self._rsum1[k] = self.T[k] = 0.0
        self.lead = self._lead_key = -1
        self._lead_n = 0
        self._nfull = 0
        self._i = self._n = 0
        self.outage = 0
        self.set = 0

    def step(self, b_f: float, b_r: float, ok_f: bool, ok_r: bool, psi_f: float, psi_r: float,
             dw_f: float, dw_r: float, u_f: float, u_r: float, F_f: float = 0.0, F_r: float = 0.0) -> None:
        """One cycle: the lateral lasers' readings (m; used only where ``ok_*``), each carrier's
        measured ψ and Δω, the currents held since the last cycle and the measured lateral
        forces (N, 0: none)."""
        d = self.d
        (ff, fr), (rf, rr) = d.laser_rows
        zf, zr = b_f - d.b0, b_r - d.b0
        x = self.x
        if not self.started:                    # first cycle: start on the measurements
            self.started = True
            det = ff * rr - fr * rf
            if ok_f and ok_r:
                x[0], x[3] = (rr * zf - fr * zr) / det, (ff * zr - rf * zf) / det
            else:
                x[0] = x[3] = 0.0
            x[1], x[4] = psi_f, psi_r
            x[2] = x[5] = 0.0
            self._ys_f.start(psi_f, u_f)
            self._ys_r.start(psi_r, u_r)
            f, r = self.front, self.rear
            f.started = r.started = True
            self._publish(ok_f, ok_r)
            return
        A, Bu, BF, c = d.A, d.Bu, d.BF, d.c
        x0, x1, x2, x3, x4, x5 = x
        # the hysteresis and damping law of each carrier: known inputs from the estimate
        ymf, ymr = d.front.yaw, d.rear.yaw
        ef, er, kf, kr = u_f, u_r, 1.0, 1.0
        if ymf is not None:
            hf, kf = self._ys_f.inputs(ymf, x1, u_f)
            ef = u_f + hf
        if ymr is not None:
            hr, kr = self._ys_r.inputs(ymr, x4, u_r)
            er = u_r + hr
        # predict: the yaw rows depend on their own carrier's ψ, ψ̇ and u only (the design's
        # block structure, exact zeros elsewhere: JointDesign)
        p0 = (A[0] * x0 + A[1] * x1 + A[2] * x2 + A[3] * x3 + A[4] * x4 + A[5] * x5
              + Bu[0] * ef + Bu[1] * er + BF[0] * F_f + BF[1] * F_r + c[0])
        p1 = A[7] * x1 + A[8] * x2 + Bu[2] * ef + c[1]
        p2 = (A[13] * x1 + A[14] * x2 + Bu[4] * ef + c[2]) * kf
        p3 = (A[18] * x0 + A[19] * x1 + A[20] * x2 + A[21] * x3 + A[22] * x4 + A[23] * x5
              + Bu[6] * ef + Bu[7] * er + BF[6] * F_f + BF[7] * F_r + c[3])
        p4 = A[28] * x4 + A[29] * x5 + Bu[9] * er + c[4]
        p5 = (A[34] * x4 + A[35] * x5 + Bu[11] * er + c[5]) * kr
        gf, gr = d.front.dw_row, d.rear.dw_row
        s = (0 if ok_f else 2) + (0 if ok_r else 1)
        n0 = zf - (ff * p0 + fr * p3) if ok_f else 0.0
        n1 = zr - (rf * p0 + rr * p3) if ok_r else 0.0
        n2 = psi_f - p1
        n3 = psi_r - p4
        n4 = dw_f - (gf[0] * p0 + gf[1] * p2 + gf[2] * u_f)
        n5 = dw_r - (gr[0] * p3 + gr[1] * p5 + gr[2] * u_r)
        nu = self.nu
        nu[0], nu[1], nu[2], nu[3], nu[4], nu[5] = n0, n1, n2, n3, n4, n5
        K = d.K[s]
        x[0] = p0 + K[0] * n0 + K[1] * n1 + K[2] * n2 + K[3] * n3 + K[4] * n4 + K[5] * n5
        x[1] = p1 + K[6] * n0 + K[7] * n1 + K[8] * n2 + K[9] * n3 + K[10] * n4 + K[11] * n5
        x[2] = p2 + K[12] * n0 + K[13] * n1 + K[14] * n2 + K[15] * n3 + K[16] * n4 + K[17] * n5
        x[3] = p3 + K[18] * n0 + K[19] * n1 + K[20] * n2 + K[21] * n3 + K[22] * n4 + K[23] * n5
        x[4] = p4 + K[24] * n0 + K[25] * n1 + K[26] * n2 + K[27] * n3 + K[28] * n4 + K[29] * n5
        x[5] = p5 + K[30] * n0 + K[31] * n1 + K[32] * n2 + K[33] * n3 + K[34] * n4 + K[35] * n5
        if ymf is not None:                     # ẑ follows ψ̂ past the dead band
            self._ys_f.follow(ymf, x[1] - x1)
        if ymr is not None:
            self._ys_r.follow(ymr, x[4] - x4)
        self.set = s
        self.outage = 0 if s == 0 else self.outage + 1
        self._window(s)
        self._publish(ok_f, ok_r)

    def _window(self, s: int) -> None:
        i, N, nu = self._i, self._N, self.nu
        rs, r1 = self._rsum, self._rsum1
        q0, q1, q2, q3, q4, q5 = self._raw
        # the time-weighted sums first (from the sums before this cycle): every sample's k drops by 1
        m = N - 1
        r1[0] += m * nu[0] - rs[0] + q0[i]
        r1[1] += m * nu[1] - rs[1] + q1[i]
        r1[2] += m * nu[2] - rs[2] + q2[i]
        r1[3] += m * nu[3] - rs[3] + q3[i]
        r1[4] += m * nu[4] - rs[4] + q4[i]
        r1[5] += m * nu[5] - rs[5] + q5[i]
        rs[0] += nu[0] - q0[i]
        rs[1] += nu[1] - q1[i]
        rs[2] += nu[2] - q2[i]
        rs[3] += nu[3] - q3[i]
        rs[4] += nu[4] - q4[i]
        rs[5] += nu[5] - q5[i]
        q0[i], q1[i], q2[i], q3[i], q4[i], q5[i] = nu
        self._nfull = self._nfull + 1 if s == 0 else 0
        self._i = i + 1 if i + 1 < N else 0
        if self._n < N:
            self._n += 1
        if self._n == N:
            invN = 1.0 / N
            T = self.T
            W = self.d.isolation
            if self._nfull >= N and W:
                # the whole window on all lasers: the bias test of each measurement (it tells a
                # lateral laser from a yaw laser and from the encoders; b_f from b_r it cannot)
                a0, a1, a2, a3, a4, a5 = rs
                w0 = W[0] * a0 + W[1] * a1 + W[2] * a2 + W[3] * a3 + W[4] * a4 + W[5] * a5
                w1 = W[6] * a0 + W[7] * a1 + W[8] * a2 + W[9] * a3 + W[10] * a4 + W[11] * a5
                w2 = W[12] * a0 + W[13] * a1 + W[14] * a2 + W[15] * a3 + W[16] * a4 + W[17] * a5
                w3 = W[18] * a0 + W[19] * a1 + W[20] * a2 + W[21] * a3 + W[22] * a4 + W[23] * a5
                w4 = W[24] * a0 + W[25] * a1 + W[26] * a2 + W[27] * a3 + W[28] * a4 + W[29] * a5
                w5 = W[30] * a0 + W[31] * a1 + W[32] * a2 + W[33] * a3 + W[34] * a4 + W[35] * a5
                T[0], T[1], T[2] = w0 * w0 * invN, w1 * w1 * invN, w2 * w2 * invN
                T[3], T[4], T[5] = w3 * w3 * invN, w4 * w4 * invN, w5 * w5 * invN
                mx = max(T)
                j = T.index(mx)
                if mx > DRIFT_GATE and self.d.drift:
                    self._drift_test(T)
                    mx = max(T)
                    j = T.index(mx)
                    key = 0 if j < 2 else j        # counted only past the gate, where something is found
                    if key == self._lead_key:
                        self._lead_n += 1
                    else:
                        self._lead_key, self._lead_n = key, 1
                else:
                    self._lead_key, self._lead_n = -1, 0
                self.lead = j
            else:                                # a laser out: each measurement's own statistic
                inv = self._inv[s]                   # (normalised by this set's variances)
                for j in range(6):
                    z = rs[j] * inv[j]
                    T[j] = z * z * invN
                self.lead = self._lead_key = -1
                self._lead_n = 0

    def _drift_test(self, T: list) -> None:
        """The drift test of every measurement (``JointDesign.drift``) into ``T``: a bias that
        grows over the window, as a drifting laser's does, is named by the measurement whose
        drift explains the innovations best (the bias test cannot tell a lateral laser's ramp
        from a yaw pair's bias: its lag term)."""
        D, s0, s1 = self.d.drift, self._rsum, self._rsum1
        a0, a1, a2, a3, a4, a5 = s0
        b0, b1, b2, b3, b4, b5 = s1
        for j in range(6):
            o = 15 * j
            u0, u1, u2, u3, u4, u5, l0, l1, l2, l3, l4, l5, i11, i12, i22 = D[o:o + 15]
            z1 = u0 * a0 + u1 * a1 + u2 * a2 + u3 * a3 + u4 * a4 + u5 * a5
            z2 = (u0 * b0 + u1 * b1 + u2 * b2 + u3 * b3 + u4 * b4 + u5 * b5
                  + l0 * a0 + l1 * a1 + l2 * a2 + l3 * a3 + l4 * a4 + l5 * a5)
            T[j] = i11 * z1 * z1 + 2.0 * i12 * z1 * z2 + i22 * z2 * z2

    def _publish(self, ok_f: bool, ok_r: bool) -> None:
        """Write each carrier's view (its own laser's statistic as its lateral one; the window
        means only once the window is full, where the supervisor reads them)."""
        x, T, nu, d, k = self.x, self.T, self.nu, self.d, self.outage
        full = self._n == self._N
        sig = d.sigma_y[self.set]
        f, r = self.front, self.rear
        f.y, f.psi, f.rate, r.y, r.psi, r.rate = x
        f.nu_lat = nu[0] if ok_f else math.nan
        r.nu_lat = nu[1] if ok_r else math.nan
        f.nu_psi, r.nu_psi, f.nu_dw, r.nu_dw = nu[2], nu[3], nu[4], nu[5]
        f.T_lat, r.T_lat, f.T_psi, r.T_psi, f.T_dw, r.T_dw = T
        j = self.lead
        if j < 0:
            f.lead = r.lead = None
        elif self._lead_n < LEAD_CONFIRM:
            f.lead = r.lead = ""                  # not yet confirmed: no carrier's rule names it
        else:
            car, kind = JOINT_LEAD[j]
            f.lead, r.lead = (kind, "") if car == "front" else ("", kind)
        f.lat_used = 1.0 if ok_f else 0.0
        r.lat_used = 1.0 if ok_r else 0.0
        f.outage = r.outage = k
        tf, tr = sig
        f.sigma_y = tf[k] if k < len(tf) else tf[-1]
        r.sigma_y = tr[k] if k < len(tr) else tr[-1]
        if full:
            rs, invN = self._rsum, 1.0 / self._N
            f.window_full = r.window_full = True
            f.mean_lat, r.mean_lat = rs[0] * invN, rs[1] * invN     # the window means (m, rad/s)
            f.mean_dw, r.mean_dw = rs[4] * invN, rs[5] * invN
        else:
            f.window_full = r.window_full = False


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
