"""``rig dry-run --realtime``: the runtime on the real-time clock against the simulated
rig served by ``rig sim`` in a separate process (the plant must not share the loop's
interpreter lock: a busy thread in the same process delays the loop's wake-up by up to
the interpreter's switch interval)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rig_runtime import config
from rig_runtime.clock import RealtimeClock, apply_realtime
from rig_runtime.config import RigConfig
from rig_runtime.devices import RigDevices
from rig_runtime.runner import execute
from rig_runtime.scenario import Scenario

from .launcher import start_sim_process


def run_realtime_dry_run(cfg: RigConfig, scenario: Scenario, args: argparse.Namespace, log: Path) -> tuple[dict, int]:
    with start_sim_process(config=cfg.source, scenario=scenario.source or None, seed=args.seed) as sp:
        rcfg = config.load(sp.config_path)
        devices = RigDevices(rcfg)
        rt_report = apply_realtime(rcfg.realtime)
        clock = RealtimeClock(rcfg.realtime.spin_us * 1e-6)
        summary, code, _ = execute(rcfg, devices, clock, scenario=scenario, duration_s=args.duration, log_path=log,
                                   status=sys.stderr.isatty() and not args.json,
                                   extra_attrs={"mode": "dry-run realtime (rig sim process)",
                                                "realtime": "; ".join(rt_report)})
    summary["sim_time_s"] = summary["cycles"] * rcfg.controller.h
    summary["realtime"] = rt_report
    return summary, code
