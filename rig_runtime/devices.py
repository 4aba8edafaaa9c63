"""The rig's devices as the loop sees them: six lasers, the drive bus (wheel speeds in,
currents out) and the force–torque sensors, behind one lifecycle (``configure``,
``activate``, ``poll``, ``write``, ``deactivate``, ``close``).

Drivers are chosen by name from the config (:mod:`rig_runtime.registry`, imported lazily).
A backend decides only what is on the other end of each transport: the constructor takes
the laser ports, a python-can bus object and the F/T endpoints in place of the config's.
"""

from __future__ import annotations

import math
from typing import Mapping, NamedTuple, Optional, Sequence

from .clock import helper_cpus
from .config import LASER_ROLES, WHEELS, RigConfig
from .errors import ConfigError, DeviceInitError
from .hardware import Freshness
from .registry import driver_class
from .safety import Channel, Converters

FT_COMPONENTS = ("fx", "fy", "fz", "mx", "my", "mz")
FT_RANGE = (300.0, 30.0)    # FT 300 class: ±300 N, ±30 N m (rated range)
_NO_WRENCH = (math.nan,) * len(FT_COMPONENTS)
_INVALID = Freshness.INVALID


class Reading(NamedTuple):
    """Everything one poll brought, addressed by name: a sample per supervisor channel
    (lasers by role, wheels by wheel, F/T sensors by name; a :class:`ChannelSample`, the
    fields of :class:`~rig_runtime.safety.Sample`), each channel's latest value by the same
    name (what the geometry reads), the F/T wrench components (``RigDevices.extra_columns``
    order, the log's columns) and the converters.

    The mappings, the samples in them and the wrench are the device set's own, made once at
    construction (names resolved there, not per cycle) and filled in place by every poll:
    they hold this cycle's values until the next poll — copy what must outlive the cycle."""
    t: float
    samples: Mapping[str, "ChannelSample"]
    values: Mapping[str, float]
    wrench: Sequence[float]
    converters: Converters


class ChannelSample:
    """One channel's sample as the latest poll filed it, by the field names of
    :class:`~rig_runtime.safety.Sample` (what the supervisor reads): the value, the time it
    arrived (NaN: never), the driver's health and, for a device answering the runtime's
    requests, the requests unanswered (-1: free-running). One per channel, made at
    construction and filled in place by every poll (no object per sample and cycle)."""

    __slots__ = ("value", "t", "health", "unanswered")

    def __init__(self) -> None:
        self.value, self.t, self.health, self.unanswered = math.nan, math.nan, None, -1


class _FTSlot:
    """An F/T sensor's part of the poll: its name, its first wrench column, its sample and
    what the latest poll filed (the wrench, its time and health; a NaN time: nothing yet)."""

    __slots__ = ("name", "column", "sample", "wrench", "t", "health")

    def __init__(self, name: str, column: int, sample: ChannelSample) -> None:
        self.name, self.column, self.sample = name, column, sample
        self.wrench, self.t, self.health = None, math.nan, None


def require_complete(cfg: RigConfig) -> None:
    """The device set a run needs: a laser for every role, a drive for every wheel."""
    dcfg = cfg.devices
    have = {l.role for l in dcfg.lasers}
    missing = [r for r in LASER_ROLES if r not in have]
    if missing:
        raise ConfigError(cfg.source, "devices.lasers", "one laser for each of " + ", ".join(LASER_ROLES) +
                          f" (missing {', '.join(missing)})")
    wheels = {d.wheel for d in dcfg.can.drives}
    if wheels != set(WHEELS):
        raise ConfigError(cfg.source, "devices.can.drives", "one drive for each wheel fl, fr, rl, rr")


