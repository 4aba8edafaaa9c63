"""The rig's devices as the control loop sees them: six lasers, the drive bus (wheel
speeds in, currents out) and the force–torque sensors, each turned into supervisor
``Channel``s updated in place every cycle.

Drivers are chosen by name from the config (``drivers.registry``); the loop only sees
this class's small interface (``loop.DeviceSet``).
"""

from __future__ import annotations

import math
import os
from typing import Callable, Mapping, Optional, Sequence

from drivers.base import Freshness
from drivers.registry import driver_class

from .config import LASER_ROLES, WHEELS, RigConfig
from .errors import ConfigError, DeviceInitError
from .safety import Channel

FT_COMPONENTS = ("fx", "fy", "fz", "mx", "my", "mz")
_INVALID = Freshness.INVALID
FT_RANGE = (300.0, 30.0)    # FT 300 class: ±300 N, ±30 N m (rated range)


def _update(c: Channel, value: float, t: float, health) -> None:
    """A supervisor channel from one driver reading (``t`` NaN = nothing received yet)."""
    c.value = value
    c.t = t if t == t else -math.inf
    c.state = health.state
    c.cause = health.cause
    c.bad = health.bad_frames


class RigDevices:
    """Owns the drivers; ``open`` brings everything up (blocking), ``poll``/``write`` are
    the non-blocking per-cycle calls."""

    def __init__(self, cfg: RigConfig, *, laser_ports: Optional[Mapping[str, str]] = None,
                 can_bus=None, ft_endpoints: Optional[Mapping[str, tuple[str, int]]] = None):
        dcfg = cfg.devices
        h = cfg.controller.h
        stale = cfg.limits.stale_periods * h
        by_role = {l.role: l for l in dcfg.lasers}
        missing = [r for r in LASER_ROLES if r not in by_role]
        if missing:
            raise ConfigError(cfg.source, "devices.lasers", "one laser for each of " + ", ".join(LASER_ROLES) +
                              f" (missing {', '.join(missing)})")
        wheels = {d.wheel for d in dcfg.can.drives}
        if wheels != set(WHEELS):
            raise ConfigError(cfg.source, "devices.can.drives", "one drive for each wheel fl, fr, rl, rr")
        self.cfg = cfg
        self.lasers = []
        for i, role in enumerate(LASER_ROLES):
            lc = by_role[role]
            port = (laser_ports or {}).get(role, lc.port)
            if port == "sim":
                raise ConfigError(cfg.source, f"devices.lasers[{i}].port",
                                  "a serial port ('sim' is only valid with the simulated plant: rig dry-run)")
            cls = driver_class("laser", lc.driver, f"devices.lasers[{i}].driver")
            self.lasers.append(cls(lc, port=port, stale_after_s=stale))
        cls = driver_class("can", dcfg.can.driver, "devices.can.driver")
        self.drives = cls(dcfg.can, bus=can_bus, period_s=h)
        self.ft = None
        if dcfg.ft.sensors:
            cls = driver_class("ft", dcfg.ft.driver, "devices.ft.driver")
            kw = {}
            loop_cpus = set(cfg.realtime.cpu_affinity or ())
            others = sorted(set(range(os.cpu_count() or 1)) - loop_cpus) if loop_cpus else []
            if others:
                kw["poller_cpus"] = others      # keep the F/T poll process off the loop's CPU
            self.ft = cls(dcfg.ft, endpoints=dict(ft_endpoints) if ft_endpoints else None, **kw)
        self.ft_names = [s.name for s in dcfg.ft.sensors]
        # ---- channels the supervisor checks
        step = cfg.limits.laser_step_max or math.inf
        self.channels: list[Channel] = []
        for role in LASER_ROLES:
            lc = by_role[role]
            lo = lc.offset_mm * 1e-3
            self.channels.append(Channel(role, "laser", lo, lo + lc.measuring_range_mm * 1e-3, stale,
                                         step_max=step, stuck_check=True))
        w_max = 3.0 * abs(cfg.plant.v) / cfg.plant.r0 + 10.0
        for w in WHEELS:
            self.channels.append(Channel(w, "wheel", -w_max, w_max, stale, stuck_check=True))
        for n in self.ft_names:
            self.channels.append(Channel(n, "ft", -FT_RANGE[0], FT_RANGE[0], dcfg.ft.stale_s))
        self.dist = [math.nan] * 6
        self.omega = [math.nan] * 4
        self.extra_columns = [f"{n}_{c}" for n in self.ft_names for c in FT_COMPONENTS]
        self.extra_values = [math.nan] * len(self.extra_columns)
        self.converters_ok = True
        self.converters_ready = False
        self.converter_cause = ""
        self.before_laser_poll: Optional[Callable[[], None]] = None
        self._opened: list = []

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open every device; on failure close what was opened and re-raise (names the device)."""
        try:
            for d in self.lasers:
                d.open(); self._opened.append(d)
            self.drives.open(); self._opened.append(self.drives)
            if self.ft is not None:
                self.ft.open(); self._opened.append(self.ft)
        except Exception as e:
            self.close()
            if isinstance(e, (DeviceInitError, ConfigError)):
                raise
            raise DeviceInitError("devices", f"{type(e).__name__}: {e}") from e

    def close(self) -> None:
        """Zero current, disable the converters, close everything; never raises."""
        for d in reversed(self._opened):
            try:
                d.close()
            except Exception:
                pass
        self._opened.clear()

    # ------------------------------------------------------------------ cycle
    def poll(self, now: float) -> None:
        """Every device's latest samples into the supervisor channels. The drives and the
        F/T hand-off first, the lasers last (freshest); ``before_laser_poll`` (a lockstep
        simulator's "laser bytes delivered" wait) runs just before the lasers are read."""
        # _update inlined: this runs every 5 ms for 14 channels
        ch = self.channels
        ninf = -math.inf
        rd = self.drives.poll(now)
        ok, cause = True, ""
        omega = self.omega
        j = 0
        for r in rd.wheels.values():        # WHEELS order (DriveBus sorts its drives so)
            hl = r.health
            c = ch[6 + j]
            v = r.omega
            c.value = v
            t = r.t
            c.t = t if t == t else ninf
            st = hl.state
            c.state = st
            c.cause = hl.cause
            c.bad = hl.bad_frames
            omega[j] = v
            if st is _INVALID and ok:
                ok, cause = False, f"drive {r.wheel} (node {r.node_id}): {hl.cause}"
            j += 1
        if rd.bus.state is _INVALID and ok:
            ok, cause = False, f"CAN bus: {rd.bus.cause}"
        self.converters_ok = ok
        self.converter_cause = cause
        self.converters_ready = rd.ready
        if self.ft is not None:
            fr = self.ft.poll(now)
            ev = self.extra_values
            for k, n in enumerate(self.ft_names):
                r = fr[n]
                w = r.wrench
                _update(ch[10 + k], math.nan if w is None else w.fy, r.t, r.health)
                if w is not None:
                    ev[6 * k:6 * k + 6] = (w.fx, w.fy, w.fz, w.mx, w.my, w.mz)
        if self.before_laser_poll is not None:
            self.before_laser_poll()
        dist = self.dist
        i = 0
        for d in self.lasers:
            r = d.poll(now)
            c = ch[i]
            hl = r.health
            v = r.value_m
            c.value = v
            t = r.t
            c.t = t if t == t else ninf
            c.state = hl.state
            c.cause = hl.cause
            c.bad = hl.bad_frames
            dist[i] = v
            i += 1

    def write(self, currents: Sequence[float], now: float) -> None:
        self.drives.write(currents, now)

    def disable(self, now: float) -> None:
        self.drives.disable(now)
