"""``rig sim``'s work: build the simulated rig, print its ports (and write the config for
``rig run``), ``ready``, serve in real time until SIGINT/SIGTERM (or a duration), shut down
cleanly. The command line is ``rig_runtime/sim_command.py``; what is served,
docs/sim-process.md."""

from __future__ import annotations

import gc
import logging
import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Optional, Sequence

from rig_runtime import config as rig_config
from rig_runtime.clock import set_cpu_affinity, set_sched_fifo

from .generated_config import devices_section, write_generated_config
from .port_lines import port_lines
from .realtime_sim import RealtimeSim

__all__ = ["serve", "SWITCH_INTERVAL_S"]

SWITCH_INTERVAL_S = 0.0005     # interpreter switch interval in the rig sim process


def _say(text: str) -> None:
    print(f"rig sim: {text}", file=sys.stderr, flush=True)


def serve(config_path: str | Path | None = None, scenario: str | Path | None = None, seed: Optional[int] = None,
          write_config: str | Path | None = None, status_file: str | Path | None = None,
          status_period_s: float = 0.05, duration_s: Optional[float] = None,
          rt_priority: Optional[int] = None, cpu_affinity: Optional[Sequence[int]] = None,
          runtime_rt_priority: Optional[int] = None, runtime_cpu_affinity: Optional[Sequence[int]] = None,
          can_interface: str = "slcan", can_responder: str = "process", out=None) -> int:
    """Body of ``rig sim``: build, print the port lines (and write the config), ``ready``,
    serve until SIGINT/SIGTERM (or ``duration_s``), shut down cleanly; returns 0.

    ``rt_priority`` / ``cpu_affinity``: SCHED_FIFO priority of the CAN responder (the plant
    side's threads get one less) and CPUs for the simulator (set before any thread or
    process is started, so all inherit them), when the OS permits — reported on stderr
    either way. ``can_responder``: "process" (the SLCAN adapter and the drives in a child
    process of their own) or "thread" (in this process; see :class:`RealtimeSim`).
    ``runtime_rt_priority`` / ``runtime_cpu_affinity``: written as
    ``realtime.sched_fifo_priority`` / ``realtime.cpu_affinity`` into the generated config,
    for the ``rig run`` that uses it (docs/sim-process.md has measurements).
    ``can_interface``: the python-can interface the generated config names for the
    adapter's pty — ``slcan`` (python-can's own client) or ``rig_slcan``
    (drivers/slcan_bus.py, which reads whole buffers instead of single bytes)."""
    from rig_runtime.scenario import load_scenario
    out = out or sys.stdout
    # a thread waking for its deadline waits for the interpreter lock up to the switch
    # interval (5 ms by default): measured p99 release lateness 2.7 ms -> 0.35 ms at 0.5 ms
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    for name in ("can", "canopen", "pymodbus"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    src = Path(config_path) if config_path else rig_config.DEFAULT_CONFIG
    cfg = rig_config.load(src)
    sc = load_scenario(scenario) if scenario else None
    if cpu_affinity:
        err = set_cpu_affinity(cpu_affinity)
        _say(f"cpu affinity {sorted(cpu_affinity)}: " + (f"not applied ({err})" if err else "applied"))
    if rt_priority is not None:
        # the CAN responder (the latency-critical part) at rt_priority, every thread of the
        # plant side (plant, F/T server, status) one below, all SCHED_FIFO: a plant-side thread
        # holding the interpreter lock is then never preempted by ordinary load
        plant_prio = max(1, rt_priority - 1)
        err = set_sched_fifo(plant_prio)
        if err:
            _say(f"SCHED_FIFO priority {rt_priority}: not applied ({err})")
            rt_priority = None
        else:
            _say(f"SCHED_FIFO priority {rt_priority} (CAN responder), {plant_prio} (plant side): applied")
    stop = threading.Event()
    old = {}
    for s in (signal.SIGINT, signal.SIGTERM):
        old[s] = signal.signal(s, lambda *_: stop.set())
    rt = None
    try:
        rt = RealtimeSim(cfg, sc, seed=seed, status_file=status_file, status_period_s=status_period_s,
                         can_responder=can_responder, responder_rt_priority=rt_priority)
        lines = port_lines(rt.laser_ports, rt.can_port, rt.ft_endpoints)    # the ports exist from construction on
        if write_config:
            rt_over: dict[str, Any] = {}
            if runtime_rt_priority is not None:
                rt_over["sched_fifo_priority"] = int(runtime_rt_priority)
            if runtime_cpu_affinity:
                rt_over["cpu_affinity"] = [int(c) for c in runtime_cpu_affinity]
            devices = devices_section(cfg.devices, rt.laser_ports, rt.laser_rates_hz, can_interface,
                                      rt.can_port, rt.ft_endpoints)
            write_generated_config(write_config, src, devices, {"realtime": rt_over} if rt_over else None)
        gc.collect()                    # collections while serving then skip the start-up objects
        gc.freeze()
        rt.start()
        if status_file:
            rt.write_status()
            lines.append(f"status {Path(status_file).resolve()}")
        if write_config:
            lines.append(f"config {Path(write_config).resolve()}")
        lines.append("ready")
        try:
            out.write("\n".join(lines) + "\n")
            out.flush()
        except (BrokenPipeError, OSError):
            pass
        t_end = time.monotonic() + duration_s if duration_s is not None else math.inf
        while not stop.wait(min(0.2, max(0.0, t_end - time.monotonic()))):
            if time.monotonic() >= t_end:
                break
        tm = rt.timing()
        _say(f"stopping; plant steps {tm['steps']}, late {tm['late_steps']}, release lateness "
             f"p50/p99/max {tm['recent_lateness_us']['p50']:.0f}/{tm['recent_lateness_us']['p99']:.0f}/"
             f"{tm['max_lateness_us']:.0f} us, sessions {rt.sessions}")
    finally:
        if rt is not None:
            rt.close()
        for s, hnd in old.items():
            signal.signal(s, hnd)
    return 0
