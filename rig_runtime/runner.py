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
import signal
import sys
from pathlib import Path
from typing import Optional

from . import __version__, schema
from .clock import Clock
from .config import RigConfig
from .errors import DeviceInitError
from .loop import ControlLoop
from .recorder import Recorder
from .scenario import Reference, Scenario, open_loop_input

EXIT_OK, EXIT_CRASH, EXIT_SETUP, EXIT_FAULT = 0, 1, 2, 3


def default_log_path(prefix: str) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("logs") / f"{prefix}-{stamp}.h5"


class StatusLine:
    """A live one-line status on a terminal (state, y, ψ, current, faults, jitter)."""

    def __init__(self, stream=sys.stderr):
        self.stream = stream

    def __call__(self, loop: ControlLoop) -> None:
        m = loop.last_measurement
        st = loop.stats
        lat = st.lateness.last * 1e6
        y = m.y_r * 1e3 if m else math.nan
        psi = m.psi_ar * 1e3 if m else math.nan
        self.stream.write(f"\r{loop.supervisor.state.name:<8} y={y:+7.3f} mm  psi={psi:+7.3f} mrad  "
                          f"u={2 * loop.currents[2]:+6.3f} A  faults={len(loop.supervisor.faults)}  "
                          f"late={lat:6.1f} us  misses={st.deadline_misses}   ")
        self.stream.flush()


def execute(cfg: RigConfig, devices, clock: Clock, *, scenario: Optional[Scenario], duration_s: Optional[float],
            log_path: Path, status: bool, in_cycle=None, on_running=None, extra_attrs: dict | None = None,
            arm_timeout_s: float = 2.0, open_context=None,
            recorder_writer: str = "thread") -> tuple[dict, int, ControlLoop | None]:
    """Run one session; returns (summary, exit code, loop). Devices are closed on return.
    ``recorder_writer="inline"`` lets the loop thread write the log (lockstep runs)."""
    reference = Reference(scenario.reference) if scenario else (lambda t: 0.0)
    open_loop = (scenario.open_loop.carrier, open_loop_input(scenario.open_loop)) if scenario and scenario.open_loop else None
    duration = duration_s if duration_s is not None else (scenario.duration_s if scenario else math.inf)
    log_path = Path(log_path)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    loop: ControlLoop | None = None
    rec = None
    old_handlers = {}
    try:
        if open_context is not None:
            with open_context():
                devices.open()
        else:
            devices.open()
        loop = ControlLoop(cfg, devices, clock, reference=reference, open_loop=open_loop,
                           in_cycle=in_cycle, on_running=on_running)
        attrs = {"config": json.dumps(schema.to_dict(cfg)), "software_version": __version__,
                 "start_time": _dt.datetime.now(_dt.timezone.utc).isoformat(), "h": cfg.controller.h,
                 "config_source": cfg.source, "scenario": scenario.name if scenario else "",
                 "scenario_source": scenario.source if scenario else "",
                 "experiment": (scenario.experiment or "") if scenario else ""}
        attrs.update(extra_attrs or {})
        rec = Recorder(log_path, loop.columns, attrs=attrs, buffer_cycles=cfg.recorder.buffer_cycles,
                       flush_s=cfg.recorder.flush_s, writer=recorder_writer)
        rec.open()
        loop.recorder = rec

        def on_signal(signum, frame):
            loop.stop_requested = True
        for s in (signal.SIGINT, signal.SIGTERM):
            try:
                old_handlers[s] = signal.signal(s, on_signal)
            except ValueError:   # not the main thread
                pass
        result = loop.run(duration, arm_timeout_s=arm_timeout_s, status=StatusLine() if status else None)
    finally:
        for s, hnd in old_handlers.items():
            signal.signal(s, hnd)
        devices.close()
        if rec is not None:
            rec.close()
        if status:
            sys.stderr.write("\n")
    if math.isnan(result.t_start):
        raise DeviceInitError("arming", "not every device is ready: " + "; ".join(result.arm_blockers[:4]))
    summary = {
        "final_state": result.final_state,
        "faults": result.faults,
        "cycles": result.cycles,
        "max_abs_current_A": result.max_abs_current_A,
        "max_abs_wire_current_A": 0.5 * result.max_abs_current_A,
        "timing": result.timing,
        "log": str(log_path),
        "recorder": {"rows": rec.rows_written, "healthy": rec.healthy, "error": rec.error},
        "run_started_t": result.t_start,
        "wall_time_s": result.wall_time_s,
    }
    code = EXIT_FAULT if result.final_state == "FAULT" else EXIT_OK
    return summary, code, loop
