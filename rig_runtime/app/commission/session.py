"""What the commissioning session observes, against any device set and clock (the rig's
devices on the real-time clock, or the simulated rig in lockstep).

Passive windows poll the devices with the power stages off (nothing is ever activated:
zero current is written only to keep the drives' SYNC and heartbeat going, as the loop's
IDLE does). A bump is one ordinary session of the control loop with an open-loop input on
one carrier: warm-up, the supervisor's ARM (the only way the power stages come on), the
pulse, zero current, STOPPING, IDLE (power stages off) — the same lifecycle as ``rig run``."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Optional

from ...clock import Clock
from ...config import WHEELS, RigConfig
from ...control import StepSequence
from ...loop import ControlLoop
from ...safety import State
from ..runner import open_recorder, run_attrs

ZERO = {w: 0.0 for w in WHEELS}


def passive(devices, clock: Clock, h: float, seconds: float, names: tuple[str, ...],
            stops=None, log=None) -> dict[str, list[float]]:
    """Every channel in ``names`` (laser roles, wheels) polled each period for ``seconds``,
    power stages off: ``{name: [value per cycle]}`` (NaN until a channel has a value). A stop
    request (``stops``) ends the window early. ``log``: the commissioning log
    (:class:`~.log.CommissionLog`) that records each cycle's reading."""
    out: dict[str, list[float]] = {n: [] for n in names}
    t0 = clock.now() + h
    for k in range(max(1, int(round(seconds / h)))):
        if stops is not None and stops.requested:
            break
        t = clock.wait_until(t0 + k * h)
        r = devices.poll(t)
        devices.write(ZERO, t)
        if log is not None:
            log.cycle(t, t - (t0 + k * h), r)
        for n in names:
            s = r.samples.get(n)
            v = r.values.get(n, math.nan)
            out[n].append(v if s is None or math.isfinite(s.t) else math.nan)   # NaN: no value yet
    return out


class _Capture:
    """The loop's status hook, called every cycle: what the bump's judgement needs."""

    def __init__(self) -> None:
        self.rec: dict[str, list[float]] = {k: [] for k in (
            "t", "running", "enabled", *(f"{q}_{c}" for q in ("psi", "dw", "y", "u") for c in ("front", "rear")),
            *(f"i_{w}" for w in WHEELS), *(f"omega_{w}" for w in WHEELS))}
        self._wheels: dict = {}

    def __call__(self, loop: ControlLoop) -> None:
        m = loop.last_measurement
        if m is None:
            return
        r = self.rec
        r["t"].append(loop.cycle.t)
        r["running"].append(1.0 if loop.supervisor.state is State.RUNNING else 0.0)
        r["enabled"].append(1.0 if loop.supervisor.active else 0.0)
        for c in ("front", "rear"):
            y, psi, dw = m.carrier(c)
            r[f"y_{c}"].append(y)
            r[f"psi_{c}"].append(psi)
            r[f"dw_{c}"].append(dw)
            r[f"u_{c}"].append(next((l.u for l in loop.lanes if l.carrier == c), 0.0))
        cur = loop.currents
        for w in WHEELS:
            r[f"i_{w}"].append(cur.get(w, 0.0))
        if not self._wheels:
            self._wheels = {c.name: c for c in loop.channels if c.kind == "wheel"}
        for w in WHEELS:
            c = self._wheels.get(w)
            r[f"omega_{w}"].append(c.value if c is not None else math.nan)


def bump_config(cfg: RigConfig, carrier: str) -> RigConfig:
    """A bump's config: the one lane is this carrier's, playing the open-loop pulse."""
    return dataclasses.replace(cfg, controlled=(carrier,))


def open_bump_log(cfg: RigConfig, devices, carrier: str, check: str, duration_s: float, path: Path,
                  when_full: str = "drop"):
    """The recorder of one bump session's normal log, open (its sidecar started). Opened before
    the devices are configured, as ``rig run`` does: a sidecar takes most of a second to
    start, longer than the drives' heartbeat consumers wait between two cycles."""
    bump_cfg = bump_config(cfg, carrier)
    attrs = run_attrs(bump_cfg, None, duration_s, {"scenario": f"commission {check}", "mode": "commission"})
    return open_recorder(bump_cfg, devices, path, attrs, when_full=when_full)


def bump(cfg: RigConfig, devices, clock: Clock, carrier: str, u_A: float, pulse_s: float, after_s: float,
         recorder=None, stops=None) -> tuple[dict[str, list[float]], dict]:
    """One pulse of ``u_A`` (differential, each wheel ±u/2) for ``pulse_s`` on ``carrier``,
    then zero current for ``after_s``, inside one armed session of the control loop
    (devices configured by the caller), recorded by ``recorder`` (``open_bump_log``; None:
    not recorded; the caller closes it). The same for a lifted carrier and one on the
    rollers: the set-up is the operator's. Returns (the captured series, the run's result)."""
    u = StepSequence(((0.0, u_A), (pulse_s, 0.0)))
    loop = ControlLoop(bump_config(cfg, carrier), devices, clock, open_loop=(carrier, u), recorder=recorder,
                       mailbox=recorder.mailbox if recorder is not None else None)
    if stops is not None:           # a signal: the loop's own clean stop (ramp, power stages off)
        stops.on_stop(lambda: setattr(loop, "stop_requested", True))
    cap = _Capture()
    result = loop.run(pulse_s + after_s, status=cap, status_period_s=0.0)
    return cap.rec, {"final_state": result.final_state, "faults": result.faults,
                     "arm_blockers": list(result.arm_blockers), "max_abs_current_A": result.max_abs_current_A}
