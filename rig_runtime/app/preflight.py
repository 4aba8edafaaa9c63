"""Everything checked before anything starts: the scenario against the configured rig,
the duration, the gains (the stability gate), and the output paths.

``rig check`` runs exactly :func:`check_run` and prints the :class:`Plan`; ``rig run`` and
``rig dry-run`` call the same function before a device is opened or a log created. Every
refusal is a :class:`~rig_runtime.errors.ConfigError` (one line, exit 2) naming the file,
key or option, what was expected and (shortened) what was found.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from .. import ceilings, coupled
from ..config import RigConfig
from ..devices import require_complete
from ..errors import ConfigError
from ..memo import across_processes, by_config
from ..scenario import Scenario

# what a fault injection can do to each kind of device (the simulated devices implement
# these: sim_backend.virtual_laser/virtual_drive/virtual_ft.FAULT_KINDS; a test keeps them equal)
LASER_FAULTS = ("dropout", "corrupt", "stuck", "offset", "out_of_range", "drift")
DRIVE_FAULTS = ("dropout", "no_heartbeat", "bus_error", "out_of_range", "stuck", "offset", "corrupt", "motor_outage")
FT_FAULTS = ("dropout", "corrupt", "stuck", "offset", "out_of_range")
NO_DEVICE_FAULTS = ("stall",)       # the runtime itself


# --------------------------------------------------------------------------- scenario vs rig
def validate_scenario(cfg: RigConfig, sc: Scenario) -> None:
    """The scenario fits the configured rig: every fault names a configured device that can
    have that fault; open-loop inputs and disturbances act on controlled (supervised)
    carriers; the reference stays inside ``±limits.y_max``; open-loop inputs inside
    ``±limits.u_max``. One function for ``rig check``, ``rig run``, ``rig dry-run``."""
    f = sc.source or sc.name
    lim = cfg.limits
    devices = {l.role: ("laser", LASER_FAULTS) for l in cfg.devices.lasers}
    devices.update({d.wheel: ("drive", DRIVE_FAULTS) for d in cfg.devices.can.drives})
    devices.update({s.name: ("F/T sensor", FT_FAULTS) for s in cfg.devices.ft.sensors})
    for i, fi in enumerate(sc.faults):
        key = f"faults[{i}].device"
        if fi.kind in NO_DEVICE_FAULTS:
            if fi.device:
                raise ConfigError(f, key, f"no device for a {fi.kind} fault (it acts on the runtime)", fi.device)
            continue
        if fi.device not in devices:
            known = ", ".join(devices) or "none configured"
            raise ConfigError(f, key, f"a device of the configured rig ({known})", fi.device)
        what, kinds = devices[fi.device]
        if fi.kind not in kinds:
            raise ConfigError(f, f"faults[{i}].kind", f"a fault a {what} can have ({', '.join(kinds)})", fi.kind)
    controlled = ", ".join(cfg.controlled)
    if sc.open_loop is not None and not set(sc.open_loop.carriers) <= set(cfg.controlled):
        raise ConfigError(f, "open_loop.carrier", f"a controlled (supervised) carrier ({controlled})",
                          sc.open_loop.carrier)
    for i, d in enumerate(sc.disturbances):
        if d.carrier not in cfg.controlled:
            raise ConfigError(f, f"disturbances[{i}].carrier", f"a controlled (supervised) carrier ({controlled})",
                              d.carrier)
    for i, p in enumerate(sc.reference):
        if abs(p.y_mm) * 1e-3 > lim.y_max:
            raise ConfigError(f, f"reference[{i}].y_mm", f"|y_ref| <= limits.y_max = {lim.y_max * 1e3:g} mm", p.y_mm)
    for carrier, points in sc.references.items():
        if carrier not in cfg.controlled:
            raise ConfigError(f, f"reference.{carrier}", f"references for controlled carriers only ({controlled})",
                              carrier)
        for i, p in enumerate(points):
            if abs(p.y_mm) * 1e-3 > lim.y_max:
                raise ConfigError(f, f"reference.{carrier}[{i}].y_mm",
                                  f"|y_ref| <= limits.y_max = {lim.y_max * 1e3:g} mm", p.y_mm)
    validate_speed(cfg, sc)
    if sc.open_loop is not None:
        for i, (_, u) in enumerate(sc.open_loop.steps):
            if abs(u) > lim.u_max:
                raise ConfigError(f, f"open_loop.steps[{i}]", f"|u| <= limits.u_max = {lim.u_max:g} A", u)
        for i, s in enumerate(sc.open_loop.sine or ()):
            peak = abs(s.bias_A) + abs(s.amplitude_A)
            if peak > lim.u_max:
                raise ConfigError(f, f"open_loop.sine[{i}]",
                                  f"|bias_A| + |amplitude_A| <= limits.u_max = {lim.u_max:g} A", peak)


def validate_speed(cfg: RigConfig, sc: Scenario) -> None:
    """The scenario's speed profile fits the config: every point within the hardware's
    ``v_max``; and, where the controller runs (not an open-loop experiment, whose input does
    not depend on the gains), within ``controller.schedule.v_range`` (the range the stability
    gate covered), or equal to ``plant.v`` without a schedule (fixed gains are analysed at
    that speed only). The profile is piecewise linear between its points: checking them suffices."""
    f = sc.source or sc.name
    v_max = cfg.hardware.ceilings.v_max
    s = cfg.controller.schedule
    for i, p in enumerate(sc.speed):
        key = f"speed[{i}].v"
        if not abs(p.v) <= v_max:
            raise ConfigError(f, key, f"|v| <= the hardware's v_max = {v_max:g} m/s ({cfg.hardware.source})", p.v)
        if sc.open_loop is not None:
            continue
        if s is None and p.v != cfg.plant.v:
            raise ConfigError(f, key, f"plant.v = {cfg.plant.v:g} m/s (the config has fixed gains, no "
                              "controller.schedule: the speed cannot change)", p.v)
        if s is not None and not s.v_range[0] <= p.v <= s.v_range[1]:
            raise ConfigError(f, key, f"a speed within controller.schedule.v_range = "
                              f"[{s.v_range[0]:g}, {s.v_range[1]:g}] m/s (the range the stability gate covers)", p.v)


def check_duration(value: Optional[float], what: str = "--duration") -> None:
    """A duration is a finite number of seconds > 0 (None: the default applies)."""
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ConfigError(None, what, "a finite number of seconds > 0", value)


# --------------------------------------------------------------------------- output paths
def _writable_dir(d: Path) -> str | None:
    """Why ``d`` cannot take a new file (None: it can). Tried, not guessed from mode bits
    (root, read-only mounts): a probe file is created and removed at once."""
    if not d.exists():
        return f"directory {d} does not exist"
    if not d.is_dir():
        return f"{d} is not a directory"
    try:
        fd, probe = tempfile.mkstemp(prefix=".rig-probe-", dir=d)
    except OSError as e:
        return f"directory {d} is not writable ({e.strerror})"
    os.close(fd)
    os.unlink(probe)
    return None


def _creatable_dir(d: Path) -> str | None:
    """Why directory ``d`` can neither be used nor created (None: it can)."""
    if d.exists():
        return _writable_dir(d)
    anc = d.parent
    while not anc.exists() and anc.parent != anc:
        anc = anc.parent
    return _writable_dir(anc) if anc.is_dir() else f"{anc} is not a directory"


def check_new_file(path: str | Path, what: str, *, create_dir: bool = False) -> None:
    """A file to be created: it does not exist, its directory exists (or, with
    ``create_dir``, can be created) and is writable."""
    p = Path(path)
    if p.exists() or p.is_symlink():
        raise ConfigError(None, what, "a file that does not exist yet (logs are never overwritten)", str(p))
    why = (_creatable_dir if create_dir else _writable_dir)(p.parent)
    if why:
        raise ConfigError(None, what, f"a path in a writable directory ({why})", str(p))


def check_output_file(path: str | Path, what: str, *, create_dir: bool = False) -> None:
    """A file to be (over)written: not a directory, its directory writable (or creatable)."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(None, what, "a file name (this is a directory)", str(p))
    if p.exists() and not os.access(p, os.W_OK):
        raise ConfigError(None, what, "a writable file", str(p))
    why = (_creatable_dir if create_dir else _writable_dir)(p.parent)
    if why:
        raise ConfigError(None, what, f"a path in a writable directory ({why})", str(p))


