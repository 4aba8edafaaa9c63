"""A lockstep dry run as a function: the simulated rig, the runtime's own devices and
loop, the lockstep clock. ``rig dry-run`` and the tests use it."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

from rig_runtime.clock import LockstepClock
from rig_runtime.config import RigConfig
from rig_runtime.devices import RigDevices
from rig_runtime.metrics import steps_from_log
from rig_runtime.runner import execute
from rig_runtime.scenario import Scenario

from .rig import SimulatedRig


def run_lockstep(cfg: RigConfig, scenario: Optional[Scenario], log_path: Path, *, seed: Optional[int] = None,
                 duration_s: Optional[float] = None,
                 prepare: Optional[Callable[[SimulatedRig, RigDevices, LockstepClock], None]] = None) -> tuple[dict, int]:
    """Run ``scenario`` against the simulated plant; returns (summary, exit code).

    ``prepare(sim, devices, clock)`` runs before the devices open (tests use it to tap the
    CAN wire or to wrap a device)."""
    sim = SimulatedRig(cfg, scenario, seed=seed)
    try:
        clock = LockstepClock(advance=sim.advance)
        devices = RigDevices(cfg, laser_ports=sim.laser_ports, can_bus=sim.runtime_bus(),
                             ft_endpoints=sim.ft_endpoints)
        sim.defer_laser_delivery = True     # the runtime waits for the laser bytes before reading them
        devices.before_laser_poll = sim.await_laser_delivery
        if prepare is not None:
            prepare(sim, devices, clock)
        summary, code, _ = execute(
            cfg, devices, clock, scenario=scenario, duration_s=duration_s, log_path=log_path,
            status=False, in_cycle=sim.in_cycle(clock), on_running=sim.on_running,
            extra_attrs={"mode": "dry-run lockstep", "seed": sim.seed},
            open_context=lambda: sim.drives.serving(0.0),
            recorder_writer="inline")       # simulated time: no deadlines, no writer thread
        summary["sim_time_s"] = clock.now()
        summary["seed"] = sim.seed
    finally:
        sim.close()
    summary["steps"] = steps_from_log(log_path, scenario, cfg.controller.h)
    return summary, code
