"""``rig sim``: serve the simulated rig in its own process, in real time, for an unmodified
``rig run`` in another process (registered with the CLI on import; the work is done by
``sim_backend.serve``, imported only when the command runs).

Output on stdout, one line each, then ``ready``::

    laser b_f /dev/pts/7            (one per laser role)
    can slcan /dev/pts/9            (the emulated SLCAN adapter)
    ft ft_fl 127.0.0.1:40123        (one per force–torque sensor, Modbus TCP)
    status /abs/path/status.json    (with --status-file)
    config /abs/path/generated.yaml (with --write-config)
    ready

See docs/sim-process.md.
"""

from __future__ import annotations

import argparse

from .command import arg, command


def _cpus(text: str) -> list[int]:
    """``0`` or ``0,2`` -> [0] / [0, 2]."""
    try:
        cpus = [int(c) for c in text.split(",") if c.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected CPU numbers like 0 or 0,2, got {text!r}") from None
    if not cpus or min(cpus) < 0:
        raise argparse.ArgumentTypeError(f"expected CPU numbers like 0 or 0,2, got {text!r}")
    return cpus


def _checked(fn):
    """Check the operator's input before anything is served (one line and exit 2 each): the
    durations, the output files, and the scenario's faults and disturbances against the
    simulated rig (``preflight.validate_scenario``)."""
    import functools

    @functools.wraps(fn)
    def run(args: argparse.Namespace) -> int:
        from .. import config
        from . import preflight
        from ..scenario import load_scenario
        preflight.check_duration(args.duration)
        preflight.check_duration(args.status_period, "--status-period")
        for path, what in ((args.write_config, "--write-config"), (args.status_file, "--status-file")):
            if path:
                preflight.check_output_file(path, what, create_dir=True)
        if args.scenario:
            preflight.validate_scenario(config.load(args.config), load_scenario(args.scenario))
        return fn(args)
    return run


@command("sim", "serve the simulated rig in real time for `rig run` in another process "
                "(lasers on ptys, SLCAN adapter on a pty, Modbus TCP F/T sensors)")
@arg("--config", help="config file of the simulated rig (default: configs/sim.yaml)")
@arg("--scenario", help="scenario name or path whose disturbances and faults the plant applies "
                        "(scenario time starts when the runtime has enabled every drive)")
@arg("--seed", type=int, help="random seed of the simulated sensors (default: sim.seed)")
@arg("--write-config", metavar="PATH", help="write a rig config for `rig run --config PATH` pointing at the ports")
@arg("--status-file", metavar="PATH", help="rewrite a JSON status (applied currents, drive states, plant, timing) "
                                           "every --status-period")
@arg("--status-period", type=float, default=0.05, metavar="S", help="status file period, s (default 0.05)")
@arg("--duration", type=float, metavar="S", help="stop after S seconds (default: serve until SIGINT/SIGTERM)")
@arg("--rt-priority", type=int, metavar="N", help="SCHED_FIFO priority of the CAN responder; the plant side's "
                                                 "threads get N-1 (when permitted)")
@arg("--cpu-affinity", type=_cpus, metavar="CPUS", help="CPUs for the simulator, e.g. 0 or 0,2 (when permitted)")
@arg("--runtime-rt-priority", type=int, metavar="N",
     help="write realtime.sched_fifo_priority: N into the generated config (for the rig run that uses it)")
@arg("--runtime-cpu-affinity", type=_cpus, metavar="CPUS",
     help="write realtime.cpu_affinity: [CPUS] into the generated config")
@arg("--can-interface", default="rig_slcan", choices=("slcan", "rig_slcan"),
     help="python-can interface the generated config uses for the SLCAN pty: rig_slcan (default: the "
          "project's buffer-reading client, measured drive poll 0.12 ms p50) or slcan (python-can's own "
          "client, reads byte by byte: 1.8 ms p50)")
@arg("--can-responder", default="process", choices=("process", "thread"),
     help="where the emulated SLCAN adapter and the virtual drives run: process (default: a child "
          "process of their own, so no plant-side thread delays a TPDO) or thread (in this process)")
@_checked
def cmd_sim(args: argparse.Namespace) -> int:
    from sim_backend.serve import serve
    return serve(args.config, args.scenario, args.seed, write_config=args.write_config,
                 status_file=args.status_file, status_period_s=args.status_period, duration_s=args.duration,
                 rt_priority=args.rt_priority, cpu_affinity=args.cpu_affinity,
                 runtime_rt_priority=args.runtime_rt_priority, runtime_cpu_affinity=args.runtime_cpu_affinity,
                 can_interface=args.can_interface, can_responder=args.can_responder)
