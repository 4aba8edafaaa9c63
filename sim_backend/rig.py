"""The simulated rig: the plant with a virtual device on the other end of every wire.

Lasers stream frames into pty pairs, the converters are CiA 402 drives on a python-can
bus, the force–torque sensors sit behind real Modbus TCP servers on 127.0.0.1. In
lockstep (``advance(t)``, called by the runtime's ``LockstepClock``) the plant is
integrated to ``t`` with the currents the virtual drives actually apply, then every
virtual device emits what it would have sent by ``t``. Scenario disturbances act on the
plant; scenario faults are injected into the virtual devices (or, for ``stall``, into
the runtime's clock).
"""

from __future__ import annotations

import itertools
import math
import random
from typing import Callable, Optional

import can

from drivers.ft300 import Wrench
from rig_runtime.config import LASER_ROLES, WHEELS, RigConfig
from rig_runtime.geometry import ideal_readings, pose_from_carriers
from rig_runtime.scenario import Scenario

from .lockstep_bus import LockstepBus
from .plant import LiftedCarrier, Plant
from .simconfig import sim_config
from .virtual_drive import VirtualDriveSet
from .virtual_ft import VirtualFTServer
from .virtual_laser import LaserGroup, VirtualLaser

_channel_ids = itertools.count()


class SimulatedRig:
    def __init__(self, cfg: RigConfig, scenario: Optional[Scenario] = None, seed: Optional[int] = None,
                 drive_bus: Optional[can.BusABC] = None):
        self.cfg = cfg
        self.sc = sim_config(cfg)
        self.seed = self.sc.seed if seed is None else seed
        self.scenario = scenario
        self.h = cfg.controller.h
        self._rng = random.Random(self.seed)
        p = cfg.plant
        lifted = scenario is not None and scenario.lifted_carrier == "rear"
        self.plant = Plant(p, wheel_dynamics=self.sc.wheel_dynamics,
                           rear_lifted=LiftedCarrier(self.sc.lifted_D, self.sc.lifted_psi_off) if lifted else None)
        psi0 = p.psi_off
        y0 = p.c_y * p.v * psi0 / p.a_lat + p.y_off / (2 * p.l0) * p.v / p.a_lat
        if self.sc.initial_y_mm is not None:
            y0 = self.sc.initial_y_mm * 1e-3
        psi_ar = None if scenario is None or scenario.initial_psi_mrad is None else scenario.initial_psi_mrad * 1e-3
        self.plant.reset(y_r=y0, psi_ar=psi_ar)   # psi None: at rest (K·0 + psi_off), z = psi
        self.t = 0.0
        self._drive_bus = drive_bus
        self.defer_laser_delivery = False   # advance() waits for the laser bytes itself
        self.ft_driver = None
        self._next_ft = 0.0
        self._closers: list[Callable[[], None]] = []
        try:
            self._open_devices()
        except Exception:
            self.close()
            raise
        self.t_run0 = math.nan
        self._events = self._schedule()
        self._stall_done: set[int] = set()

    # ------------------------------------------------------------------ devices
    def _open_devices(self) -> None:
        cfg, sc = self.cfg, self.sc
        self.lasers: dict[str, VirtualLaser] = {}
        for i, lc in enumerate(cfg.devices.lasers):
            vl = VirtualLaser(lc, noise_std_m=sc.laser_noise_m, latency_s=sc.laser_latency_s,
                              seed=self.seed * 101 + i, output_rate_hz=sc.laser_rate_hz)
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
        self.drives = VirtualDriveSet(cfg.devices.can, self.bus, seed=self.seed)
        wd = [self.drives.drives.get(w) for w in WHEELS]
        self._wheel_drives = None if None in wd else wd     # None: current_A(wheel) raises for the missing one
        self._closers.append(self.drives.close)
        names = [s.name for s in cfg.devices.ft.sensors]
        self.ft = VirtualFTServer(names).start() if names else None
        if self.ft is not None:
            self._closers.append(self.ft.close)
        self.ft_period = 1.0 / (sc.ft_rate_hz or cfg.devices.ft.poll_hz)
        self._publish(0.0)

    @property
    def laser_ports(self) -> dict[str, str]:
        return {r: v.port_name for r, v in self.lasers.items()}

    @property
    def ft_endpoints(self) -> dict[str, tuple[str, int]]:
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

    def attach_ft_driver(self, driver) -> None:
        """Lockstep: the runtime's F/T driver is polled by the simulated clock at the
        sensors' rate instead of by its own thread, so runs are deterministic."""
        self.ft_driver = driver

    # ------------------------------------------------------------------ scenario
    def _schedule(self) -> list:
        """(t_start, t_end, kind, item) for every disturbance and fault, scenario time."""
        ev = []
        if self.scenario is not None:
            for d in self.scenario.disturbances:
                ev.append((d.t, d.t + d.duration_s, "dist", d))
            for f in self.scenario.faults:
                ev.append((f.t, f.t + f.duration_s, "fault", f))
        return ev

    def on_running(self, t: float) -> None:
        """The runtime entered RUNNING at ``t``: scenario time starts here."""
        self.t_run0 = t
        self._active_faults: set[int] = set()

    def in_cycle(self, clock) -> Callable[[float, float], None]:
        """A hook for the loop that starves the runtime (``stall`` faults) on ``clock``."""
        def hook(t: float, tr: float) -> None:
            if self.scenario is None or math.isnan(self.t_run0):
                return
            for i, f in enumerate(self.scenario.faults):
                if f.kind == "stall" and i not in self._stall_done and tr >= f.t:
                    self._stall_done.add(i)
                    clock.spend(f.duration_s)
        return hook

    def _forces(self, tau: float) -> tuple[float, float, float, float]:
        Ff = Fr = Mf = Mr = 0.0
        for t0, t1, kind, d in self._events:
            if kind == "dist" and t0 <= tau < t1:
                if d.carrier == "front":
                    Ff += d.F_y; Mf += d.M_z
                else:
                    Fr += d.F_y; Mr += d.M_z
        return Ff, Fr, Mf, Mr

    def _update_faults(self, tau: float) -> None:
        for i, (t0, t1, kind, f) in enumerate(self._events):
            if kind != "fault" or f.kind == "stall":
                continue
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
            kw = {"corrupt": {"p": f.fraction}, "offset": {"amount_m": f.amount}}.get(f.kind, {})
            return vl.inject(f.kind, **kw)
        if dev in WHEELS:
            if not on:
                return self.drives.clear(f.kind)
            kw = {"bus_error": {"fraction": f.fraction}, "corrupt": {"fraction": f.fraction},
                  "offset": {"amount": f.amount}}.get(f.kind, {})
            return self.drives.inject(f.kind, wheel=dev, **kw)
        if self.ft is not None and dev in self.ft.endpoints:
            if not on:
                return self.ft.clear(dev, f.kind)
            kw = {"offset": {"fy": f.amount}}.get(f.kind, {})
            return self.ft.inject(dev, f.kind, **kw)
        raise ValueError(f"scenario fault {f.kind!r}: unknown device {dev!r}")

    # ------------------------------------------------------------------ lockstep
    def advance(self, t: float) -> None:
        """Integrate the plant to ``t`` and let every virtual device emit up to ``t``.

        Ordered for the wall clock: the drives' frames wait in their outbox while the plant
        steps and the laser frames are written, then go out while the kernel delivers the
        pty bytes; the wait for delivery (the runtime must see all of them) comes last —
        or, with ``defer_laser_delivery``, in :meth:`await_laser_delivery`."""
        h, plant, drives = self.h, self.plant, self.drives
        self._laser_group.wait()        # a deferred delivery nobody awaited (no-op otherwise)
        drives.hold()
        try:
            drives.service(self.t)      # SYNC/RPDOs the runtime sent last cycle; TPDOs back
            running = not math.isnan(self.t_run0)
            while self.t < t - 1e-12:
                dt = t - self.t
                if dt >= h - 1e-9:       # float residue of t0 + k h must not change the step size
                    dt = h
                tau = self.t - self.t_run0 if running else -1.0
                if running:
                    self._update_faults(tau)
                Ff, Fr, Mf, Mr = self._forces(tau) if running else (0.0, 0.0, 0.0, 0.0)
                wd = self._wheel_drives
                fl, fr, rl, rr = ([d.current_A() for d in wd] if wd is not None
                                  else [drives.current_A(w) for w in WHEELS])
                du_f = fl - fr
                du_r = rl - rr
                plant.step(dt, du_f, du_r, Ff, Fr, Mf, Mr)
                self.t += dt
                if self.t < t - 1e-12:
                    drives.service(self.t)   # watchdog and heartbeats keep time during a stall
            self.set_laser_distances()
            self._laser_group.emit(t)
        finally:
            drives.release()
        self._publish_rest(t)
        if not self.defer_laser_delivery:
            self._laser_group.wait()

    def await_laser_delivery(self) -> None:
        """Return once the laser bytes of the latest ``advance`` are readable at the ports.
        With ``defer_laser_delivery`` the runtime calls this just before it reads the lasers
        (``RigDevices.before_laser_poll``), so the kernel delivers them while the runtime
        polls its other devices."""
        self._laser_group.wait()

    def _publish(self, t: float) -> None:
        """Physical values -> virtual devices (their own codecs), frames up to ``t``."""
        self.set_laser_distances()
        self._laser_group.emit(t)
        self._publish_rest(t)
        self._laser_group.wait()

    def _publish_rest(self, t: float) -> None:
        """Wheel speeds and, when due, F/T registers (and the lockstep F/T poll: the
        driver sends its requests, the simulated sensors answer them in this thread, the
        driver collects the replies — no thread hand-over in the round)."""
        self.set_wheel_speeds()
        if self.ft is not None and t >= self._next_ft - 1e-12:
            self._next_ft = t + self.ft_period
            self.set_wrenches()
            drv = self.ft_driver
            if drv is not None:
                drv.poll_devices_start()
                self.ft.serve_inline()
                drv.poll_devices_finish()

    def set_laser_distances(self) -> None:
        """The distances the six lasers see for the plant's pose (no frames are emitted)."""
        p, geo = self.plant, self.cfg.geometry
        pose = pose_from_carriers(p.y_f, p.y_r, p.psi_af, p.psi_ar, geo)
        r = ideal_readings(pose, geo, s0=0.0)
        for (vl, s0), v in zip(self._laser_targets, (r.b_f, r.b_r, r.s_fl, r.s_fr, r.s_rl, r.s_rr)):
            if vl is not None:
                vl.set_distance(v + s0)

    def set_wheel_speeds(self) -> None:
        """The plant's wheel speeds, with encoder noise, to the virtual drives."""
        p = self.plant
        g = self._rng.gauss
        en = self.sc.encoder_noise_rad_s
        self.drives.set_wheel_speeds([om + (g(0.0, en) if en else 0.0)
                                      for om in (p.omega_fl, p.omega_fr, p.omega_rl, p.omega_rr)])

    def set_wrenches(self) -> None:
        """The plant's force–torque readings, with noise on the forces, to the Modbus servers."""
        fr = self.plant.ft_readings()
        g = self._rng.gauss
        n = self.sc.ft_noise_N
        for s in self.cfg.devices.ft.sensors:
            vals6 = fr.get(s.name[-2:], (0.0,) * 6)
            self.ft.set_wrench(s.name, Wrench(*(v + (g(0.0, n) if n and k < 3 else 0.0)
                                                for k, v in enumerate(vals6))))

    def close(self) -> None:
        for c in reversed(self._closers):
            try:
                c()
            except Exception:
                pass
        self._closers.clear()
