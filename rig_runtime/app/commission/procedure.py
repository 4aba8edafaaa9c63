"""The commissioning procedure: prompts, the passive windows, the bumps, the judgement, in
that order, against a configured-by-us device set. ``run`` is the same for the rig and for
the simulated rig; ``run_lockstep`` builds the simulated rig in process (tests)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

from ...clock import Clock
from ...config import LASER_ROLES, WHEELS, RigConfig
from . import CHECKS
from .judge import Item, judge_bump, judge_encoders, judge_lasers
from .session import bump, passive

BUMP_WIRE_A = 0.3           # each wheel's current during a bump (A); the differential u is twice it
BUMP_S = 0.2                # the pulse
AFTER_S = 0.3               # zero current after the pulse, still armed: the yaw angle's answer
PASSIVE_S = 8.0             # the operator's window for the passive motions


def laser_prompt(seconds: float) -> str:
    return (f"lasers (power stages off): within the next {seconds:g} s, one after the other, each by hand "
            "and let go again: push the vehicle about 2 mm to the left (+y, away from the lateral lasers); "
            "turn the rear carrier nose-left by a few mrad; turn the front carrier nose-right by a few mrad.")


def encoder_prompt(cfg: RigConfig) -> str:
    return (f"encoders (power stages off): the rollers turning forward at v = {cfg.plant.v:+.2f} m/s "
            f"(the roller drive; the wheels' drives stay off); the wheels roll at "
            f"{cfg.plant.v / cfg.plant.r0:+.2f} rad/s.")


def bump_prompt() -> str:
    return (f"bump tests: the rollers turning at v, the rig clear of people; for each bump the supervisor "
            f"arms (power stages on), a pulse of ±{BUMP_WIRE_A:.1f} A per wheel for {BUMP_S:.1f} s on one "
            f"wheel pair, then zero current and the power stages off again.")


@dataclass(frozen=True)
class Report:
    items: tuple[Item, ...]
    checks: tuple[str, ...]
    sessions: tuple[dict, ...] = ()

    @property
    def passed(self) -> bool:
        return bool(self.items) and all(i.passed for i in self.items)

    def as_dict(self) -> dict:
        return {"result": "pass" if self.passed else "fail", "checks": list(self.checks),
                "items": [i.as_dict() for i in self.items], "sessions": list(self.sessions)}

    def text(self) -> str:
        out = []
        for i in self.items:
            vals = ", ".join(f"{k}={v:+.3f}" if isinstance(v, float) and math.isfinite(v) else f"{k}={v}"
                             for k, v in i.measured.items())
            out.append(f"{'PASS' if i.passed else 'FAIL'} {i.name}: {vals}")
            out += [f"    likely fault: {f}" for f in i.faults]
            if i.note:
                out.append(f"    note: {i.note}")
        out.append(f"commissioning {'passed' if self.passed else 'FAILED'} ({', '.join(self.checks)})")
        return "\n".join(out)


def run(cfg: RigConfig, devices, clock: Clock, checks: Sequence[str] = CHECKS,
        confirm: Callable[[str], bool] = lambda text: True, say: Callable[[str], None] = lambda s: None,
        passive_s: float = PASSIVE_S, stops=None, log_prefix: Optional[Path] = None,
        when_full: str = "drop") -> Report:
    """Configure the devices (no power), then each selected check in ``CHECKS`` order; the
    devices are closed on every path. Each bump is recorded as a normal log,
    ``<log_prefix>-bump-<carrier>.h5`` (None: not recorded). ``confirm(prompt)``: the operator's go (False: that
    check is not run, and fails)."""
    h = cfg.controller.h
    items: list[Item] = []
    sessions: list[dict] = []
    node_ids = {d.wheel: d.node_id for d in cfg.devices.can.drives}
    try:
        devices.configure()
        if "lasers" in checks:
            if confirm(laser_prompt(passive_s)):
                items.append(judge_lasers(passive(devices, clock, h, passive_s, LASER_ROLES, stops)))
            else:
                items.append(Item("lasers", False, {}, ("not run: the operator declined",)))
        if "encoders" in checks:
            if confirm(encoder_prompt(cfg)):
                items.append(judge_encoders(passive(devices, clock, h, 1.0, WHEELS, stops), cfg))
            else:
                items.append(Item("encoders", False, {}, ("not run: the operator declined",)))
        bumps = [c for c in ("rear", "front") if f"bump-{c}" in checks]
        if bumps and not confirm(bump_prompt()):
            items += [Item(f"bump-{c}", False, {}, ("not run: the operator declined",)) for c in bumps]
            bumps = []
        lasers = next((i for i in items if i.name == "lasers"), None)
        for c in bumps:
            if stops is not None and stops.requested:
                break
            u = 2 * BUMP_WIRE_A
            say(f"bump {c}: u = {u:+.2f} A ({BUMP_WIRE_A:+.2f} A / {-BUMP_WIRE_A:+.2f} A on the wire) for {BUMP_S} s")
            log = None if log_prefix is None else Path(f"{log_prefix}-bump-{c}.h5")
            rec, res = bump(cfg, devices, clock, c, u, BUMP_S, AFTER_S, log_path=log, when_full=when_full, stops=stops)
            res["log"] = str(log) if log is not None else None
            devices.resume(clock.now())     # the stop left the drives pre-operational: back to configure()'s state
            sessions.append({"check": f"bump-{c}", **res})
            if res["final_state"] != "IDLE" or res["faults"]:
                why = "; ".join(f"{f['device']} {f['check']}" for f in res["faults"]) or "; ".join(res["arm_blockers"][:3])
                items.append(Item(f"bump-{c}", False, {}, (f"the bump session ended in {res['final_state']} ({why})",)))
                continue
            yaw_ok = None if lasers is None else not any(r in f for f in lasers.faults for r in (f"s_{c[0]}l", f"s_{c[0]}r"))
            items.append(judge_bump(c, u, rec, cfg, node_ids, yaw_lasers_ok=yaw_ok))
    finally:
        devices.close()
    return Report(tuple(items), tuple(c for c in CHECKS if c in checks), tuple(sessions))


def run_lockstep(cfg: RigConfig, checks: Sequence[str] = CHECKS, *, seed: Optional[int] = None,
                 passive_s: float = 2.2, prepare: Optional[Callable] = None,
                 log_prefix: Optional[Path] = None) -> Report:
    """``run`` against the simulated rig in this process, on the lockstep clock (the
    simulated operator moves the vehicle: ``sim: {operator: commission}`` is set here).
    ``prepare(sim)`` runs before anything is configured (tests tap the CAN wire)."""
    import dataclasses

    from sim_backend.rig import SimulatedRig

    from ...clock import LockstepClock
    from ...devices import RigDevices
    sim_cfg = dataclasses.replace(cfg, sim={**(cfg.sim or {}), "operator": "commission"})
    sim = SimulatedRig(sim_cfg, None, seed=seed)
    try:
        if prepare is not None:
            prepare(sim)
        devices = RigDevices(cfg, laser_ports=sim.laser_ports, can_bus=sim.runtime_bus(), ft_endpoints=sim.ft_endpoints)
        return run(cfg, devices, LockstepClock(advance=sim.advance), checks, passive_s=passive_s,
                   log_prefix=log_prefix, when_full="wait")
    finally:
        sim.close()