class RigDevices:
    """Owns the drivers. ``configure`` brings everything up without power (blocking);
    ``activate`` (the supervisor's ARM) enables the power stages; ``poll``/``write`` are the
    non-blocking per-cycle calls; ``deactivate`` is the safe stop; ``close`` releases all."""

    def __init__(self, cfg: RigConfig, *, laser_ports: Optional[Mapping[str, str]] = None,
                 can_bus=None, ft_endpoints: Optional[Mapping[str, tuple[str, int]]] = None):
        dcfg = cfg.devices
        h = cfg.controller.h
        stale = cfg.limits.stale_periods * h
        require_complete(cfg)
        by_role = {l.role: l for l in dcfg.lasers}
        self.cfg = cfg
        self._stale = stale
        self.lasers = []
        for i, role in enumerate(LASER_ROLES):
            lc = by_role[role]
            port = (laser_ports or {}).get(role, lc.port)
            if port == "sim":
                raise ConfigError(cfg.source, f"devices.lasers[{i}].port",
                                  "a serial port ('sim' is only valid with the simulated plant: rig dry-run)")
            cls = driver_class("laser", lc.driver, f"devices.lasers[{i}].driver")
            self.lasers.append(cls(lc, port=port))
        cls = driver_class("can", dcfg.can.driver, "devices.can.driver")
        self.drives = cls(dcfg.can, bus=can_bus, period_s=h)
        self.ft = None
        if dcfg.ft.sensors:
            cls = driver_class("ft", dcfg.ft.driver, "devices.ft.driver")
            kw = {}
            others = helper_cpus(cfg.realtime)
            if others:
                kw["poller_cpus"] = others      # keep an F/T poll process off the loop's CPU
            self.ft = cls(dcfg.ft, endpoints=dict(ft_endpoints) if ft_endpoints else None, **kw)
        self.ft_names = [s.name for s in dcfg.ft.sensors]
        self.extra_columns = [f"{n}_{c}" for n in self.ft_names for c in FT_COMPONENTS]
        self._configured: list = []
        # what poll() fills in place (Reading), made here: one sample and one value per channel
        # (the wheels, the F/T sensors, the lasers), the wrench columns
        wheels = [d.wheel for d in dcfg.can.drives]
        names = [*wheels, *self.ft_names, *LASER_ROLES]
        self._samples: dict[str, ChannelSample] = {n: ChannelSample() for n in names}
        self._values: dict[str, float] = dict.fromkeys(names, math.nan)
        self._wrench = [math.nan] * len(self.extra_columns)
        # per F/T sensor what the latest poll filed: while its poller has nothing new (it runs
        # slower than the loop) the sensor's entries stay as they are
        self._ft_slots = [_FTSlot(n, len(FT_COMPONENTS) * i, self._samples[n]) for i, n in enumerate(self.ft_names)]
        # each laser driver with its role's sample (the lasers were made in LASER_ROLES order)
        self._laser_slots = [(d, role, self._samples[role]) for d, role in zip(self.lasers, LASER_ROLES)]

    def channels(self) -> list[Channel]:
        """The supervisor's channels, named as :meth:`poll` names its samples, with each
        device's plausible range."""
        cfg = self.cfg
        by_role = {l.role: l for l in cfg.devices.lasers}
        step = cfg.limits.laser_step_max or math.inf
        out = []
        for role in LASER_ROLES:
            lc = by_role[role]
            lo = lc.offset_mm * 1e-3
            out.append(Channel(role, "laser", lo, lo + lc.measuring_range_mm * 1e-3, self._stale,
                               step_max=step, stuck_check=True))
        sch = cfg.controller.schedule      # a vehicle runs over its schedule's speed range
        v = max(abs(cfg.plant.v), *(abs(x) for x in sch.v_range)) if sch is not None else abs(cfg.plant.v)
        w_max = 3.0 * v / cfg.plant.r0 + 10.0
        for w in WHEELS:
            out.append(Channel(w, "wheel", -w_max, w_max, self._stale, stuck_check=True))
        for n in self.ft_names:
            out.append(Channel(n, "ft", -FT_RANGE[0], FT_RANGE[0], cfg.limits.ft_stale_s))
        return out

    # ------------------------------------------------------------------ lifecycle
    def configure(self) -> None:
        """Configure every device (no power), the drives last; on failure close what was
        configured and re-raise (the error names the device)."""
        try:
            for d in self.lasers:
                d.configure(); self._configured.append(d)
            if self.ft is not None:
                self.ft.configure(); self._configured.append(self.ft)
            # the drives last: their heartbeat consumers run from here, and the loop's first
            # write (the runtime's first heartbeat) must follow within the consumer time —
            # not after, say, an F/T poll process has been spawned
            self.drives.configure(); self._configured.append(self.drives)
        except Exception as e:
            self.close()
            if isinstance(e, (DeviceInitError, ConfigError)):
                raise
            raise DeviceInitError("devices", f"{type(e).__name__}: {e}") from e

    def activate(self, now: float) -> None:
        """Power stages on (non-blocking); called by the supervisor's ARM transition."""
        self.drives.activate(now)

    def deactivate(self, now: float) -> None:
        """Zero, quick stop, disable (non-blocking); FAULT and the end of a stop."""
        self.drives.deactivate(now)

    def isolate(self, wheel: str, now: float) -> None:
        """One drive quick-stopped and disabled while the others run (RECONFIGURED)."""
        self.drives.isolate(wheel, now)

    def resume(self, now: float) -> None:
        """Communication on, power stages off, as after ``configure()`` (an operator's fault
        reset; the supervisor calls it)."""
        self.drives.resume(now)

    def close(self) -> None:
        """Deactivate and close everything; never raises."""
        for d in reversed(self._configured):
            try:
                d.close()
            except Exception:
                pass
        self._configured.clear()

    # ------------------------------------------------------------------ cycle
    def poll(self, now: float) -> Reading:
        """Every device's latest samples by name: the drives and the F/T hand-off first, the
        lasers last (freshest). Fills the device set's own mappings in place (:class:`Reading`)."""
        samples, values = self._samples, self._values
        rd = self.drives.poll(now)
        ok, cause = True, ""
        drives = not_enabled = ()   # per wheel: each INVALID drive's (wheel, cause), each power stage not enabled
        torque = []                 # per wheel: (wheel, its drive's reported current)
        for w, r in rd.wheels.items():
            v = values[w] = r.omega
            h = r.health
            s = samples[w]
            s.value, s.t, s.health = v, r.t, h
            s.unanswered = r.syncs_unanswered
            torque.append((w, r.current_A))
            if h.state is _INVALID:
                why = f"drive {r.wheel} (node {r.node_id}): {h.cause}"
                drives += ((w, why),)
                if ok:
                    ok, cause = False, why
                not_enabled += (w,)
            elif not r.enabled:                 # as the driver's `enabled`
                not_enabled += (w,)
        bus = rd.bus
        bus_ok = bus.state is not _INVALID
        if ok and not bus_ok:
            ok, cause = False, f"CAN bus: {bus.cause}"
        if self.ft is not None:
            fr = self.ft.poll(now)
            wrench = self._wrench
            for slot in self._ft_slots:
                r = fr[slot.name]
                w, t, h = r.wrench, r.t, r.health
                if w is not slot.wrench or h is not slot.health or not t == slot.t:   # else: in place already
                    i = slot.column
                    if w is None:
                        fy = math.nan
                        wrench[i:i + 6] = _NO_WRENCH
                    else:
                        fy = w.fy
                        wrench[i:i + 6] = (w.fx, fy, w.fz, w.mx, w.my, w.mz)      # FT_COMPONENTS
                    s = slot.sample
                    s.value, s.t, s.health = fy, t, h
                    values[slot.name] = fy
                    slot.wrench, slot.t, slot.health = w, t, h
        for d, role, s in self._laser_slots:
            r = d.poll(now)
            v = values[role] = r.value_m
            s.value, s.t, s.health = v, r.t, r.health
        converters = Converters(ok=ok, cause=cause, enabled=rd.enabled, bus_error_t=rd.bus_error_t,
                                bus_cause=bus.cause, drives=drives, not_enabled=not_enabled, bus_ok=bus_ok,
                                torque=tuple(torque))
        return Reading(t=now, samples=samples, values=values, wrench=self._wrench, converters=converters)

    def write(self, currents: Mapping[str, float], now: float) -> None:
        """Each wheel's current (A) by wheel name."""
        self.drives.write(currents, now)

    def counters(self) -> dict[str, dict[str, int]]:
        """Each device's statistics (status views, tests)."""
        out = {d.name: d.counters() for d in self.lasers}
        out[self.drives.name] = self.drives.counters()
        if self.ft is not None:
            out[self.ft.name] = self.ft.counters()
        return out
