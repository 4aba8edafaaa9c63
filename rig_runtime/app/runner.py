"""What ``rig run`` and ``rig dry-run`` share: open devices, check health, arm, run the
loop, stop cleanly, close the log, and summarise.

SIGINT/SIGTERM ask the loop to stop (STOPPING → zero current → converters disabled → log
closed, exit 0). Any exception inside the loop zeroes the current and disables the
converters before it propagates (exit ≠ 0).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import sys
from pathlib import Path
from typing import Optional, Sequence

from .. import __version__, analysis, schema
from ..clock import Clock, helper_cpus
from ..config import CARRIERS, RigConfig
from ..errors import DeviceInitError
from ..lanes import split
from ..loop import ControlLoop, log_columns
from ..recorder import Recorder
from ..scenario import Reference, Scenario, open_loop_input
from .live import StatusPublisher
from .observer_design import designs as observer_designs
from .signals import StopSignals

EXIT_OK, EXIT_CRASH, EXIT_SETUP, EXIT_FAULT = 0, 1, 2, 3


def default_log_path(prefix: str) -> Path:
    """``logs/PREFIX-YYYYmmdd-HHMMSS-mmm-PID.h5``: unique across concurrent runs."""
    now = _dt.datetime.now()
    return Path("logs") / f"{prefix}-{now:%Y%m%d-%H%M%S}-{now.microsecond // 1000:03d}-{os.getpid()}.h5"


class StatusLine:
    """A live one-line status on a terminal (state, y, ψ, current, faults, jitter)."""

    def __init__(self, stream=sys.stderr):
        self.stream = stream

    def __call__(self, loop: ControlLoop) -> None:
        st = loop.stats
        lat = st.lateness.last * 1e6
        lanes = " ".join(f"{l.carrier}: y={l.y * 1e3:+7.3f} mm psi={l.psi * 1e3:+7.3f} mrad u={l.u:+6.3f} A"
                         for l in loop.lanes)
        self.stream.write(f"\r{loop.supervisor.state.name:<8} {lanes}  faults={len(loop.supervisor.faults)}  "
                          f"late={lat:6.1f} us  misses={st.deadline_misses}   ")
        self.stream.flush()


def run_attrs(cfg: RigConfig, scenario: Optional[Scenario], duration_s: float, extra: dict | None = None) -> dict:
    """The attributes every run's log carries (docs/log-format.md)."""
    attrs = {"config": json.dumps(schema.to_dict(cfg)), "software_version": __version__,
             "start_time": _dt.datetime.now(_dt.timezone.utc).isoformat(), "h": cfg.controller.h,
             "config_source": cfg.source, "scenario": scenario.name if scenario else "",
             "scenario_source": scenario.source if scenario else "",
             "experiment": (scenario.experiment or "") if scenario else "",
             # the identification's carrier and set-up (rig identify reads them)
             "open_loop_carrier": scenario.open_loop.carrier if scenario and scenario.open_loop else "",
             "lifted_carrier": (scenario.lifted_carrier or "") if scenario else "",
             "duration_s": float(duration_s), "controlled": list(cfg.controlled)}
    attrs.update(extra or {})
    return attrs


def open_recorder(cfg: RigConfig, devices, log_path: Path, attrs: dict, *, observed: Sequence[str] = (),
                  outputs: Sequence[tuple[str, dict]] = (), when_full: str = "drop") -> Recorder:
    """A run's recorder, open (its sidecar started): the log's columns for this config and
    device set, the recorder settings of the config, the helper CPUs off the loop's."""
    rec = Recorder(log_path, log_columns(cfg, devices.channels(), devices.extra_columns, list(observed)),
                   attrs=attrs, buffer_cycles=cfg.recorder.buffer_cycles, flush_s=cfg.recorder.flush_s,
                   outputs=outputs, when_full=when_full, cpus=helper_cpus(cfg.realtime))
    rec.open()
    return rec


