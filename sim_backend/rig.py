"""The simulated rig: the plant with a virtual device on the other end of every wire.

Lasers stream frames into serial lines, the converters are CiA 402 drives on a python-can
bus, the force–torque sensors sit behind Modbus TCP servers. The wires are in-process
(``sim.wires: memory``, the default: :mod:`rig_runtime.wires` byte pipes, ``mem://`` URLs
the drivers open like any port or endpoint) or the kernel's (``kernel``: pty pairs and
TCP on 127.0.0.1, what ``rig sim`` serves to other processes); the same bytes either way.
The CAN bus is in-process in both (``sim.can_bus``). The
runtime reaches the simulated rig only through those transports (``laser_ports``,
``runtime_bus()``, ``ft_endpoints``) and through its clock,
``LockstepClock(advance=sim.advance)``: ``advance(t)`` completes every delivery up to
``t`` before the runtime's release — the drives take the frames the runtime sent, the
plant is integrated to ``t`` with the currents they apply, every laser's frames up to
``t`` are readable at its port, the F/T requests the runtime sent are answered, and the
drives' replies are on the bus. Runs are deterministic for a seed.

Until the first ``advance`` (the runtime's blocking start-up: SDO configuration of the
drives) the virtual drives answer from a thread at the frozen time ``t`` = 0; from then on
only inside ``advance``. Scenario time starts when every virtual drive has reached
OPERATION ENABLED for the first time (the runtime enables the power stages at its ARM):
disturbances act on the plant, faults are injected into the virtual devices, and a
``stall`` fault makes ``advance`` return a release time later than ``t`` (the runtime
sees a starved machine, while the plant and the drives' timers run on). A fault naming a
device or fault kind the simulated rig does not have is refused when the rig is built.

``RealtimeSim`` (``rig sim``) serves the same rig in real time with :meth:`step`, the
``set_*`` publishers and :meth:`start_scenario` / :meth:`end_scenario`, with its own CAN
responder in front of the drives (``drive_bus``).
"""

from __future__ import annotations

import itertools
import math
import random
from typing import Callable, Optional, Sequence

import can

from drivers.ft_codec import Wrench
from rig_runtime.config import LASER_ROLES, WHEELS, RigConfig
from rig_runtime.errors import ConfigError
from rig_runtime.geometry import ideal_readings, pose_from_carriers
from rig_runtime.scenario import Scenario

from . import hands, lifted_wheels, miswire, virtual_drive, virtual_ft, virtual_laser
from .lockstep_bus import LockstepBus
from .plant import LiftedCarrier, Plant
from .simconfig import sim_config
from .virtual_drive import VirtualDriveSet
from .virtual_ft import VirtualFTServer
from .virtual_laser import LaserGroup, VirtualLaser

_channel_ids = itertools.count()
_NO_FORCES = (0.0, 0.0, 0.0, 0.0)
_NO_WRENCH = (0.0,) * 6


