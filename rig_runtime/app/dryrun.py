"""A lockstep dry run as a function: the simulated rig, the runtime's own devices and
loop, the lockstep clock. ``rig dry-run`` and the tests use it.

The simulator plugs in only through the transports it serves (laser ptys, a python-can
bus, Modbus TCP endpoints on 127.0.0.1) and the clock (``LockstepClock(advance=sim.advance)``);
the runtime's devices, loop and recorder are the ones ``rig run`` uses."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Sequence

from sim_backend.rig import SimulatedRig

from ..clock import LockstepClock
from ..config import RigConfig
from ..devices import RigDevices
from ..logformat import TRUTH_GROUP
from ..scenario import Scenario
from .metrics import steps_from_log
from .runner import execute
from .signals import StopSignals


TRUTH_FIELDS = ("t", "y_f", "y_r", "psi_af", "psi_ar")


class TruthRecorder:
    """The simulated plant's true state at every release of the lockstep clock (after the
    plant was integrated to it: the state the lasers' frames of that cycle show), written
    after the run into the log's group ``sim_truth`` — marked as simulation, never a
    measurement — so that an estimate can be judged against it (docs/observer.md)."""

    def __init__(self, sim: SimulatedRig):
        self.sim = sim
        self.rows: list[tuple[float, ...]] = []

    def advance(self, t: float):
        r = self.sim.advance(t)
        p = self.sim.plant
        self.rows.append((self.sim.t, p.y_f, p.y_r, p.psi_af, p.psi_ar))
        return r

    def write(self, log_path: Path) -> None:
        import h5py
        import numpy as np
        data = np.array(self.rows, dtype=float).reshape(-1, len(TRUTH_FIELDS))
        with h5py.File(log_path, "a") as f:
            if TRUTH_GROUP in f:
                del f[TRUTH_GROUP]
            g = f.create_group(TRUTH_GROUP)
            g.attrs["simulation"] = ("SIMULATION: the simulated plant's true state (m, rad) at each "
                                     "release of the lockstep clock, simulated time t (s); not a measurement")
            for i, name in enumerate(TRUTH_FIELDS):
                g.create_dataset(name, data=data[:, i])


def run_lockstep(cfg: RigConfig, scenario: Optional[Scenario], log_path: Path, *, seed: Optional[int] = None,
                 duration_s: Optional[float] = None,
                 prepare: Optional[Callable[[SimulatedRig, RigDevices, LockstepClock], None]] = None,
                 stops: Optional[StopSignals] = None, outputs: Sequence[tuple[str, dict]] = (),
                 hold_on_fault: bool = False) -> tuple[dict, int]:
    """Run ``scenario`` against the simulated plant; returns (summary, exit code).

    ``prepare(sim, devices, clock)`` runs before the devices are configured (tests use it
    to tap the CAN wire or to wrap a device)."""
    summary, code, _ = run_lockstep_read(cfg, scenario, log_path, seed=seed, duration_s=duration_s, prepare=prepare,
                                         stops=stops, outputs=outputs, hold_on_fault=hold_on_fault)
    return summary, code


def run_lockstep_read(cfg: RigConfig, scenario: Optional[Scenario], log_path: Path, *,
                      seed: Optional[int] = None, duration_s: Optional[float] = None,
                      prepare: Optional[Callable[[SimulatedRig, RigDevices, LockstepClock], None]] = None,
                      stops: Optional[StopSignals] = None, outputs: Sequence[tuple[str, dict]] = (),
                      hold_on_fault: bool = False) -> tuple[dict, int, Optional[dict]]:
    """:func:`run_lockstep`, and the log as ``export.read_log`` reads it after the run (the
    step metrics are computed from it; None if the recorder was not healthy): a caller that
    needs more from the log (a campaign's metrics) does not read it a second time."""
    sim = SimulatedRig(cfg, scenario, seed=seed)
    truth = TruthRecorder(sim)
    try:
        clock = LockstepClock(advance=truth.advance)
        devices = RigDevices(cfg, laser_ports=sim.laser_ports, can_bus=sim.runtime_bus(),
                             ft_endpoints=sim.ft_endpoints)
        if prepare is not None:
            prepare(sim, devices, clock)
        summary, code, _ = execute(
            cfg, devices, clock, scenario=scenario, duration_s=duration_s, log_path=log_path,
            status=False, extra_attrs={"mode": "dry-run lockstep", "seed": sim.seed},
            stops=stops, outputs=outputs, hold_on_fault=hold_on_fault,
            recorder_when_full="wait")
        summary["sim_time_s"] = clock.now()
        summary["seed"] = sim.seed
        summary["clock"] = "lockstep"       # no deadlines: the summary reports wall-clock cost per cycle
        summary["wall_us_per_cycle"] = summary["wall_time_s"] * 1e6 / max(summary["cycles"], 1)
    finally:
        sim.close()
    read = None
    if summary["recorder"]["healthy"]:      # a log the recorder could not write is not read or added to
        if log_path is not None and Path(log_path).exists():
            truth.write(Path(log_path))
        if scenario is not None:
            from .export import read_log
            read = read_log(log_path)
        summary["steps"] = steps_from_log(read, scenario, cfg.controller.h)
    return summary, code, read
