"""What ``rig run`` and ``rig dry-run`` share: open devices, check health, arm, run the
loop, stop cleanly, close the log, and summarise.

SIGINT/SIGTERM ask the loop to stop (STOPPING → zero current → converters disabled → log
closed, exit 0). Any exception inside the loop zeroes the current and disables the
converters before it propagates (exit ≠ 0).

Shutdown is bounded: once the devices are closed (power stages off) the recorder gets
``recorder.close_timeout_s`` to close the log; past it (a disk that does not answer) the
recording sidecar is left to close the log when the disk answers, one line says so, and the
run exits with the code of what happened. A second stop signal ends the process at once
once the power stages are off (at once if they already are). The summary's ``ended_by``
names what ended the run first (a fault, a signal, ``rig ctl``, the duration).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import sys
from pathlib import Path
from typing import Optional, Sequence

from .. import __version__, schema
from ..clock import Clock, helper_cpus
from ..config import CARRIERS, RigConfig
from ..errors import DeviceInitError
from ..allocation import split
from ..lanes import law_signals
from ..logformat import LAW_SIGNALS_ATTR
from ..loop import ControlLoop, log_columns
from ..memo import across_processes, by_config
from ..recorder import Recorder
from ..scenario import Reference, Scenario, open_loop_input
from . import preflight
from .live import StatusPublisher
from .signals import StopSignals

EXIT_OK, EXIT_CRASH, EXIT_SETUP, EXIT_FAULT = 0, 1, 2, 3


def _observer_designs(cfg: RigConfig) -> dict:
    from .observer_design import designs
    return designs(cfg)


#: what a design is made of (rig_runtime/observer.py's frozen dataclasses of plain floats)
DESIGN_CLASSES = tuple(("rig_runtime.observer", n) for n in
                       ("ObserverDesign", "SpeedTable", "YawModel", "CarrierPart", "JointDesign", "JointCarrier"))
_designs_on_disk = across_processes("observer-designs", _observer_designs, DESIGN_CLASSES)
_designs_kept = by_config(_designs_on_disk)     # once per config in a process: a warm worker reads no disk


def observer_designs(cfg: RigConfig) -> dict:
    """The observers' designs (``observer_design.designs``; scipy's Riccati solver),
    imported here, when a run is set up: the commands that start no run import no scipy.
    Kept on disk for the next process (``memo.across_processes``: by the config's every value
    and the code's bytes), so a run whose config was designed before imports no scipy."""
    return _designs_kept(cfg)


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
    device set, the recorder settings of the config, the helper CPUs off the loop's. A
    lockstep run (``when_full="wait"``) without live outputs writes its log in this process
    (``writer="inline"``: no interpreter started per run; the same writer and file)."""
    writer = "inline" if when_full == "wait" and not outputs else "sidecar"
    attrs = {**attrs, LAW_SIGNALS_ATTR: dict(law_signals(cfg))}    # what the law's columns are (the viewers read it)
    rec = Recorder(log_path, log_columns(cfg, devices.channels(), devices.extra_columns, list(observed)),
                   attrs=attrs, buffer_cycles=cfg.recorder.buffer_cycles, flush_s=cfg.recorder.flush_s,
                   outputs=outputs, when_full=when_full, cpus=helper_cpus(cfg.realtime), writer=writer)
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
    again or a stop ends it. ``recorder_when_full="wait"``: a full recording ring is written
    out instead of dropping the row (lockstep runs only; without ``outputs`` the log is then
    written in this process, see :func:`open_recorder`)."""
    preflight.stability_gate(cfg)       # also for callers that bypass the CLI's preflight (once per config)
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
    power_off = False
    log_done = False             # the recorder's close returned (the log closed, or left to its sidecar)
    first = {}                   # what came first: the stop request, relative to the faults and the loop's end

    def code_now() -> int:
        """The exit code of what has happened so far (for a second signal that ends at once)."""
        if result is None:
            return 128 + (stops.signum or 0)
        return EXIT_FAULT if result.final_state == "FAULT" or result.arm_blockers else EXIT_OK

    def leave_now() -> None:
        """A second stop signal with the power stages off: exit at once, one line."""
        if not power_off:
            return                  # looked at again once the devices are closed
        left = ""
        if rec is not None and not log_done:
            if rec.writer == "inline":
                rec.close()         # in this process (lockstep): nobody else would close the log
            else:
                left = f"; the recording sidecar closes {log_path} on its own"
        sys.stdout.flush()
        sys.stderr.write(f"\nrig: second {stops.name or 'stop signal'}: exiting now (power stages off){left}\n")
        sys.stderr.flush()
        os._exit(code_now())

    def on_stop() -> None:
        if loop is not None:
            loop.stop_requested = True
            first.setdefault("faults_before_stop", len(loop.supervisor.faults))
        first.setdefault("loop_ended_before_stop", result is not None)

    stops.on_stop(on_stop)
    stops.on_repeat(leave_now)
    try:
        if not stops.requested and log_path is not None:
            rec = open_recorder(cfg, devices, log_path, run_attrs(cfg, scenario, duration, extra_attrs),
                                observed=list(observers), outputs=outputs, when_full=recorder_when_full)
        # the mailbox carries operator commands, if an output (rig ctl's server) sends any
        loop = ControlLoop(cfg, devices, clock, reference=reference, open_loop=open_loop, recorder=rec,
                           mailbox=rec.mailbox if rec is not None else None, observers=observers)
        if stops.requested:
            on_stop()
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
        try:
            devices.close()
        finally:
            power_off = True
        if status and not outputs:
            sys.stderr.write("\n")
        if stops.repeats:
            leave_now()
        try:
            if rec is not None:
                if rec.close(timeout=cfg.recorder.close_timeout_s):
                    if result is None and rec.rows_written == 0:
                        log_path.unlink(missing_ok=True)    # the loop never ran: no empty log left behind
                else:
                    sys.stderr.write(f"rig: {rec.left_running}; exiting\n")
        finally:
            log_done = True
            stops.forget(on_stop)
            stops.forget(leave_now)
    # a stop that came after the first fault or after the loop had ended did not end the run
    signal_ended = (stops.requested and not first.get("loop_ended_before_stop", False)
                    and first.get("faults_before_stop", 0) == 0)
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
        "recorder": ({"rows": rec.rows_written, "healthy": rec.healthy, "error": rec.error,
                      "closed": not rec.left_running, "left_running": rec.left_running} if rec is not None
                     else {"rows": 0, "healthy": True, "error": "not recording", "closed": True, "left_running": ""}),
        "run_started_t": result.t_start if result.t_start is not None else math.nan,
        "wall_time_s": result.wall_time_s,
    }
    if result.degraded:
        summary["degraded"] = result.degraded       # DEGRADED intervals (docs/observer.md)
    if result.reconfigured:
        summary["reconfigured"] = result.reconfigured   # RECONFIGURED intervals (docs/safety.md)
    if signal_ended:
        summary["ended_by"] = stops.name
    elif result.faults:
        f = result.faults[0]
        summary["ended_by"] = f"fault: {f['device']} {f['check']}: {f['message']}"
    elif operator_stop:
        summary["ended_by"] = "rig ctl stop"
    else:
        summary["ended_by"] = "duration reached"
    if signal_ended:
        summary["stopped_by"] = stops.name
    elif operator_stop:
        summary["stopped_by"] = "rig ctl"
    elif stops.requested:
        summary["late_stop"] = stops.name           # came after the run had ended (a fault, or its end)
    code = EXIT_FAULT if result.final_state == "FAULT" else EXIT_OK
    if rec is not None and not rec.healthy:
        code = EXIT_FAULT           # the log is not whole (a write failed, at the end too): never a clean exit
    if result.arm_blockers:     # RUNNING once, then arming again after `rig ctl reset-fault` failed
        summary["arm_failed"] = "could not arm again after the fault reset: " + "; ".join(result.arm_blockers[:4])
        code = EXIT_FAULT
    return summary, code, loop