class SimulatedRig:
    """``wires``: "memory" or "kernel" (None: ``sim.wires``; always "kernel" with a
    ``drive_bus``, i.e. for ``rig sim``, whose clients are other processes)."""

    def __init__(self, cfg: RigConfig, scenario: Optional[Scenario] = None, seed: Optional[int] = None,
                 drive_bus: Optional[can.BusABC] = None, wires: Optional[str] = None):
        self.cfg = cfg
        self.sc = sim_config(cfg)
        if wires is None:
            wires = "kernel" if drive_bus is not None else self.sc.wires
        if wires not in ("memory", "kernel"):
            raise ValueError(f"wires must be 'memory' or 'kernel', got {wires!r}")
        self.wires = wires
        self.miswire = self.sc.miswire or miswire.NONE
        self.seed = self.sc.seed if seed is None else seed
        self.scenario = scenario
        self.h = cfg.controller.h
        self._rng = random.Random(self.seed)
        self.plant = self._new_plant(cfg.plant, scenario)
        self.speed = scenario.speed_profile(cfg.plant.v) if scenario is not None else (lambda tau: cfg.plant.v)
        self._check_speed()
        self.plant.set_speed(self.speed(0.0))    # the rollers run at the scenario's start speed
        self._reset_plant(cfg.plant, scenario)
        self.t = 0.0
        self._drive_bus = drive_bus
        self._check_scenario()
        self.t_run0 = math.nan                  # scenario time 0 (simulated time); NaN: not started
        self.powered_once = False               # every power stage was on at least once (the hands let go)
        self.power_sessions = [0, 0]            # power-on sessions started, ended (the operator's set-ups)
        self._power_on = False
        # the wheels of a carrier off the rollers spin freely (sim_backend/lifted_wheels.py)
        p = cfg.plant
        lifted = scenario.lifted_carrier if scenario is not None else None
        self.lifted_wheels = lifted_wheels.LiftedWheels(p.J_x, p.k_tau)
        self._lifted_by_setup = tuple(c for c in ("front", "rear") if c == lifted or not self.plant.rolling(c))
        self._update_lifted()
        self._events = self._schedule()
        # the disturbances and the non-stall faults with their index, picked out once: step looks at them
        self._dists = [(t0, t1, d) for t0, t1, kind, d in self._events if kind == "dist"]
        self._fault_events = [(i, t0, t1, f) for i, (t0, t1, kind, f) in enumerate(self._events)
                              if kind == "fault" and f.kind != "stall"]
        self._active_faults: set[int] = set()
        self._stalls_done: set[int] = set()
        # the scenario's stall faults (index, fault), picked out once: advance looks at them each cycle
        self._stalls = [(i, f) for i, f in enumerate(scenario.faults) if f.kind == "stall"] if scenario is not None else []
        self._next_ft = 0.0
        self._closers: list[Callable[[], None]] = []
        try:
            self._open_devices()
        except Exception:
            self.close()
            raise
        self._serving_start_up = drive_bus is None
        if self._serving_start_up:              # the runtime's blocking start-up, before the first advance
            self.drives.start_realtime(time_fn=lambda: self.t)

    # ------------------------------------------------------------------ the contact set-up
    def _new_plant(self, p, scenario: Optional[Scenario]) -> Plant:
        """The plant with the set-up of the config (``plant.front_contact``, ``plant.rear_contact``)
        and the scenario (``lifted_carrier``: that carrier off the rollers, Sec. 4.3.2, with the
        contact-free ``sim.lifted_D`` and ``sim.lifted_psi_off``; the other one must be out of
        contact by the config: the paper's free response and its mirror for the front)."""
        lifted_name = scenario.lifted_carrier if scenario is not None else None
        if lifted_name is not None:
            other = "front" if lifted_name == "rear" else "rear"
            if getattr(p, f"{other}_contact"):
                raise ConfigError(self.cfg.source or None, f"plant.{other}_contact",
                                  f"false for scenario {scenario.name!r} (lifted_carrier: {lifted_name}: "
                                  f"no carrier on the rollers during a free response)", True)
        lifted = LiftedCarrier(self.sc.lifted_D, self.sc.lifted_psi_off)
        return Plant(p, wheel_dynamics=self.sc.wheel_dynamics,
                     rear_lifted=lifted if lifted_name == "rear" else None,
                     front_lifted=lifted if lifted_name == "front" else None)

    def _check_speed(self) -> None:
        """A speed profile needs the static wheel relation (4): the dynamic form (3) has the
        creep pole -c11 r0²/(J_x v), unbounded at v = 0 and unstable for v < 0 as written."""
        sc = self.scenario
        if sc is None or not sc.speed or self.sc.wheel_dynamics != "dynamic":
            return
        vs = [p.v for p in sc.speed]
        if any(v != self.cfg.plant.v for v in vs):
            raise ConfigError(self.cfg.source or None, "sim.wheel_dynamics",
                              f"'static' for scenario {sc.name!r} with a speed profile (the dynamic form (3) "
                              f"runs at the fixed plant.v > 0 only)", "dynamic")

    def _reset_plant(self, p, scenario: Optional[Scenario]) -> None:
        """The plant at rest for u = 0 (yaw at psi_off, z = psi; the rolling carrier(s) at the
        lateral rest position); ``sim.initial_y_mm`` sets the y of the carrier in contact (the
        rear's when both are) and the scenario's ``initial_psi_mrad`` the yaw of the lifted or
        open-loop carrier (the rear's without either)."""
        pl = self.plant
        psi = None if scenario is None or scenario.initial_psi_mrad is None else scenario.initial_psi_mrad * 1e-3
        which = "rear"
        if scenario is not None:
            which = scenario.lifted_carrier or (scenario.open_loop.carrier if scenario.open_loop else "rear")
        y0 = None if self.sc.initial_y_mm is None else self.sc.initial_y_mm * 1e-3
        kw = {"psi_af" if which == "front" else "psi_ar": psi}
        if pl.rear_contact or pl.rear_lifted:
            if y0 is None and p.rear is None and pl.v == p.v and pl.a_r != 0.0:   # the paper's set-up as it always was
                y0 = p.c_y * p.v * p.psi_off / p.a_lat + p.y_off / (2 * p.l0) * p.v / p.a_lat
            kw["y_r"] = y0                                        # None: the plant's rest value
        else:
            kw["y_f"] = y0
        pl.reset(**kw)   # psi None: at rest (K·0 + psi_off), z = psi

    # ------------------------------------------------------------------ devices
    def _open_devices(self) -> None:
        cfg, sc = self.cfg, self.sc
        self.lasers: dict[str, VirtualLaser] = {}
        for i, lc in enumerate(cfg.devices.lasers):
            vl = VirtualLaser(lc, noise_std_m=sc.laser_noise_m, latency_s=sc.laser_latency_s,
                              seed=self.seed * 101 + i, output_rate_hz=sc.laser_rate_hz,
                              wire="memory" if self.wires == "memory" else "pty")
            self._closers.append(vl.close)
            self.lasers[lc.role] = vl
        self._laser_group = LaserGroup(list(self.lasers.values()))
        self.s0 = {}
        for lc in cfg.devices.lasers:
            self.s0[lc.role] = (lc.offset_mm + 0.5 * lc.measuring_range_mm) * 1e-3
        # (laser or None, mid-range offset added to its ideal reading) in LASER_ROLES order
        self._laser_targets = [(self.lasers.get(r), self.s0.get(r, 0.0) if r.startswith("s") else 0.0)
                               for r in LASER_ROLES]
        self.can_channel = f"rig-sim-{next(_channel_ids)}-{id(self)}"
        if self._drive_bus is not None:      # e.g. the far side of an emulated SLCAN adapter
            self.bus = self._drive_bus
        else:
            self.bus = self._new_bus()
            self._closers.append(self.bus.shutdown)
        self.drives = VirtualDriveSet(self.wired_can(), self.bus, seed=self.seed)
        wd = [self.drives.drives.get(w) for w in WHEELS]
        self._wheel_drives = None if None in wd else wd     # None: current_A(wheel) raises for the missing one
        self._closers.append(self.drives.close)
        names = [s.name for s in cfg.devices.ft.sensors]
        # a poll process cannot reach an in-process wire: its sensors stay on TCP
        in_process = self.wires == "memory" and cfg.devices.ft.poller != "process"
        self.ft = VirtualFTServer(names, stream="memory" if in_process else "tcp").start() if names else None
        if self.ft is not None:
            self._closers.append(self.ft.close)
        self.ft_period = 1.0 / (sc.ft_rate_hz or cfg.devices.ft.poll_hz)
        # (sensor name, the wheel whose plant reading it carries: its name's last two letters)
        self._ft_wheels = tuple((s.name, s.name[-2:]) for s in cfg.devices.ft.sensors)
        self.set_laser_distances()
        self._laser_group.emit(0.0)
        self.set_wheel_speeds()
        self._set_wrenches_when_due(0.0)
        self._laser_group.wait()

    def wired_can(self):
        """The drives as the simulated rig is wired (``sim.miswire.node_swap``), for the
        virtual drives wherever they run."""
        return miswire.drive_config(self.miswire, self.cfg.devices.can)

    @property
    def laser_ports(self) -> dict[str, str]:
        """Laser role -> the port the runtime reads (``devices.lasers[].port``): a pty path
        or a ``mem://`` URL."""
        return {r: v.port_name for r, v in self.lasers.items()}

    @property
    def ft_endpoints(self) -> dict[str, tuple[str, int]]:
        """F/T sensor name -> (host, port) of its Modbus TCP server on 127.0.0.1, or
        (``mem://NAME``, 0) of its in-process endpoint."""
        return dict(self.ft.endpoints) if self.ft is not None else {}

    def runtime_bus(self) -> can.BusABC:
        """A python-can bus for the runtime's side (or a tap) of the simulated CAN wire;
        shut down with the simulated rig."""
        bus = self._new_bus()
        self._closers.append(bus.shutdown)
        return bus

    def _new_bus(self) -> can.BusABC:
        if self.sc.can_bus == "lockstep":
            return LockstepBus(channel=self.can_channel)
        return can.Bus(interface="virtual", channel=self.can_channel, receive_own_messages=False)

    # ------------------------------------------------------------------ scenario
    def _check_scenario(self) -> None:
        """Every fault names a device of this rig and a fault that device can have."""
        if self.scenario is None:
            return
        dev = self.cfg.devices
        kinds: dict[str, Sequence[str]] = {}
        kinds.update({lc.role: virtual_laser.FAULT_KINDS for lc in dev.lasers})
        kinds.update({d.wheel: tuple(virtual_drive.FAULT_KINDS) for d in dev.can.drives})
        kinds.update({s.name: virtual_ft.FAULT_KINDS for s in dev.ft.sensors})
        where = self.scenario.source or f"scenario {self.scenario.name!r}"
        for i, f in enumerate(self.scenario.faults):
            if f.kind == "stall":
                continue
            if f.device not in kinds:
                raise ConfigError(where, f"faults[{i}].device",
                                  f"a device of the simulated rig for fault {f.kind!r} (one of "
                                  f"{', '.join(kinds)})", f.device)
            if f.kind not in kinds[f.device]:
                raise ConfigError(where, f"faults[{i}].kind",
                                  f"a fault device {f.device!r} can have (one of {', '.join(kinds[f.device])})",
                                  f.kind)

    def _schedule(self) -> list:
        """(t_start, t_end, kind, item) for every disturbance and fault, scenario time."""
        ev = []
        if self.scenario is not None:
            for d in self.scenario.disturbances:
                ev.append((d.t, d.t + d.duration_s, "dist", d))
            for f in self.scenario.faults:
                ev.append((f.t, f.t + f.duration_s, "fault", f))
        return ev

    @property
    def scenario_started(self) -> bool:
        return not math.isnan(self.t_run0)

    def start_scenario(self, t: float) -> None:
        """Scenario time 0 is simulated time ``t`` (lockstep: called by :meth:`advance`)."""
        self.end_scenario()
        self.t_run0 = t
        self.powered_once = True

    def end_scenario(self) -> None:
        """Clear the active faults, stop disturbances and scenario time (``rig sim``: a
        session ended); stalls that happened stay done."""
        for i in sorted(self._active_faults):
            self._inject(self._events[i][3], False)
        self._active_faults.clear()
        self.t_run0 = math.nan

    def _forces(self, tau: float) -> tuple[float, float, float, float]:
        if not self._dists:
            return _NO_FORCES
        Ff = Fr = Mf = Mr = 0.0
        for t0, t1, d in self._dists:
            if t0 <= tau < t1:
                if d.carrier == "front":
                    Ff += d.F_y; Mf += d.M_z
                else:
                    Fr += d.F_y; Mr += d.M_z
        return Ff, Fr, Mf, Mr

    def _update_faults(self, tau: float) -> None:
        for i, t0, t1, f in self._fault_events:
            on = t0 <= tau < t1
            if on and i not in self._active_faults:
                self._active_faults.add(i)
                self._inject(f, True)
            elif not on and i in self._active_faults:
                self._active_faults.discard(i)
                self._inject(f, False)

    def _inject(self, f, on: bool) -> None:
        dev = f.device
        if dev in self.lasers:
            vl = self.lasers[dev]
            if not on:
                return vl.clear(f.kind)
            kw = {"corrupt": {"p": f.fraction}, "offset": {"amount_m": f.amount},
                  "drift": {"amount_m": 0.0}}.get(f.kind, {})
            return vl.inject(f.kind, **kw)
        if dev in self.drives.drives:
            if not on:
                return self.drives.clear(f.kind, wheel=dev)
            kw = {"bus_error": {"fraction": f.fraction}, "corrupt": {"fraction": f.fraction},
                  "offset": {"amount": f.amount}, "motor_outage": {"mode": f.mode}}.get(f.kind, {})
            return self.drives.inject(f.kind, wheel=dev, **kw)
        if not on:
            return self.ft.clear(dev, f.kind)
        kw = {"offset": {"fy": f.amount}}.get(f.kind, {})
        return self.ft.inject(dev, f.kind, **kw)

    def _update_drifts(self, tau: float) -> None:
        """Each active drift fault's bias at scenario time ``tau``: rate × time since it began."""
        if not self._active_faults:
            return
        for i in self._active_faults:
            t0, _, kind, f = self._events[i]
            if f.kind == "drift":
                self.lasers[f.device].set_drift(f.rate_mm_s * 1e-3 * (tau - t0))

    def _stall_s(self, t: float) -> float:
        """How long the runtime is starved at its release ``t``: the scenario's ``stall``
        faults whose time has come, each once."""
        if not self._stalls or not self.scenario_started:
            return 0.0
        tau = t - self.t_run0
        d = 0.0
        for i, f in self._stalls:
            if i not in self._stalls_done and tau >= f.t:
                self._stalls_done.add(i)
                d += f.duration_s
        return d

    def power_observed(self, on: bool) -> None:
        """Every power stage on (``on``) or not: counts the power-on sessions, which the
        simulated operator's set-ups follow (lockstep: :meth:`advance`; ``rig sim``: the CAN
        responder's session events)."""
        if on != self._power_on:
            self._power_on = on
            self.power_sessions[0 if on else 1] += 1
            self._update_lifted()

    def _update_lifted(self) -> None:
        """Which carriers are off the rollers now: the set-up's (``plant.front_contact: false``,
        a scenario's ``lifted_carrier``) and those the simulated operator holds lifted."""
        by_hand = self.sc.operator == "commission" and hands.carriers_lifted(
            self.power_sessions[1], self.sc.operator_lifted_sessions)
        lw = self.lifted_wheels
        for carrier, wheels in (("front", ("fl", "fr")), ("rear", ("rl", "rr"))):
            for w in wheels:
                if carrier in self._lifted_by_setup or by_hand:
                    lw.lift(w, 0.0)             # off the rollers (from the start: at rest)
                else:
                    lw.lower(w)

    # ------------------------------------------------------------------ the plant
    def step(self, dt: float, currents: Sequence[float]) -> None:
        """One plant step of ``dt`` from ``self.t`` with the wheels' applied ``currents``
        (A, ``WHEELS`` order): scenario faults switched, forces applied and the roller speed
        ``speed(tau)`` of the scenario's profile set at the step's start (scenario time tau;
        0 before the scenario started), then ``self.t += dt``. The one plant step of both
        :meth:`advance` and ``RealtimeSim``."""
        if self.scenario_started:
            tau = self.t - self.t_run0
            self._update_faults(tau)
            self._update_drifts(tau)
            forces = self._forces(tau)
        else:
            tau = 0.0
            forces = _NO_FORCES
        if self.miswire.current_sign:
            currents = miswire.motor_currents(self.miswire, currents)
        fl, fr, rl, rr = currents
        self.plant.set_speed(self.speed(tau))   # the roller speed, held over the step (ZOH)
        self.plant.step(dt, fl - fr, rl - rr, *forces)
        if self.lifted_wheels.omega:
            self.lifted_wheels.step(dt, dict(zip(WHEELS, currents)))
        self.t += dt

    def applied_currents(self) -> list[float]:
        """What the virtual drives' power stages apply now, A, ``WHEELS`` order."""
        wd = self._wheel_drives
        if wd is not None:
            return [d.current_A() for d in wd]
        return [self.drives.current_A(w) for w in WHEELS]

    # ------------------------------------------------------------------ lockstep
    def advance(self, t: float) -> Optional[float]:
        """Complete every delivery up to ``t``; returns a later release time while a
        ``stall`` fault starves the runtime, else None.

        The drives take the SYNC/RPDOs the runtime sent last cycle (their replies wait in
        an outbox); the plant is integrated to the release time in steps of h with the
        currents they apply (their timers run between steps); every laser's frames up to
        then are written into its wire; the replies go onto the bus; wheel speeds and, when
        due, F/T registers are set and the F/T requests pending are answered; the call
        returns once every laser byte is readable (a pty: the kernel delivered it)."""
        h, drives = self.h, self.drives
        if self._serving_start_up:
            self._serving_start_up = False
            drives.stop()                   # from now on the drives act only in here
        drives.hold()
        try:
            drives.service(self.t)          # SYNC/RPDOs the runtime sent last cycle; TPDOs back
            on = drives.operation_enabled()
            self.power_observed(on)
            if not self.scenario_started and on:
                self.start_scenario(self.t)
            t_rel = t + self._stall_s(t)
            while self.t < t_rel - 1e-12:
                dt = t_rel - self.t
                if dt >= h - 1e-9:          # float residue of t0 + k h must not change the step size
                    dt = h
                self.step(dt, self.applied_currents())
                if self.t < t_rel - 1e-12:
                    drives.service(self.t)  # watchdog and heartbeats keep time during a stall
            self.set_laser_distances()
            self._laser_group.emit(t_rel)
        finally:
            drives.release()
        self.set_wheel_speeds()
        if self.ft is not None:
            self._set_wrenches_when_due(t_rel)
            self.ft.answer_pending()
        self._laser_group.wait()
        return t_rel if t_rel > t else None

    # ------------------------------------------------------------------ physical values -> devices
    def _set_wrenches_when_due(self, t: float) -> None:
        if self.ft is not None and t >= self._next_ft - 1e-12:
            self._next_ft = t + self.ft_period
            self.set_wrenches()

    def set_laser_distances(self) -> None:
        """The distances the six lasers see for the plant's pose (no frames are emitted)."""
        p, geo = self.plant, self.cfg.geometry
        hand = hands.offset(self.t) if self.sc.operator == "commission" and not self.powered_once else hands.NO_HANDS
        pose = pose_from_carriers(p.y_f + hand.dy_f, p.y_r + hand.dy_r, p.psi_af + hand.dpsi_af,
                                  p.psi_ar + hand.dpsi_ar, geo)
        r = ideal_readings(pose, geo, s0=0.0)
        mw = self.miswire
        if mw.laser_sign or mw.laser_swap:
            vals = {role: v + s0 for role, (_, s0), v in zip(LASER_ROLES, self._laser_targets,
                                                             (r.b_f, r.b_r, r.s_fl, r.s_fr, r.s_rl, r.s_rr))
                    if role in self.lasers}
            for role, v in miswire.laser_values(mw, vals, self.s0).items():
                self.lasers[role].set_distance(v)
            return
        for (vl, s0), v in zip(self._laser_targets, (r.b_f, r.b_r, r.s_fl, r.s_fr, r.s_rl, r.s_rr)):
            if vl is not None:
                vl.set_distance(v + s0)

    def set_wheel_speeds(self) -> None:
        """The wheel speeds — the plant's, a lifted wheel's own (``lifted_wheels``) — with
        encoder noise, to the virtual drives."""
        p = self.plant
        lifted = self.lifted_wheels.omega
        en = self.sc.encoder_noise_rad_s
        g = self._rng.gauss
        om = []                         # one loop, the draws in WHEELS order
        for w, pw in zip(WHEELS, (p.omega_fl, p.omega_fr, p.omega_rl, p.omega_rr)):
            if lifted:
                pw = lifted.get(w, pw)
            om.append(pw + g(0.0, en) if en else pw + 0.0)
        self.drives.set_wheel_speeds(miswire.wheel_speeds(self.miswire, om) if self.miswire.encoders else om)

    def set_wrenches(self) -> None:
        """The plant's force–torque readings, with noise on the forces (fx, fy, fz drawn in
        that order per sensor), to the Modbus servers."""
        fr = self.plant.ft_readings()
        g = self._rng.gauss
        n = self.sc.ft_noise_N
        for name, wheel in self._ft_wheels:
            fx, fy, fz, mx, my, mz = fr.get(wheel, _NO_WRENCH)
            if n:
                fx += g(0.0, n)
                fy += g(0.0, n)
                fz += g(0.0, n)
            else:
                fx += 0.0; fy += 0.0; fz += 0.0
            self.ft.set_wrench(name, Wrench(fx, fy, fz, mx + 0.0, my + 0.0, mz + 0.0))

    def close(self) -> None:
        """Close every transport and device (ptys, servers, buses). Idempotent."""
        for c in reversed(self._closers):
            try:
                c()
            except Exception:
                pass
        self._closers.clear()

    def __enter__(self) -> "SimulatedRig":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