def _importable(module: str) -> bool:
    """Whether ``import module`` succeeds in a fresh interpreter like this one (its own
    session: a stop signal meant for this run does not reach it)."""
    try:
        r = subprocess.run([sys.executable, "-c", f"import {module}"], stdin=subprocess.DEVNULL,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    except OSError:
        return False
    return r.returncode == 0


def check_plot_dir(path: str | Path, what: str) -> None:
    """A directory for PNG plots: matplotlib importable, the path a directory (or creatable).
    Imported in a child interpreter, not here: ``rig dry-run --report`` checks this in the
    process that then runs the loop, which must not load matplotlib (plots come after the run)."""
    if not _importable("matplotlib"):
        raise ConfigError(None, what, "matplotlib installed for plots (pip install 'rig-runtime[plot]')")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(None, what, "a directory (this is a file)", str(p))
    why = _creatable_dir(p)
    if why:
        raise ConfigError(None, what, f"a writable directory ({why})", str(p))


# --------------------------------------------------------------------------- the whole check
@dataclass(frozen=True)
class Plan:
    """What a run would do, once every check passed (``rig check`` prints it)."""

    cfg: RigConfig
    scenario: Optional[Scenario]
    duration_s: float            # inf: until SIGINT/SIGTERM
    duration_from: str
    log: Optional[Path]
    slowest: dict                # damping D -> the slowest sampled eigenvalue (1/s); a vehicle config:
                                 # "coupled" -> (v, |z|, speeds analysed, held band) of the largest |z|


def _gate(cfg: RigConfig) -> bool:
    from .. import analysis
    analysis.stability_gate(cfg)        # raises UnstableLoopError: nothing is kept
    return True


def _sampled_loop(cfg: RigConfig, damping: float):
    from .. import analysis
    return analysis.sampled_loop(cfg, damping)


def _slowest(cfg: RigConfig) -> dict:
    """``Plan.slowest`` (plain floats): a vehicle config's largest sampled |z| of the coupled
    analysis, else the slowest sampled eigenvalue at D_min and D_max."""
    if coupled.applies(cfg):
        r = coupled_analysis(cfg)
        worst = max(r.points, key=lambda p: p.spectral_radius)
        band = tuple(float(b) for b in r.band) if r.band else None
        return {"coupled": (float(worst.v), float(worst.spectral_radius), len(r.points), band)}
    return {float(D): float(max(sampled_loop(cfg, D).real)) for D in (cfg.plant.D_min, cfg.plant.D_max)}


# Pure functions of the config, once per config in a process (rig_runtime/memo.py): a run
# passes the gate here and again in the runner; a warm worker runs the same config again.
# The gate's pass and the plan's eigenvalues are also kept on disk for the next process
# (memo.across_processes: keyed by the config's every value and the code's bytes; a refusal
# is never kept): a dry run from the shell then imports no scipy for them.
stability_gate = by_config(across_processes("stability-gate", _gate))     # analysis.stability_gate
coupled_analysis = by_config(coupled.analyse)
sampled_loop = by_config(_sampled_loop)         # analysis.sampled_loop(cfg, D)
slowest = by_config(across_processes("plan-slowest", _slowest))


def check_run(cfg: RigConfig, scenario: Optional[Scenario], duration_s: Optional[float], *,
              log: Optional[Path] = None, log_is_default: bool = False,
              report: Optional[str] = None) -> Plan:
    """Every check a run makes before it opens anything (``rig check`` is exactly this):
    the device set, the scenario against the rig, the duration, the stability gate, the
    log path (and the report directory). Returns the :class:`Plan`."""
    require_complete(cfg)
    if scenario is not None:
        validate_scenario(cfg, scenario)
    check_duration(duration_s)
    stability_gate(cfg)
    if log is not None:
        check_new_file(log, "--log", create_dir=log_is_default)
    if report is not None:
        check_plot_dir(report, "--report")
    if duration_s is not None:
        d, src = duration_s, "--duration"
    elif scenario is not None:
        d, src = scenario.duration_s, "the scenario's duration_s"
    else:
        d, src = math.inf, "until SIGINT/SIGTERM"
    return Plan(cfg, scenario, d, src, Path(log) if log is not None else None, slowest(cfg))


def describe(plan: Plan) -> list[str]:
    """``rig check``'s report: config, hardware, carriers, gains, limits with their
    ceilings, scenario, duration, log."""
    cfg, sc = plan.cfg, plan.scenario
    c = cfg.controller
    g = c.decoupled if c.law == "decoupled" else c.pipd
    hw = cfg.hardware
    out = [f"config: {cfg.source}",
           f"hardware: {hw.source}" + (f" ({hw.name})" if hw.name else ""),
           f"controlled carriers: {', '.join(cfg.controlled)}"]
    if c.law == "p":
        out.append(f"law: p   K_P = {c.K_P:g} A/m   h = {c.h:g} s")
    else:
        out.append(f"law: {c.law}   K_P,y = {g.K_P_y:g}  K_I,y = {g.K_I_y:g}  K_P,psi = {g.K_P_psi:g}  "
                   f"K_D,psi = {g.K_D_psi:g}  T_f,psi = {g.T_f_psi:g} s   h = {c.h:g} s")
        if c.law == "decoupled":
            out.append(f"  across the carriers: b_y = {g.b_y:g}  K_x,y = {g.K_x_y:g} rad/m  T_x,y = {g.T_x_y:g} s  "
                       f"K_I,psi = {g.K_I_psi:g} A/(rad s)")
        for who in ("front", "rear"):
            own = getattr(c, who)
            if own is not None:
                out.append(f"  {who} carrier's own gains: K_P,y = {own.K_P_y:g}  K_I,y = {own.K_I_y:g}  "
                           f"K_P,psi = {own.K_P_psi:g}  K_D,psi = {own.K_D_psi:g}  T_f,psi = {own.T_f_psi:g} s")
    if c.schedule is not None:
        s = c.schedule
        out.append(f"schedule: outer gains x v_d/v, v_d = {coupled.design_speed(cfg):g} m/s; v_range "
                   f"[{s.v_range[0]:g}, {s.v_range[1]:g}] m/s; held for |v| < {s.v_min:g} m/s")
    if "coupled" in plan.slowest:
        v, r, n, band = plan.slowest["coupled"]
        held = f"; held for |v| < {band[1]:g} m/s" if band else ""
        out.append(f"sampled closed loop (coupled, carriers in contact: {', '.join(cfg.plant.in_contact)}): "
                   f"stable at {n} speed(s) in both directions in the gate's damping cases (largest |z| = {r:.6f} "
                   f"at v = {v:+g} m/s{held})")
    else:
        out.append("sampled closed loop: stable (slowest eigenvalue " +
                   ", ".join(f"{ev:+.3f} 1/s at D = {D:g}" for D, ev in plan.slowest.items()) + ")")
    out.append("limits (value <= hardware ceiling):")
    rows = list(ceilings.bounds(cfg))
    w = max(len(b.key) for b in rows)
    for b in rows:
        v = "off" if b.value is None else f"{b.value:g}"
        out.append(f"  {b.key:<{w}}  {v:>8} <= {b.ceiling:<8g} {b.unit}")
    lim = cfg.limits
    out.append(f"  (no ceiling: stuck_periods {lim.stuck_periods}, laser_step_max {lim.laser_step_max} m, "
               f"corrupt_cycles {lim.corrupt_cycles})")
    if sc is None:
        out.append("scenario: none (hold y_ref = 0)")
    else:
        parts = []
        for who in (cfg.controlled if sc.references else ("",)):
            ys = [p.y_mm for p in (sc.reference_for(who) if who else sc.reference)]
            parts.append(f"reference{' ' + who if who else ''} {len(ys)} point(s), "
                         f"y_ref in [{min(ys):g}, {max(ys):g}] mm")
        if sc.speed:
            vs = [p.v for p in sc.speed]
            parts.append(f"speed profile {len(vs)} point(s), v in [{min(vs):g}, {max(vs):g}] m/s")
        if sc.open_loop is not None:
            parts.append(f"open loop on the {sc.open_loop.carrier} carrier")
        parts.append(f"{len(sc.disturbances)} disturbance(s)")
        parts.append(f"{len(sc.faults)} fault(s)" + (f": {', '.join(f'{x.kind} {x.device}'.strip() for x in sc.faults)}"
                                                     if sc.faults else ""))
        out.append(f"scenario: {sc.name} ({sc.source}): " + "; ".join(parts))
    dur = "until SIGINT/SIGTERM" if math.isinf(plan.duration_s) else f"{plan.duration_s:g} s ({plan.duration_from})"
    out.append(f"duration: {dur}")
    if plan.log is not None:
        out.append(f"log: {plan.log}" + ("" if plan.log.parent.exists() else f" (directory {plan.log.parent} will be created)"))
    return out
