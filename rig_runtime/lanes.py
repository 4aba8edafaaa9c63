"""Lanes: the per-carrier part of the cycle.

A lane is one wheel carrier the runtime drives: its measurement (y, ψ, Δω from the
geometry), its reference, its controller (or an open-loop input), the differential current
the supervisor let through, and the two wheels that current goes to. A second carrier, a
per-carrier reference or a new stage (an estimator) is one more lane or one more step of a
lane, never new indices.

How a carrier's differential current u = i_left − i_right reaches its wheels is the
allocation's (``rig_runtime.allocation``: ±u/2, or the remaining wheel alone after a drive
loss).
"""

from __future__ import annotations

from functools import partial
from operator import attrgetter
from typing import Callable, Mapping, Optional, Sequence

from .config import RigConfig, Schedule
from .control import law_of, make_controller
from .damping import YawDamping
from .geometry import Measurement
from .observer import Observer, ObserverDesign, make_observers

CARRIER_WHEELS: dict[str, tuple[str, str]] = {"front": ("fl", "fr"), "rear": ("rl", "rr")}   # (left, right)


class Lane:
    """One carrier the runtime drives (see the module docstring). Per cycle: ``sense`` →
    ``estimate`` (a lane with an observer) → (``start`` when RUNNING begins) →
    ``schedule`` → ``control`` → ``apply``."""

    __slots__ = ("carrier", "wheels", "controller", "reference", "open_loop", "controlled",
                 "y", "psi", "dw", "y_ref", "u_cmd", "u", "observer", "lateral_lasers", "ft_sensors",
                 "sched", "v_design", "signals", "signal_values")

    def __init__(self, carrier: str, controller, reference: Callable[[float], float],
                 open_loop: Optional[Callable[[float], float]] = None,
                 observer: Optional[ObserverDesign] = None,
                 schedule: Optional[Schedule] = None, v_design: float = 1.0):
        self.carrier = carrier
        self.sched = schedule if controller is not None else None   # None: fixed gains
        self.v_design = v_design
        # a design (its own filter) or a built observer (a carrier's view of the joint filter)
        self.observer = Observer(observer) if isinstance(observer, ObserverDesign) else observer
        self.lateral_lasers = self.observer.d.lateral_lasers if observer is not None else ()
        self.ft_sensors = self.observer.d.ft_sensors if observer is not None else ()
        self.wheels = CARRIER_WHEELS[carrier]
        self.controller = controller            # None: the lane only plays an open-loop input
        self.controlled = controller is not None
        self.reference = reference
        self.open_loop = open_loop
        self.y = self.psi = self.dw = 0.0
        self.y_ref = 0.0
        self.u_cmd = 0.0                        # what the controller / input asked for
        self.u = 0.0                            # what the supervisor let through
        # the law's signals (its declaration, ``law.signals``), resolved once: ``signal_values()`` gives
        # them as the controller's last step left them (a controlled lane's first columns in the log row)
        self.signals = tuple(controller.law.signals) if controller is not None else ()
        self.signal_values: Callable[[], tuple[float, ...]] = \
            partial(signal_getter(controller, self.signals), controller) if controller is not None else tuple

    def sense(self, m: Measurement) -> None:
        """This cycle's measurement of the carrier."""
        self.y, self.psi, self.dw = m.carrier(self.carrier)

    def estimate(self, lat_ok: bool, y_other: float, f_lat: float = 0.0) -> None:
        """The observer's step on this cycle's measurement and the current held since the
        last cycle (``lat_ok``: the lateral lasers are fit this cycle, as the supervisor
        judges them; ``y_other``: the other carrier's lateral displacement, ``f_lat``: its
        measured lateral force (N), known inputs)."""
        self.observer.step(self.y, self.psi, self.dw, self.u, y_other, lat_ok, f_lat)

    def schedule(self, v_hat: float) -> None:
        """The speed schedule on the measured speed ``v_hat`` (the schedule law,
        docs/vehicle.md): outside the standstill band the outer PI's gain factor is
        g = v_design / v̂ (sign included); inside it (|v̂| < v_min, or no speed measured) the
        lateral loop holds, and it resumes bumplessly on leaving it. Nothing without a
        ``controller.schedule``. The lane's observer (with a schedule: a table of designs over
        speed) takes the design for v̂ here, for its next prediction over the coming period."""
        sch = self.sched
        if sch is None:
            return
        if self.observer is not None:
            self.observer.select(v_hat)
        c = self.controller
        if abs(v_hat) >= sch.v_min:         # False for NaN: no speed, no lateral control
            c.set_gain_factor(self.v_design / v_hat)
            if c.held:
                c.resume()
        elif not c.held:
            c.hold(sch.hold_ramp_s)

    def log_values(self) -> tuple[float, float, float, float, float]:
        """``LANE_FIELDS`` of the loop's log (after the law's signals): u_cmd, u_lim, y_ref,
        the schedule's gain factor and whether the lateral loop holds (1.0/0.0)."""
        c = self.controller
        return (self.u_cmd, self.u, self.y_ref, c.g, 1.0 if c.held else 0.0)

    def start(self) -> None:
        """RUNNING began: the controller starts bumplessly on the reference's first value."""
        if self.controller is not None:
            self.controller.start(self.reference(0.0), self.y, self.psi)

    def control(self, t_run: float, running: bool) -> float:
        """The reference at run time ``t_run`` and the command of this cycle (0 unless RUNNING)."""
        self.y_ref = y_ref = self.reference(t_run)
        if not running:
            u = 0.0
        elif self.open_loop is not None:
            u = self.open_loop(t_run)
        else:
            u = self.controller.step(y_ref, self.y, self.psi)
        self.u_cmd = u
        return u

    def apply(self, u: float) -> None:
        """The current the supervisor let through; the controller learns it (anti-windup)."""
        self.u = u
        if self.controller is not None:
            self.controller.limit_feedback(u)


