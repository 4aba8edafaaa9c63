"""Typed, frozen configuration of the rig, validated before anything runs.

A config file is YAML with top-level sections; ``include:`` lists further files (relative
to the including file) whose sections are merged in. Each section is validated against
the dataclasses below; every error names the file, the key path and what was expected.

Units are SI (m, rad, s, A) unless a key says otherwise (``*_mm``, ``*_hz``, ``*_ms``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Optional

from . import schema
from .ceilings import HardwareDescription
from .ceilings import check as check_ceilings
from .errors import ConfigError
from .memo import across_processes
from .schema import check, nonneg, positive, unit_interval

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
DEFAULT_CONFIG = CONFIG_DIR / "sim.yaml"

LASER_ROLES = ("b_f", "b_r", "s_fl", "s_fr", "s_rl", "s_rr")
WHEELS = ("fl", "fr", "rl", "rr")


# --------------------------------------------------------------------------- geometry
@dataclass(frozen=True, kw_only=True)
class Geometry:
    """Sensor geometry of Sec. 2 (Fig. 2). Lengths in m."""

    b0: float = check(positive)       # nominal laser-to-plate distance when centred
    l_L: float = check(positive)      # spacing of the two lateral lasers along the track
    l0: float = check(positive)       # frame centre to front/rear wheel carrier
    d0: float = check(positive)       # spacing of the left/right yaw lasers


# --------------------------------------------------------------------------- plant
@dataclass(frozen=True, kw_only=True)
class BoucWen:
    a: float = check(unit_interval)   # a_Bouc, ratio of post- to pre-yield stiffness
    A: float = 1.0
    beta: float = check(positive)
    gamma: float = 0.0
    n: int = check(positive, default=1)


@dataclass(frozen=True, kw_only=True)
class CarrierPlant:
    """One carrier's own values of the plant parameters (``plant.front:`` / ``plant.rear:``):
    each key given here replaces the common value for that carrier; a key left out keeps it.
    The carriers are identified separately (Sec. 4.1.1) and may differ ("varying open-loop
    stability"); the speed and the contact set-up are the rig's, not a carrier's."""

    b: Optional[float] = check(positive, default=None)
    r0: Optional[float] = check(positive, default=None)
    delta0: Optional[float] = check(positive, default=None)
    l0: Optional[float] = check(positive, default=None)
    y_off: Optional[float] = None
    c11: Optional[float] = check(positive, default=None)
    J_x: Optional[float] = check(positive, default=None)
    k_tau: Optional[float] = check(positive, default=None)
    omega0: Optional[float] = check(positive, default=None)
    K: Optional[float] = check(positive, default=None)
    D_min: Optional[float] = check(positive, default=None)
    D_max: Optional[float] = check(positive, default=None)
    c_udot_max: Optional[float] = check(positive, default=None)
    u_filter_hz: Optional[float] = check(positive, default=None)
    psi_off: Optional[float] = None
    bouc_wen: Optional[BoucWen] = None

    def overrides(self) -> dict[str, Any]:
        """The keys this carrier sets (name → value)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}


CARRIERS = ("front", "rear")


@dataclass(frozen=True, kw_only=True)
class Plant:
    """Plant parameters (Sec. 4; Table 3, Table 1 quantities as estimates): the common values,
    with per-carrier overrides in ``front`` / ``rear`` (``carrier(name)`` resolves them)."""

    v: float                                  # roller surface speed, m/s (sign = direction)
    b: float = check(positive)                # track width (contact-point spacing), m
    r0: float = check(positive)               # wheel radius, m
    delta0: float = check(positive)           # equivalent conicity angle, rad
    l0: float = check(positive)               # frame centre to wheel carrier, m
    y_off: float = 0.0                        # lateral offset, m (Sec. 4.1.2)
    c11: float = check(positive)              # extended Kalker coefficient c̄11, N
    J_x: float = check(positive)              # wheel rolling inertia, kg m^2
    k_tau: float = check(positive)            # motor constant, N m / A
    omega0: float = check(positive)           # yaw natural frequency, rad/s
    K: float = check(positive)                # yaw static gain, rad / A
    D_min: float = check(positive)            # damping for fast input changes
    D_max: float = check(positive)            # damping for slow input changes
    c_udot_max: float = check(positive)       # |du/dt| at which D reaches D_min, A/s
    u_filter_hz: float = check(positive, default=10.0)  # low pass used for du/dt in (7)
    psi_off: float = 0.0                      # yaw offset, rad
    bouc_wen: Optional[BoucWen] = None        # hysteresis (8)/(9); None = linear
    front_contact: bool = False               # front carrier on the rollers (else lifted, y_f = 0)
    rear_contact: bool = True                 # rear carrier on the rollers (false: the mirrored set-up, y_r = 0)
    front: Optional[CarrierPlant] = None      # the front carrier's own values (None: the common ones)
    rear: Optional[CarrierPlant] = None       # the rear carrier's own values

    def __post_init__(self) -> None:
        if self.D_max < self.D_min:
            raise ConfigError(None, "D_max", f"a damping >= D_min ({self.D_min})", self.D_max)
        if not self.delta0 < math.pi / 4:
            raise ConfigError(None, "delta0", "a conicity angle below pi/4 rad", self.delta0)
        for name in CARRIERS:
            own = getattr(self, name)
            if own is None:
                continue
            try:
                self.carrier(name)
            except ConfigError as e:
                raise ConfigError(None, f"{name}.{e.key_path}", e.expected, e.got) from None

    def carrier(self, name: str) -> "Plant":
        """The parameters of carrier ``name`` ("front" / "rear"): the common values with that
        carrier's overrides applied (a Plant without overrides of its own)."""
        if name not in CARRIERS:
            raise ValueError(f"carrier: expected 'front' or 'rear', got {name!r}")
        own = getattr(self, name)
        return dataclasses.replace(self, front=None, rear=None, **(own.overrides() if own else {}))

    @property
    def in_contact(self) -> tuple[str, ...]:
        """The carriers on the rollers by the config (``front_contact``, ``rear_contact``)."""
        return tuple(c for c, on in (("front", self.front_contact), ("rear", self.rear_contact)) if on)

    @property
    def per_carrier(self) -> bool:
        """Whether a carrier has values of its own."""
        return self.front is not None or self.rear is not None

    @property
    def c_y(self) -> float:
        """c̄_y of Sec. 4.1.1 (wheel non-flatness factor)."""
        d, r0, b = self.delta0, self.r0, self.b
        return (2 * r0 * math.cos(d) ** 3 - 2 * r0 * math.cos(d) + b * math.cos(d) ** 2 * math.sin(d)) / (b * math.sin(d))

    @property
    def Gamma(self) -> float:
        """Γ of Sec. 4.2 (geometric parameter of the rolling-radius difference)."""
        t = math.tan(self.delta0)
        return t / (self.b / 2 - self.r0 * t)

    @property
    def a_lat(self) -> float:
        """Lateral pole c̄_y v / (2 l0) of (2b)/(10), 1/s."""
        return self.c_y * self.v / (2 * self.l0)


# --------------------------------------------------------------------------- controller
@dataclass(frozen=True, kw_only=True)
class PIPDGains:
    K_P_y: float          # outer PI, rad/m
    K_I_y: float          # rad/(m s)
    K_P_psi: float        # inner PD, A/rad
    K_D_psi: float        # A s/rad
    T_f_psi: float = check(positive)   # differentiator time constant, s
    D_sched: float = check(nonneg, default=0.0)  # the yaw loop scheduled on D̂ of (7) (control.PIPDLaw): K_P,ψ's raise, in units of the one that keeps the slow pole; 0 off


@dataclass(frozen=True, kw_only=True)
class DecoupledGains(PIPDGains):
    """The decoupled PI-PD of the vehicle (``law: decoupled``, docs/vehicle.md §5): the PI-PD's
    gains, a setpoint weight on the outer P term and the gain of the cross-carrier decoupling."""

    b_y: float = check(unit_interval, default=1.0)        # setpoint weight: ψ_ref's P term is K_P,y (b y_ref − y)
    K_x_y: float = check(nonneg, default=0.0)       # rad/m: ψ_ref − K_x,y (y_f − y_r) (1/(2 l0) cancels (2a)/(2b)'s coupling)
    K_I_psi: float = check(nonneg, default=0.0)     # A/(rad s): the yaw loop's integral term
    T_x_y: float = check(nonneg, default=0.0)       # s: the decoupling term's lead (on d/dt (y_f − y_r), filtered by T_f_psi)
    K_t_y: float = check(nonneg, default=0.0)       # rad/m: the trailing carrier's ψ_ref + K_t,y |g| (y_f − y_r) (it follows the leader)


PIPD_GAINS = ("K_P_y", "K_I_y", "K_P_psi", "K_D_psi", "T_f_psi")   # the PI-PD law's gains (PIPDGains)
DECOUPLED_GAINS = PIPD_GAINS + ("b_y", "K_x_y", "K_I_psi", "T_x_y", "K_t_y", "D_sched")                   # the decoupled law's (DecoupledGains)
P_GAINS = ("K_P",)                                                  # the P law's (Controller.K_P)
TUNABLE_GAINS = DECOUPLED_GAINS + P_GAINS                           # what `rig ctl set` may change


@dataclass(frozen=True, kw_only=True)
class Schedule:
    """Gain scheduling on the measured speed (docs/vehicle.md). The outer PI's gains are scaled
    by ``v_design / v̂`` (sign included), so that the lateral input gain c̄_y v times the gain
    stays what the gains were designed for at ``v_design``; the inner PD is not scheduled (the
    yaw dynamics (6) are taken as speed independent). Below ``v_min`` in |v̂| the lateral loop
    holds: the integrator is frozen and ψ_ref goes to 0 over ``hold_ramp_s``; it resumes
    bumplessly above. ``v_range`` is the speed range the analysis and the stability gate cover."""

    v_design: Optional[float] = None                # m/s the gains were designed for (None: plant.v)
    v_min: float = check(positive, default=0.2)     # m/s, ESTIMATE: the standstill band |v̂| < v_min
    v_range: tuple[float, float]                    # m/s [lo, hi] the rig runs at (both signs allowed)
    hold_ramp_s: float = check(positive, default=1.0)   # s, ψ_ref to 0 on entering the band
    v_filter_hz: float = check(positive, default=2.0)   # Hz, low-pass of the measured speed

    def __post_init__(self) -> None:
        lo, hi = self.v_range
        if not lo < hi:
            raise ConfigError(None, "v_range", "[lo, hi] with lo < hi (m/s)", list(self.v_range))
        if self.v_design is not None and not abs(self.v_design) >= self.v_min:
            raise ConfigError(None, "v_design", f"a speed outside the standstill band (|v| >= v_min = "
                              f"{self.v_min:g} m/s)", self.v_design)


@dataclass(frozen=True, kw_only=True)
class Controller:
    h: float = check(positive)                      # sample time, s
    law: Literal["pipd", "p", "decoupled"] = "pipd"
    pipd: PIPDGains = field(default=None)  # type: ignore[assignment]
    decoupled: Optional[DecoupledGains] = None      # the gains of law decoupled (both carriers)
    front: Optional[PIPDGains] = None               # the front carrier's own gains (None: pipd)
    rear: Optional[PIPDGains] = None                # the rear carrier's own gains (None: pipd)
    schedule: Optional[Schedule] = None             # None: fixed gains (the paper's set-up, v fixed)
    K_P: float = 500.0                              # P baseline (Sec. 5.1), A/m
    discretization: Literal["tustin", "zoh"] = "tustin"
    # live tuning (`rig ctl set`): [lo, hi] per gain; a gain without bounds is not tunable. The
    # configured gain itself need not lie inside (the bounds are what an operator may set live).
    tuning: dict[str, tuple[float, float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.pipd is None:
            raise ConfigError(None, "pipd", "a mapping (missing key)")
        if self.law == "decoupled" and self.decoupled is None:
            raise ConfigError(None, "decoupled", "the gains of law decoupled (missing key)")
        if self.law == "decoupled" and (self.front is not None or self.rear is not None):
            raise ConfigError(None, "front" if self.front is not None else "rear",
                              "no per-carrier gains with law decoupled (one set, controller.decoupled)")
        for name, (lo, hi) in self.tuning.items():
            key = f"tuning.{name}"
            if name not in TUNABLE_GAINS:
                raise ConfigError(None, key, "a tunable gain (one of " + ", ".join(TUNABLE_GAINS) + ")")
            if not 0 < lo <= hi:
                raise ConfigError(None, key, "bounds [lo, hi] with 0 < lo <= hi", [lo, hi])

    def gains(self, carrier: str) -> PIPDGains:
        """The PI-PD gains of carrier ``carrier`` (its own, else the common ``pipd``)."""
        if carrier not in CARRIERS:
            raise ValueError(f"carrier: expected 'front' or 'rear', got {carrier!r}")
        return getattr(self, carrier) or self.pipd


# --------------------------------------------------------------------------- limits / safety
@dataclass(frozen=True, kw_only=True)
class Limits:
    """Table 2 as far as the text gives it, plus the supervisor's own bounds."""

    u_max: float = check(positive)                  # |Δu| and |current on the wire|, A
    psi_max: float = check(positive)                # |ψ|, rad
    psi_ref_max: Optional[float] = check(positive, default=None)    # |ψ_ref| the outer PI may ask for, rad (None: unclipped)
    y_max: float = check(positive)                  # |y|, m
    psi_rate_max: Optional[float] = check(positive, default=None)   # |ψ̇|, rad/s
    du_max: float = check(positive, default=200.0)  # command rate limit, A/s
    stale_periods: int = check(positive, default=4)     # laser: no valid value for this many h; drive: this many SYNCs unanswered -> stale
    ft_stale_s: float = check(positive, default=0.5)    # F/T: no sample for this long -> stale (they poll at their own rate)
    overrun_burst: int = check(positive, default=5)     # consecutive deadline misses -> fault
    stop_ramp_s: float = check(nonneg, default=0.5)     # STOPPING ramp to zero
    stuck_periods: Optional[int] = check(positive, default=200)  # bit-identical samples -> stuck
    laser_step_max: Optional[float] = check(positive, default=0.002)  # m per period -> implausible jump
    corrupt_cycles: Optional[int] = check(positive, default=20)   # garbled frames in this many cycles in a row -> link fault
    innovation_chi2: Optional[float] = check(positive, default=None)  # observer: χ²(1) of a measurement's window-mean
                                                    # normalised innovation above this -> the sensor disagrees (None: off)
    innovation_window: int = check(positive, default=200)   # cycles in that window
    v_disagree_max: float = check(positive, default=0.05)   # m/s: carriers in contact whose encoders'
                                                    # speeds differ by more -> the encoders disagree about v (ESTIMATE)

    def __post_init__(self) -> None:
        if self.psi_ref_max is not None and self.psi_ref_max > self.psi_max:
            raise ConfigError(None, "psi_ref_max", f"at most psi_max ({self.psi_max:g} rad)", self.psi_ref_max)


@dataclass(frozen=True, kw_only=True)
class TuningCriteria:
    """Design checks of Sec. 5.2.3."""

    psi_design: float = 0.05          # rad
    psi_rate_design: float = 0.4      # rad/s
    u_design_max: float = 2.0         # A
    y_design: float = 0.008           # m
    psi_ref_design_max: float = 0.06  # rad
    slowest_eig_min: float = -1.5     # 1/s
    outer_lateral_form: Literal["eq17", "eq10"] = "eq17"
    D_values: tuple[float, ...] = (0.0, 0.1, 0.5, 1.0, 2.2, 6.0, 20.0, 100.0)


# --------------------------------------------------------------------------- observer
@dataclass(frozen=True, kw_only=True)
class ObserverNoise:
    """Standard deviations of the sensors as the observer assumes them (per sample)."""

    lateral_laser_m: float = check(positive, default=1.0e-6)    # one lateral laser reading, m
    yaw_laser_m: float = check(positive, default=1.0e-6)        # one yaw laser reading, m
    encoder_rad_s: float = check(positive, default=0.002)       # one wheel speed, rad/s


@dataclass(frozen=True, kw_only=True)
class Observer:
    """The lateral-displacement observer of every controlled carrier (docs/observer.md):
    sensor noise, process noise (what the linear model leaves out) and the damping of (6)."""

    noise: ObserverNoise = field(default_factory=ObserverNoise)
    q_y: float = check(positive, default=1.0e-5)            # lateral velocity noise density (unmodelled forces), m/s per √Hz
    q_psi_acc: float = check(positive, default=2.0)         # yaw acceleration noise (hysteresis, damping), rad/s² per √Hz
    D: Optional[float] = check(positive, default=None)      # damping of (6) in the model (None: plant.D_min)
    yaw_model: bool = True   # the plant's hysteresis (9) and damping law (7) as a known nonlinear input (docs/observer.md)


@dataclass(frozen=True, kw_only=True)
class DegradedLimits:
    """The tighter limits a carrier runs under while it is controlled on the observer's ŷ
    (each capped at the corresponding ``limits:`` value: never looser)."""

    u_max: float = check(positive, default=2.0)          # A
    y_max: float = check(positive, default=0.004)        # m, judged on ŷ


@dataclass(frozen=True, kw_only=True)
class Degraded:
    """What a lost lateral laser does (docs/observer.md, "Degraded mode"): ``stop`` — the
    channel rule's fault, as without an observer; ``observe`` — the carriers whose y it
    feeds continue on their observer's ŷ under ``limits``, for at most ``max_s``; the laser
    is readmitted once it is fit and agrees with ŷ within ``readmit_tol_m`` for
    ``readmit_s``. The estimate's error σ (the design's outage covariance) beyond
    ``sigma_y_max`` ends the degraded run in the normal clean stop."""

    on_lateral_loss: Literal["observe", "stop"] = "stop"
    # a drive lost while RUNNING (docs/safety.md, "Drive outages"): ``reallocate`` — if the
    # outage analysis finds the reconfigured loop stable at the measured speed, the carrier runs
    # RECONFIGURED on its remaining wheel(s) under ``limits``; ``stop`` — the converter fault
    on_drive_loss: Literal["reallocate", "stop"] = "stop"
    # a drive without torque response (silent outage): its reported torque actual further than
    # torque_residual_A from every one of its latest commands, each at least that large, for
    # torque_hold_s (docs/safety.md, "Drive outages": set from healthy runs)
    torque_residual_A: float = check(positive, default=0.02)
    torque_hold_s: float = check(positive, default=0.05)
    max_s: float = check(positive, default=15.0)
    limits: DegradedLimits = field(default_factory=DegradedLimits)
    readmit_s: float = check(positive, default=1.0)
    readmit_tol_m: float = check(positive, default=0.1e-3)
    sigma_y_max: float = check(positive, default=0.1e-3)    # m, ESTIMATE (docs/observer.md)


# --------------------------------------------------------------------------- devices
@dataclass(frozen=True, kw_only=True)
class LaserDevice:
    role: Literal["b_f", "b_r", "s_fl", "s_fr", "s_rl", "s_rr"]
    driver: str = "optoncdt1420"                    # rig_runtime.registry name
    port: str                                       # serial port, or "sim" for the virtual device
    measuring_range_mm: float = check(positive)
    offset_mm: float = 0.0                          # distance from the reference to the start of range
    baudrate: int = check(positive, default=921600)
    output_rate_hz: float = check(positive, default=4000.0)
    average: bool = False                           # mean of this cycle's values instead of latest


@dataclass(frozen=True, kw_only=True)
class Drive:
    wheel: Literal["fl", "fr", "rl", "rr"]
    node_id: int = check(("a CANopen node id 1..127", lambda v: 1 <= v <= 127))
    rated_current_A: float = check(positive)
    velocity_factor: float = check(positive)        # rad/s per unit of 0x606C
    heartbeat_ms: int = check(positive, default=50)  # producer time of the drive


@dataclass(frozen=True, kw_only=True)
class CanBus:
    REMOVED_KEYS = {"tpdo_timeout_periods": "a drive's TPDO is judged now by limits.stale_periods, "
                    "as SYNCs left unanswered"}
    driver: str = "cia402"                          # rig_runtime.registry name
    interface: str = "virtual"                      # python-can interface name
    channel: str = "rig"
    bitrate: int = check(positive, default=1_000_000)
    eds: str = "irdw-drive.eds"                     # relative to configs/
    heartbeat_ms: int = check(positive, default=100)  # runtime's own producer time
    heartbeat_timeout_factor: float = check(positive, default=2.5)
    watchdog_ms: int = check(positive, default=50)  # drive cuts current without SYNC/RPDO
    drives: tuple[Drive, ...] = ()


@dataclass(frozen=True, kw_only=True)
class FTSensor:
    name: str
    transport: Literal["tcp", "rtu"] = "tcp"
    host: str = "127.0.0.1"
    port: int = 502                                 # TCP port
    serial_port: str = ""                           # RTU
    baudrate: int = check(positive, default=19200)
    unit_id: int = check(positive, default=9)


FT_POLLERS = ("process", "thread", "inline")       # where the F/T driver polls (drivers.ft300.POLLERS)


@dataclass(frozen=True, kw_only=True)
class FTBus:
    REMOVED_KEYS = {"stale_s": "the supervisor judges an F/T sample's age by limits.ft_stale_s"}
    driver: str = "robotiq_ft300"                   # rig_runtime.registry name
    poller: str = "process"                         # one of FT_POLLERS
    poll_hz: float = check(positive, default=50.0)
    timeout_s: float = check(positive, default=0.1)
    sensors: tuple[FTSensor, ...] = ()

    def __post_init__(self) -> None:
        if self.poller not in FT_POLLERS:
            raise ConfigError(None, "poller", "one of " + ", ".join(FT_POLLERS), self.poller)
        rtu = [s.name for s in self.sensors if s.transport == "rtu"]
        if self.poller == "inline" and rtu:
            raise ConfigError(None, "poller", "'process' or 'thread' with RTU sensors (" + ", ".join(rtu) +
                              "): 'inline' polls without blocking, which only the TCP link can", self.poller)


@dataclass(frozen=True, kw_only=True)
class Devices:
    lasers: tuple[LaserDevice, ...] = ()
    can: CanBus = field(default_factory=CanBus)
    ft: FTBus = field(default_factory=FTBus)

    def __post_init__(self) -> None:
        roles = [l.role for l in self.lasers]
        for r in set(roles):
            if roles.count(r) > 1:
                raise ConfigError(None, "lasers", f"each laser role once (duplicate {r})")
        wheels = [d.wheel for d in self.can.drives]
        ids = [d.node_id for d in self.can.drives]
        if len(set(wheels)) != len(wheels) or len(set(ids)) != len(ids):
            raise ConfigError(None, "can.drives", "distinct wheels and node ids")


# --------------------------------------------------------------------------- runtime
@dataclass(frozen=True, kw_only=True)
class Realtime:
    sched_fifo_priority: Optional[int] = None
    cpu_affinity: Optional[tuple[int, ...]] = None
    mlockall: bool = False
    spin_us: float = check(nonneg, default=200.0)   # sleep until this long before the deadline, then spin
    switch_interval_us: Optional[float] = check(positive, default=250.0)  # interpreter switch interval: bounds how
                                                    # long a helper thread (F/T polling, recorder) can hold the GIL


@dataclass(frozen=True, kw_only=True)
class Recorder:
    buffer_cycles: int = check(positive, default=4096)
    flush_s: float = check(positive, default=0.5)
    close_timeout_s: float = check(positive, default=3.0)   # shutdown: the wait for the log's close (issue 29)


@dataclass(frozen=True, kw_only=True)
class RigConfig:
    geometry: Geometry
    plant: Plant
    controller: Controller
    limits: Limits
    hardware: HardwareDescription                   # the machine's ceilings (ceilings.py; a file of its own)
    controlled: tuple[Literal["front", "rear"], ...] = ("rear",)
    tuning: TuningCriteria = field(default_factory=TuningCriteria)
    devices: Devices = field(default_factory=Devices)
    realtime: Realtime = field(default_factory=Realtime)
    recorder: Recorder = field(default_factory=Recorder)
    observer: Optional[Observer] = None             # None: no observer in the lanes
    degraded: Degraded = field(default_factory=Degraded)    # a lost lateral laser: stop (default) or observe
    sim: Optional[dict[str, Any]] = None            # validated by sim_backend
    source: str = ""                                # file it was loaded from (not a YAML key)

    def __post_init__(self) -> None:
        if not self.controlled:
            raise ConfigError(None, "controlled", "at least one of 'front', 'rear'")
        check_ceilings(self)     # every limit at most its hardware ceiling, however the object was made
        d = self.degraded
        if d.on_lateral_loss == "observe":
            if self.observer is None:
                raise ConfigError(None, "degraded.on_lateral_loss", "'stop' without an observer: section "
                                  "(a carrier can only continue on an estimate it has)", d.on_lateral_loss)
            # degraded.limits looser than limits: are capped at them (safety.Supervisor), never
            # an error — the shipped sim.yaml observes, and a config that tightens its limits
            # must not have to tighten degraded.limits too


_SECTION_FILES = ("geometry", "plant", "controller", "limits", "controlled", "tuning",
                  "devices", "realtime", "recorder", "observer", "degraded", "sim", "hardware")
HARDWARE_FILE = CONFIG_DIR / "hardware.yaml"

# Bounds of a YAML file: a config is a few kB; a "billion laughs" file of a few hundred
# bytes expands to 10^9 nodes through aliases. Both are refused before construction.
MAX_YAML_BYTES = 256 * 1024
MAX_YAML_DEPTH = 32                 # nesting levels of mappings and lists
MAX_YAML_NODES = 100_000            # nodes after alias expansion


class _TooBig(Exception):
    """A YAML document beyond the loader's bounds."""


@functools.lru_cache(maxsize=1)
def _loader_class():
    """The loader: safe_load, but ``1.0e5`` is a float (YAML 1.2 style), as engineers write
    it; nesting is bounded while composing (``MAX_YAML_DEPTH``). PyYAML is imported here, when
    a text is composed: a start whose files were composed before (the disk cache) needs none."""
    import yaml

    class _Loader(yaml.SafeLoader):
        _depth = 0

        def compose_node(self, parent, index):  # noqa: D102 - PyYAML hook
            self._depth += 1
            try:
                if self._depth > MAX_YAML_DEPTH:
                    raise _TooBig(f"nesting deeper than {MAX_YAML_DEPTH} levels")
                return super().compose_node(parent, index)
            finally:
                self._depth -= 1

    _Loader.add_implicit_resolver(
        "tag:yaml.org,2002:float",
        re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""", re.X),
        list("-+0123456789."),
    )
    return _Loader


def _node_children(node) -> list:
    import yaml
    if isinstance(node, yaml.MappingNode):
        return [n for kv in node.value for n in kv]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []


def _check_expansion(root) -> None:
    """Refuse a node graph whose alias expansion exceeds ``MAX_YAML_NODES`` or that refers
    to itself (each shared node is sized once: milliseconds, whatever it expands to)."""
    size: dict[int, int] = {}
    active: set[int] = set()
    stack: list[tuple[Any, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        k = id(node)
        if done:
            active.discard(k)
            n = 1 + sum(size[id(c)] for c in _node_children(node))
            if n > MAX_YAML_NODES:
                raise _TooBig(f"more than {MAX_YAML_NODES} values after alias expansion")
            size[k] = n
        elif k not in size:
            if k in active:
                raise _TooBig("an alias that refers to itself")
            active.add(k)
            stack.append((node, True))
            stack.extend((c, False) for c in _node_children(node) if id(c) not in size)


# Documents already composed and constructed in this process, by their text: a campaign or
# synthesis worker reads the same hardware file and scenario run after run (composing a
# config in pure-Python PyYAML is ~10 ms). The value is kept pickled, so every caller gets
# a fresh copy it may change (``load_sections`` pops ``include``); bounded, oldest out.
_PARSED: dict[str, bytes] = {}
_PARSED_MAX = 64


def _load_yaml_bounded(text: str) -> Any:
    kept = _PARSED.get(text)
    if kept is not None:
        return pickle.loads(kept)
    data = _composed_across_processes(text)
    if len(_PARSED) >= _PARSED_MAX:
        del _PARSED[next(iter(_PARSED))]
    _PARSED[text] = pickle.dumps(data, protocol=pickle.HIGHEST_PROTOCOL)
    return data


def _compose_bounded(text: str) -> Any:
    loader = _loader_class()(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_expansion(node)
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _composed(text: str) -> Any:
    return _compose_bounded(text)


# ... and across processes (memo.across_processes: by the text and the code's bytes; plain
# dicts, lists, strings and numbers only; a refused text is refused each time): a `rig`
# command's start composes none of the shipped files it read before
_composed_across_processes = across_processes("yaml-document", _composed)


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_YAML_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(str(path), "", "an existing config file") from None
    except OSError as e:
        raise ConfigError(str(path), "", f"a readable file ({e.strerror})") from e
    if len(raw) > MAX_YAML_BYTES:
        raise ConfigError(str(path), "", f"a YAML file of at most {MAX_YAML_BYTES // 1024} KiB")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(str(path), "", f"UTF-8 text (invalid byte at offset {e.start})") from None
    try:
        data = _load_yaml_bounded(text)
    except _TooBig as e:
        raise ConfigError(str(path), "", f"a YAML file within the loader's bounds ({e})") from None
    except Exception as e:          # a PyYAML error (imported with the loader), else not ours
        import yaml
        if not isinstance(e, yaml.YAMLError):
            raise
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "?"
        raise ConfigError(str(path), "", f"valid YAML (syntax error at {where}: {getattr(e, 'problem', e)})") from e
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(str(path), "", "a mapping of sections at the top level", type(data).__name__)
    return data


def read_config_file(path: str | Path) -> dict[str, Any]:
    """One config file's top-level mapping as written (``include`` not followed), read as
    :func:`load` reads it; errors name the file (``rig sim --write-config`` copies it)."""
    return _read_yaml(Path(path))


def load_sections(path: Path, _seen: tuple[Path, ...] = ()) -> dict[str, tuple[Any, str]]:
    """Read a config file and its includes into ``{section: (value, file)}``."""
    path = path.resolve()
    if path in _seen:
        raise ConfigError(str(path), "include", "no include cycle")
    data = _read_yaml(path)
    out: dict[str, tuple[Any, str]] = {}
    inc = data.pop("include", [])
    if isinstance(inc, str):
        inc = [inc]
    if not isinstance(inc, list) or not all(isinstance(i, str) for i in inc):
        raise ConfigError(str(path), "include", "a list of file names", inc)
    for name in inc:
        for k, v in load_sections(path.parent / name, _seen + (path,)).items():
            if k in out:
                raise ConfigError(v[1], k, f"a section defined once (also in {out[k][1]})")
            out[k] = v
    for k, v in data.items():
        if k not in _SECTION_FILES:
            raise ConfigError(str(path), str(k), "no such section (known: include, " + ", ".join(_SECTION_FILES) + ")")
        if k == "hardware":
            _hardware_file_rules(path, data, inc, out)
        out[k] = (v, str(path))  # the including file overrides an included section
    return out


def _hardware_file_rules(path: Path, data: dict, inc: list, out: dict) -> None:
    """The hardware description is a file of its own (only ``hardware:``, no includes),
    defined once: a run config can include it but neither carry nor override ceilings."""
    k = str(path)
    if len(data) != 1 or inc:
        raise ConfigError(k, "hardware", "the hardware description in a file of its own (only a `hardware:` "
                          "section, no includes; the run config includes that file, e.g. hardware.yaml)")
    if "hardware" in out:
        raise ConfigError(k, "hardware", f"one hardware description (also in {out['hardware'][1]})")


def load(path: str | Path | None = None) -> RigConfig:
    """Load and validate a rig configuration (default: the shipped simulated rig)."""
    p = Path(path) if path is not None else DEFAULT_CONFIG
    sections = load_sections(p)
    kwargs: dict[str, Any] = {}
    import typing
    hints = typing.get_type_hints(RigConfig)
    for name in _SECTION_FILES:
        if name not in sections:
            continue
        value, file = sections[name]
        kwargs[name] = schema._convert(hints[name], value, name, file)
        if name == "hardware":
            kwargs[name] = dataclasses.replace(kwargs[name], source=file)
    for required in ("geometry", "plant", "controller", "limits"):
        if required not in kwargs:
            raise ConfigError(str(p.resolve()), required, "a section (missing; add it or include a file that has it)")
    if "hardware" not in kwargs:
        raise ConfigError(str(p.resolve()), "hardware", "the hardware description (missing; include "
                          f"{HARDWARE_FILE.name} or this rig's own hardware file: docs/safety.md)")
    try:
        return RigConfig(source=str(p.resolve()), **kwargs)
    except ConfigError as e:
        file = sections.get(e.key_path.split(".")[0], (None, str(p)))[1]
        raise ConfigError(file, e.key_path, e.expected, e.got) from None


def resolve_config_path(name: str) -> Path:
    """Resolve a file relative to the shipped configs directory."""
    p = Path(name)
    return p if p.is_absolute() else CONFIG_DIR / p