def execute(cfg: RigConfig, devices, clock: Clock, *, scenario: Optional[Scenario], duration_s: Optional[float],
            log_path: Path | None, status: bool, extra_attrs: dict | None = None, arm_timeout_s: float = 2.0,
            stops: StopSignals | None = None, outputs: Sequence[tuple[str, dict]] = (),
            hold_on_fault: bool = False, recorder_when_full: str = "drop") -> tuple[dict, int, ControlLoop | None]:
    """Run one session; returns (summary, exit code, loop). In this order: the loop and the
    recorder (its sidecar process creates the log and starts the live ``outputs``),
    ``devices.configure()`` (no power), the loop (the supervisor's ARM activates the power
    stages), then devices and recorder closed on every path. ``stops``: the command's
    installed :class:`StopSignals` (a stop request before RUNNING raises
    :class:`Interrupted` after the clean stop). ``log_path=None``: nothing recorded and no
    sidecar (benchmarks measure the loop without it). ``status``: a live view on the
    terminal — the status line, unless an output shows the status (the panel), which then
    gets a snapshot every 0.2 s through the sidecar. ``hold_on_fault``: after a FAULT the
    loop keeps cycling (zero current, power stages off) until ``rig ctl reset-fault`` arms
    again or a stop ends it. ``recorder_when_full="wait"``: a full recording ring makes the
    loop wait for the sidecar instead of dropping the row (lockstep runs only)."""
    analysis.stability_gate(cfg)        # also for callers that bypass the CLI's preflight
    # the Riccati design here, not in the loop's modules; a carrier per the set-up in rolling
    # contact only (a carrier the scenario lifts off the rollers has no (2b) and no (4))
    lifted = scenario.lifted_carrier if scenario else None
    observers = {c: d for c, d in observer_designs(cfg).items() if c != lifted}
    # each carrier's own reference (scenario.reference_for: its own points, else the common ones)
    reference = {c: Reference(scenario.reference_for(c)) for c in CARRIERS} if scenario else (lambda t: 0.0)
    open_loop = (scenario.open_loop.carrier, open_loop_input(scenario.open_loop)) if scenario and scenario.open_loop else None
    duration = duration_s if duration_s is not None else (scenario.duration_s if scenario else math.inf)
    stops = stops if stops is not None else StopSignals()
    if log_path is not None:
        log_path = Path(log_path)
        log_path.parent.mkdir(parents=True, exist_ok=True)
    rec = None
    result = None
    loop = None
    phase = "before the log was opened"
    try:
        if not stops.requested and log_path is not None:
            rec = open_recorder(cfg, devices, log_path, run_attrs(cfg, scenario, duration, extra_attrs),
                                observed=list(observers), outputs=outputs, when_full=recorder_when_full)
        # the mailbox carries operator commands, if an output (rig ctl's server) sends any
        loop = ControlLoop(cfg, devices, clock, reference=reference, open_loop=open_loop, recorder=rec,
                           mailbox=rec.mailbox if rec is not None else None, observers=observers)
        stops.on_stop(lambda: setattr(loop, "stop_requested", True))
        if not stops.requested:
            phase = "while configuring the devices"
        if not stops.requested:
            devices.configure()
            phase = "after configuring the devices"
        if not stops.requested:
            live = None
            if rec is not None and outputs:
                live = StatusPublisher(rec, duration)
            elif status:
                live = StatusLine()
            result = loop.run(duration, arm_timeout_s=arm_timeout_s, status=live, hold_on_fault=hold_on_fault)
    finally:
        devices.close()
        if rec is not None:
            rec.close()
            if result is None and rec.rows_written == 0:
                log_path.unlink(missing_ok=True)    # the loop never ran: no empty log left behind
        if status and not outputs:
            sys.stderr.write("\n")
    operator_stop = loop is not None and not stops.requested and loop.stop_requested      # rig ctl stop
    if result is None or (result.t_start is None and not result.faults and not operator_stop):
        if stops.requested:
            what = "power stages disabled" if loop is not None and loop.supervisor.ever_armed else "power stages never enabled"
            if result is not None:
                phase = "while arming" if loop.supervisor.ever_armed else "during warm-up"
            raise stops.interrupted(f"before RUNNING ({phase}): {what}"
                                    + (f", log closed: {log_path}" if log_path is not None and log_path.exists()
                                      else ", no log written"))
        raise DeviceInitError("arming", "not every device is ready: " + "; ".join(result.arm_blockers[:4]))
    summary = {
        "final_state": result.final_state,
        "faults": result.faults,
        "cycles": result.cycles,
        "max_abs_current_A": result.max_abs_current_A,
        "max_abs_wire_current_A": max(max(map(abs, split(result.max_abs_current_A))),
                                      result.max_abs_reconfigured_wheel_A),
        "timing": result.timing,
        "log": str(log_path) if log_path is not None else None,
        "recorder": ({"rows": rec.rows_written, "healthy": rec.healthy, "error": rec.error} if rec is not None
                     else {"rows": 0, "healthy": True, "error": "not recording"}),
        "run_started_t": result.t_start if result.t_start is not None else math.nan,
        "wall_time_s": result.wall_time_s,
    }
    if result.degraded:
        summary["degraded"] = result.degraded       # DEGRADED intervals (docs/observer.md)
    if result.reconfigured:
        summary["reconfigured"] = result.reconfigured   # RECONFIGURED intervals (docs/safety.md)
    if stops.requested:
        summary["stopped_by"] = stops.name
    elif operator_stop:
        summary["stopped_by"] = "rig ctl"
    code = EXIT_FAULT if result.final_state == "FAULT" else EXIT_OK
    if result.arm_blockers:     # RUNNING once, then arming again after `rig ctl reset-fault` failed
        summary["arm_failed"] = "could not arm again after the fault reset: " + "; ".join(result.arm_blockers[:4])
        code = EXIT_FAULT
    return summary, code, loop
