"""The commissioning procedure: prompts, the passive windows, the bumps, the judgement, in
that order, against a configured-by-us device set. ``run`` is the same for the rig and for
the simulated rig; ``run_lockstep`` builds the simulated rig in process (tests)."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

from ...clock import Clock
from ...config import LASER_ROLES, WHEELS, RigConfig
from ...lanes import CARRIER_WHEELS
from . import CHECKS
from .judge import (Item, encoder_signs, judge_bump, judge_encoders, judge_lasers, judge_lifted,
                    rolling_wheels)
from .log import CommissionLog, item_text
from .session import ZERO, bump, open_bump_log, passive

BUMP_WIRE_A = 0.3           # each wheel's current during a bump (A); the differential u is twice it
BUMP_S = 0.2                # the pulse
AFTER_S = 0.3               # zero current after the pulse, still armed: the yaw angle's answer
PASSIVE_S = 8.0             # the operator's window for the passive motions


def laser_prompt(seconds: float) -> str:
    return (f"lasers (power stages off; SET-UP: the carriers lifted off the rollers): within the next {seconds:g} s, one after the other, each by hand "
            "and let go again: push the vehicle about 2 mm to the left (+y, away from the lateral lasers); "
            "push its rear end about 2 mm to the left, holding the front end; turn the rear carrier nose-left "
            "by a few mrad; turn the front carrier nose-right by a few mrad.")


def encoder_prompt(cfg: RigConfig) -> str:
    lifted = [w for w in WHEELS if w not in rolling_wheels(cfg)]
    return (f"encoders (power stages off; SET-UP: the carriers set ON THE ROLLERS, a carrier lifted in this rig's "
            f"set-up stays lifted): the rollers turning forward at "
            f"v = {cfg.plant.v:+.2f} m/s (the roller drive; the wheels' drives stay off); the wheels roll at "
            f"{cfg.plant.v / cfg.plant.r0:+.2f} rad/s"
            + (f" ({', '.join(lifted)} lifted in this set-up: not judged here)." if lifted else "."))


def lifted_prompt() -> str:
    return (f"lifted bumps (SET-UP: the carriers still LIFTED off the rollers, every wheel free and at rest, the rig "
            f"clear of people): for each carrier the supervisor arms (power stages on), a pulse of "
            f"±{BUMP_WIRE_A:.1f} A per wheel for {BUMP_S:.1f} s spins its two wheels freely, then zero current "
            "and the power stages off again.")


def bump_prompt() -> str:
    return (f"bumps on the rollers (SET-UP: the carriers ON THE ROLLERS as for the encoders, the rollers "
            f"turning at v, the rig clear of people): for each bump the "
            f"supervisor arms (power stages on), a pulse of ±{BUMP_WIRE_A:.1f} A per wheel for {BUMP_S:.1f} s on "
            f"one wheel pair, then zero current and the power stages off again.")


@dataclass(frozen=True)
class Report:
    items: tuple[Item, ...]
    checks: tuple[str, ...]
    sessions: tuple[dict, ...] = ()
    log: Optional[str] = None           # the commissioning's own normal log

    @property
    def passed(self) -> bool:
        return bool(self.items) and all(i.passed for i in self.items)

    def as_dict(self) -> dict:
        return {"result": "pass" if self.passed else "fail", "checks": list(self.checks),
                "items": [i.as_dict() for i in self.items], "sessions": list(self.sessions), "log": self.log}

    def text(self) -> str:
        out = []
        for i in self.items:
            out.append(f"{'PASS' if i.passed else 'FAIL'} {i.name}: {item_text(i)}")
            out += [f"    likely fault: {f}" for f in i.faults]
            if i.note:
                out.append(f"    note: {i.note}")
        out.append(f"commissioning {'passed' if self.passed else 'FAILED'} ({', '.join(self.checks)})")
        return "\n".join(out)


def _declined(name: str) -> Item:
    return Item(name, False, {}, ("not run: the operator declined",))


def run(cfg: RigConfig, devices, clock: Clock, checks: Sequence[str] = CHECKS,
        confirm: Callable[[str], bool] = lambda text: True, say: Callable[[str], None] = lambda s: None,
        passive_s: float = PASSIVE_S, stops=None, log_prefix: Optional[Path] = None,
        when_full: str = "drop", config_hash: str = "", prompts_wait: bool = False) -> Report:
    """Configure the devices (no power), then each selected check in ``CHECKS`` order; the
    devices are closed on every path. Recorded as normal logs (``log_prefix`` None: nothing
    recorded): the commissioning's own, ``<log_prefix>.h5`` (the passive windows and the
    report, :mod:`.log`), and one per bump session, ``<log_prefix>-<check>.h5``.
    ``confirm(prompt)``: the operator's go (False: that check is not run, and fails);
    ``prompts_wait``: it waits for a person — the cycle goes on meanwhile (power stages off,
    zero current), since the drives' heartbeat consumers fault within a fraction of a second
    without the runtime's SYNC and heartbeat (the lockstep clock leaves it False: no
    simulated time passes at a prompt)."""
    h = cfg.controller.h
    items: list[Item] = []
    sessions: list[dict] = []
    node_ids = {d.wheel: d.node_id for d in cfg.devices.can.drives}
    log: Optional[CommissionLog] = None
    bump_logs: dict[str, object] = {}       # check -> its session's recorder, open until the end

    def stopped() -> bool:
        return stops is not None and stops.requested

    def session(check: str, c: str) -> Optional[dict]:
        """One bump session on carrier ``c``; its captured series, or None (a failed item added)."""
        u = 2 * BUMP_WIRE_A
        say(f"{check}: u = {u:+.2f} A ({BUMP_WIRE_A:+.2f} A / {-BUMP_WIRE_A:+.2f} A on the wire) for {BUMP_S} s")
        recorder = bump_logs.get(check)
        path = recorder.path if recorder is not None else None
        if log is not None:
            log.note(clock.now(), check, f"{check}: the session begins" + (f" (log {path})" if path else ""))
        rec, res = bump(cfg, devices, clock, c, u, BUMP_S, AFTER_S, recorder=recorder, stops=stops)
        res["log"] = str(path) if path is not None else None
        devices.resume(clock.now())     # the stop left the drives pre-operational: back to configure()'s state
        sessions.append({"check": check, **res})
        if res["final_state"] != "IDLE" or res["faults"]:
            why = "; ".join(f"{f['device']} {f['check']}" for f in res["faults"]) or "; ".join(res["arm_blockers"][:3])
            items.append(Item(check, False, {}, (f"the bump session ended in {res['final_state']} ({why})",)))
            return None
        return rec

    def ask(text: str) -> bool:
        """``confirm(text)``; while it waits for the operator, the devices are polled each
        period with zero current (not recorded). A stop request ends the wait: declined."""
        if not prompts_wait:
            return confirm(text)
        answer: list[bool] = []
        asking = threading.Thread(target=lambda: answer.append(confirm(text)), name="commission-prompt", daemon=True)
        asking.start()
        t0 = clock.now() + h
        k = 0
        while asking.is_alive() and not stopped():
            t = clock.wait_until(t0 + k * h)
            devices.poll(t)
            devices.write(ZERO, t)
            k += 1
        return bool(answer and answer[0]) and not stopped()

    def window(check: str, seconds: float, names: tuple[str, ...]) -> dict:
        if log is not None:
            log.note(clock.now(), check, f"{check}: the operator's window of {seconds:g} s begins")
        return passive(devices, clock, h, seconds, names, stops, log)

    try:
        if log_prefix is not None:      # every log opened before the devices are configured (open_bump_log)
            log = CommissionLog(cfg, devices, Path(f"{log_prefix}.h5"), config_hash, when_full=when_full)
            for check in (c for c in CHECKS if c in checks and "-" in c):
                bump_logs[check] = open_bump_log(cfg, devices, check.split("-")[1], check, BUMP_S + AFTER_S,
                                                 Path(f"{log_prefix}-{check}.h5"), when_full)
        devices.configure()
        if "lasers" in checks:
            items.append(judge_lasers(window("lasers", passive_s, LASER_ROLES)) if ask(laser_prompt(passive_s))
                         else _declined("lasers"))
        lifted = [c for c in ("rear", "front") if f"lifted-{c}" in checks]
        if lifted and not ask(lifted_prompt()):
            items += [_declined(f"lifted-{c}") for c in lifted]
            lifted = []
        lifted_recs: dict[str, dict] = {}
        for c in lifted:
            if stopped():
                break
            rec = session(f"lifted-{c}", c)
            if rec is not None:
                lifted_recs[c] = rec
        encoders = None
        if "encoders" in checks and not stopped():
            encoders = (judge_encoders(window("encoders", 1.0, WHEELS), cfg, node_ids) if ask(encoder_prompt(cfg))
                        else _declined("encoders"))
            items.append(encoders)
        # judged once the encoders' signs are known (from the rollers)
        lifted_items = {c: judge_lifted(c, 2 * BUMP_WIRE_A, BUMP_S, rec, cfg, node_ids, encoder_signs(encoders))
                        for c, rec in lifted_recs.items()}
        items += lifted_items.values()
        bumps = [c for c in ("rear", "front") if f"bump-{c}" in checks]
        if bumps and not stopped() and not ask(bump_prompt()):
            items += [_declined(f"bump-{c}") for c in bumps]
            bumps = []
        lasers = next((i for i in items if i.name == "lasers"), None)
        for c in bumps:
            if stopped():
                break
            rec = session(f"bump-{c}", c)
            if rec is not None:
                yaw_ok = None if lasers is None else not any(r in f for f in lasers.faults
                                                             for r in (f"s_{c[0]}l", f"s_{c[0]}r"))
                enc_ok = None if encoders is None else not any(f"{w} " in f for f in encoders.faults
                                                               for w in CARRIER_WHEELS[c])
                items.append(judge_bump(c, 2 * BUMP_WIRE_A, rec, cfg, node_ids, yaw_lasers_ok=yaw_ok,
                                        lifted=lifted_items.get(c), encoders_ok=enc_ok))
        items.sort(key=lambda i: CHECKS.index(i.name))
        rep = Report(tuple(items), tuple(c for c in CHECKS if c in checks), tuple(sessions),
                     str(log.path) if log is not None else None)
        if log is not None and not stopped():
            log.items(clock.now(), items, sessions, rep.passed)
    finally:
        try:
            devices.close()
        finally:
            ran = {s["check"] for s in sessions}
            for check, r in bump_logs.items():
                r.close()
                if check not in ran:        # not run (declined, stopped): no empty log left behind
                    r.path.unlink(missing_ok=True)
            if log is not None:
                log.close()
    return rep


def run_lockstep(cfg: RigConfig, checks: Sequence[str] = CHECKS, *, seed: Optional[int] = None,
                 passive_s: float = 2.2, prepare: Optional[Callable] = None,
                 log_prefix: Optional[Path] = None, lifted_sessions: Optional[int] = None) -> Report:
    """``run`` against the simulated rig in this process, on the lockstep clock (the
    simulated operator moves the vehicle and lifts the carriers for the lifted bumps: ``sim:
    {operator: commission, operator_lifted_sessions: <the lifted checks asked for>}`` is set
    here; ``lifted_sessions`` overrides it). ``prepare(sim)`` runs before anything is
    configured (tests tap the CAN wire)."""
    import dataclasses

    from sim_backend.rig import SimulatedRig

    from ...clock import LockstepClock
    from ...devices import RigDevices
    from . import record
    n_lifted = sum(1 for c in checks if c.startswith("lifted-")) if lifted_sessions is None else lifted_sessions
    sim_cfg = dataclasses.replace(cfg, sim={**(cfg.sim or {}), "operator": "commission",
                                            "operator_lifted_sessions": n_lifted})
    sim = SimulatedRig(sim_cfg, None, seed=seed)
    try:
        if prepare is not None:
            prepare(sim)
        devices = RigDevices(cfg, laser_ports=sim.laser_ports, can_bus=sim.runtime_bus(), ft_endpoints=sim.ft_endpoints)
        return run(cfg, devices, LockstepClock(advance=sim.advance), checks, passive_s=passive_s,
                   log_prefix=log_prefix, when_full="wait", config_hash=record.config_hash(cfg))
    finally:
        sim.close()
