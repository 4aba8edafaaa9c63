"""The hardware description and its ceilings: what the machine can take, which every
limit of a run config may only tighten.

The hardware description is the ``hardware:`` section, in a file of its own
(``configs/hardware.yaml``) that the run configs include. It states the drives' rated
current and the largest value each safety limit may have on this machine (mechanical
stops less the travel while stopping, the longest blind and stopping times that are
still safe). :func:`check` compares a whole config against it and refuses the first
limit that loosens a ceiling, naming the key, its value and the ceiling; it runs in
``RigConfig.__post_init__``, so no config object — loaded or made with
``dataclasses.replace`` — exists that loosens one. docs/safety.md lists the ceilings and
says how an operator changes them.

This module does not import the config module (which imports it): :func:`check` reads
the config by attribute.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterator

from .errors import ConfigError
from .schema import check as _check
from .schema import nonneg, positive


@dataclass(frozen=True, kw_only=True)
class Ceilings:
    """The largest value each limit may have on this machine (SI; times in s or ms as named)."""

    psi_max: float = _check(positive)          # rad: |ψ| the supervisor may let a carrier reach
    y_max: float = _check(positive)            # m: |y| likewise
    psi_rate_max: float = _check(positive)     # rad/s: the yaw-rate check may not be looser (nor off)
    du_max: float = _check(positive)           # A/s: command rate limit
    stale_s: float = _check(positive)          # s: longest a sample (laser, encoder, drive TPDO) may be old and used
    overrun_s: float = _check(positive)        # s: longest run of missed deadlines before the fault
    stop_ramp_s: float = _check(nonneg)        # s: longest ramp to zero current on a clean stop
    drive_watchdog_ms: float = _check(positive)     # ms: drive cuts its current without SYNC/RPDO
    heartbeat_timeout_ms: float = _check(positive)  # ms: longest heartbeat silence either side tolerates
    v_max: float = _check(positive, default=2.0)    # m/s: the rollers' top surface speed, either direction


@dataclass(frozen=True, kw_only=True)
class HardwareDescription:
    """The ``hardware:`` section: the machine, not the run."""

    name: str = ""
    drive_rated_current_A: float = _check(positive)   # the converters' rated current; each wheel gets ±u/2
    ceilings: Ceilings
    source: str = ""                                  # file it was loaded from (set by config.load)


@dataclass(frozen=True)
class Bound:
    """One limit of a config and its ceiling: ``value <= ceiling`` must hold."""

    key: str            # config key path (the one to change)
    value: Any          # the config's value (None: the check is switched off)
    ceiling: float      # in the key's own unit
    unit: str
    origin: str         # where the ceiling comes from (hardware key, and how it was converted)


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def bounds(cfg: Any) -> Iterator[Bound]:
    """Every limit of ``cfg`` with its ceiling from ``cfg.hardware`` (also what ``rig check`` prints)."""
    hw: HardwareDescription = cfg.hardware
    c = hw.ceilings
    lim, h, can = cfg.limits, cfg.controller.h, cfg.devices.can
    hk = "hardware.ceilings."
    rated = hw.drive_rated_current_A
    for i, d in enumerate(can.drives):
        yield Bound(f"devices.can.drives[{i}].rated_current_A", d.rated_current_A, rated, "A",
                    "hardware.drive_rated_current_A")
    lowest = min([rated] + [d.rated_current_A for d in can.drives])
    origin = "2 x hardware.drive_rated_current_A (each wheel carries ±u/2)" if lowest == rated else \
        f"2 x the lowest devices.can.drives[].rated_current_A ({_fmt(lowest)} A; each wheel carries ±u/2)"
    yield Bound("limits.u_max", lim.u_max, 2.0 * lowest, "A", origin)
    yield Bound("limits.psi_max", lim.psi_max, c.psi_max, "rad", hk + "psi_max")
    yield Bound("limits.y_max", lim.y_max, c.y_max, "m", hk + "y_max")
    yield Bound("limits.psi_rate_max", lim.psi_rate_max, c.psi_rate_max, "rad/s", hk + "psi_rate_max")
    yield Bound("limits.du_max", lim.du_max, c.du_max, "A/s", hk + "du_max")

    def periods(seconds: float) -> float:
        q = seconds / h + 1e-9
        return math.floor(q) if q < 2.0 ** 62 else q      # whole periods (a huge ceiling stays a float)
    per = f"periods of h = {_fmt(h)} s"
    yield Bound("limits.stale_periods", lim.stale_periods, periods(c.stale_s), per,
                f"{hk}stale_s = {_fmt(c.stale_s)} s / h")
    yield Bound("limits.overrun_burst", lim.overrun_burst, periods(c.overrun_s), per,
                f"{hk}overrun_s = {_fmt(c.overrun_s)} s / h")
    yield Bound("limits.stop_ramp_s", lim.stop_ramp_s, c.stop_ramp_s, "s", hk + "stop_ramp_s")
    yield Bound("|plant.v|", abs(cfg.plant.v), c.v_max, "m/s", hk + "v_max")
    sch = cfg.controller.schedule
    if sch is not None:
        yield Bound("|controller.schedule.v_range|", max(abs(v) for v in sch.v_range), c.v_max, "m/s",
                    hk + "v_max")
    yield Bound("devices.can.watchdog_ms", can.watchdog_ms, c.drive_watchdog_ms, "ms", hk + "drive_watchdog_ms")
    # the drives' heartbeat consumer time (how long a drive runs on after the runtime died)
    # and the runtime's timeout for each drive's heartbeat: producer time x factor
    f = can.heartbeat_timeout_factor
    hb = f"{hk}heartbeat_timeout_ms"
    yield Bound("devices.can.heartbeat_ms x heartbeat_timeout_factor", can.heartbeat_ms * f,
                c.heartbeat_timeout_ms, "ms (the drives' heartbeat consumer time)", hb)
    for i, d in enumerate(can.drives):
        yield Bound(f"devices.can.drives[{i}].heartbeat_ms x heartbeat_timeout_factor",
                    d.heartbeat_ms * f, c.heartbeat_timeout_ms, "ms (the runtime's timeout for this drive)", hb)


def violation(b: Bound) -> str | None:
    """What is wrong with ``b`` (None: it holds)."""
    if b.value is None:
        return f"a value (this check cannot be switched off on this machine: ceiling {_fmt(b.ceiling)} {b.unit})"
    if b.value > b.ceiling:
        return f"at most {_fmt(b.ceiling)} {b.unit}"
    return None


def check(cfg: Any) -> None:
    """Refuse (ConfigError, file left to the caller) the first limit of ``cfg`` above its ceiling."""
    src = cfg.hardware.source or "the hardware description"
    for b in bounds(cfg):
        what = violation(b)
        if what is not None:
            raise ConfigError(None, b.key, f"{what}: the hardware ceiling is {b.origin} ({src})", b.value)