class LateralPair:
    """The cross-lane stage of a law that reads both carriers (``controller.law: decoupled``):
    each carrier's lateral displacement by name, as its lane controls on it this cycle (after
    every lane has sensed and estimated: the loop's control stage comes after both). A carrier
    without a lane (lifted) reads 0, the lifted carrier's y."""

    __slots__ = ("_lanes",)

    def __init__(self, lanes: Sequence["Lane"]):
        self._lanes = {lane.carrier: lane for lane in lanes}

    def y(self, carrier: str) -> float:
        lane = self._lanes.get(carrier)
        return lane.y if lane is not None else 0.0


def law_signals(cfg: RigConfig) -> Mapping[str, str]:
    """The configured law's signals by name (SI unit), as the law declares them
    (``law.signals``, :mod:`rig_runtime.control`): every controlled carrier's lane logs them as
    ``{carrier}_{name}`` (the same law on every carrier)."""
    return law_of(cfg.controller, yaw=YawDamping.of(cfg.plant.carrier(cfg.controlled[0]))).signals


def signal_getter(controller, names: Sequence[str]) -> Callable[[object], tuple[float, ...]]:
    """A getter of the signals ``names`` of ``controller``, resolved once: a signal is a field
    of the controller's record of its last step (``controller.st``) or else a read-only
    accessor of the controller by that name. Always a tuple (one per name)."""
    paths = [f"st.{n}" if hasattr(controller.st, n) else n for n in names]
    missing = [n for n, p in zip(names, paths) if not hasattr(controller, n) and not p.startswith("st.")]
    if missing:
        raise AttributeError(f"{type(controller).__name__} has no signal {', '.join(missing)}")
    if len(paths) > 1:
        return attrgetter(*paths)
    if paths:
        one = attrgetter(paths[0])
        return lambda c: (one(c),)
    return lambda c: ()


def make_lanes(cfg: RigConfig, reference: Callable[[float], float] | Mapping[str, Callable[[float], float]],
               open_loop: Optional[tuple[str, Callable[[float], float]]] = None,
               observers: Optional[Mapping[str, ObserverDesign]] = None) -> list[Lane]:
    """A lane per controlled carrier (PI-PD or P with that carrier's gains, the configured
    limits and speed schedule), plus one for an open-loop input on a carrier that is not
    controlled (in that order); a controlled carrier with a design in ``observers`` carries
    its observer. ``reference``: one y_ref(t) for every carrier, or one per carrier by name
    (a carrier without one holds 0). ``open_loop``: (carrier, u(t)); the carrier ``both``
    plays the input on every controlled carrier (the controller off)."""
    observers = make_observers(observers)      # one joint filter shared by its carriers' lanes
    lim = cfg.limits
    refs = reference if isinstance(reference, Mapping) else None
    ol_carrier, ol_input = open_loop if open_loop is not None else (None, None)
    ol_carriers = tuple(cfg.controlled) if ol_carrier == "both" else (ol_carrier,)
    carriers = list(cfg.controlled) + ([ol_carrier] if ol_carrier and ol_carrier != "both"
                                       and ol_carrier not in cfg.controlled else [])
    sch = cfg.controller.schedule
    v_design = sch.v_design if sch is not None and sch.v_design is not None else cfg.plant.v
    lanes = []
    for carrier in carriers:
        controlled = carrier in cfg.controlled
        ctrl = make_controller(cfg.controller, lim.u_max, lim.psi_ref_max, carrier,
                               YawDamping.of(cfg.plant.carrier(carrier))) if controlled else None
        ref = refs.get(carrier, _zero) if refs is not None else reference
        lanes.append(Lane(carrier, ctrl, ref, ol_input if carrier in ol_carriers else None,
                          observers.get(carrier) if controlled else None, sch, v_design))
    pair = LateralPair(lanes)
    for lane in lanes:
        if hasattr(lane.controller, "couple"):      # a law across carriers reads them through one stage
            lane.controller.couple(pair)
    return lanes


def _zero(t: float) -> float:
    return 0.0
