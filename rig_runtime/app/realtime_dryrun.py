"""``rig dry-run --realtime``: the runtime on the real-time clock against the simulated
rig served by ``rig sim`` in a separate process (the plant must not share the loop's
interpreter lock: a busy thread in the same process delays the loop's wake-up by up to
the interpreter's switch interval)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

from sim_backend.launcher import start_sim_process

from .. import config
from ..clock import RealtimeClock, apply_realtime
from ..config import RigConfig
from ..devices import RigDevices
from ..scenario import Scenario
from .runner import execute
from .signals import StopSignals


def run_realtime_dry_run(cfg: RigConfig, scenario: Scenario, log: Path, *, seed: Optional[int] = None,
                         duration_s: Optional[float] = None, status: bool = False,
                         stops: Optional[StopSignals] = None, outputs: Sequence[tuple[str, dict]] = (),
                         hold_on_fault: bool = False) -> tuple[dict, int]:
    with start_sim_process(config=cfg.source, scenario=scenario.source or None, seed=seed) as sp:
        rcfg = config.load(sp.config_path)
        devices = RigDevices(rcfg)
        rt_report = apply_realtime(rcfg.realtime)
        clock = RealtimeClock(rcfg.realtime.spin_us * 1e-6)
        summary, code, _ = execute(rcfg, devices, clock, scenario=scenario, duration_s=duration_s, log_path=log,
                                   status=status, stops=stops, outputs=outputs, hold_on_fault=hold_on_fault, extra_attrs={"mode": "dry-run realtime (rig sim process)",
                                                               "realtime": "; ".join(rt_report)})
    summary["sim_time_s"] = summary["cycles"] * rcfg.controller.h
    summary["realtime"] = rt_report
    return summary, code
