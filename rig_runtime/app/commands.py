"""``rig run``, ``rig dry-run``, ``rig check``, ``rig export`` (registered with the CLI on import).

``rig run`` and ``rig dry-run`` call ``preflight.check_run`` (what ``rig check`` runs and
prints) before a device is opened or a log created."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from . import preflight
from .command import arg, command
from .metrics import clean
from .quiet import quiet_device_libraries
from .runner import EXIT_OK, default_log_path, execute


def _run_time(summary: dict, t: float) -> str:
    """A loop-clock time as run time (s since RUNNING began), or as it is if the start is unknown."""
    t0 = summary.get("run_started_t")
    if t0 is None or t0 != t0:
        return f"t={t:.3f} s (loop clock)"
    return f"t={t - t0:+.3f} s"


def _print_summary(summary: dict, as_json: bool) -> None:
    """The end-of-run summary. Fault times are run time (s since RUNNING began) in every mode;
    a lockstep run has no deadlines (its lateness and work are zero by construction), so it
    reports what a cycle cost in wall-clock time instead."""
    t0 = summary.get("run_started_t")
    if t0 is not None and t0 == t0:
        for f in summary["faults"]:
            f.setdefault("t_run", f["t"] - t0)
    if as_json:
        print(json.dumps(clean(summary)))
        return
    t = summary["timing"]
    if summary.get("stopped_by"):
        print(f"stopped by {summary['stopped_by']} (operator stop: current ramped to zero, power stages off)")
    elif summary.get("ended_by"):
        print(f"ended by {summary['ended_by']}"
              + (f" ({summary['late_stop']} came after the end)" if summary.get("late_stop") else ""))
    print(f"final state: {summary['final_state']}   cycles: {summary['cycles']}   log: {summary['log']}")
    wire = summary["max_abs_wire_current_A"]
    print(f"currents: max |u| (differential current per carrier) {summary['max_abs_current_A']:.3f} A, "
          f"max |i| per wheel (wire current: ±u/2, all of u on a lone wheel) {wire:.3f} A")
    for f in summary["faults"]:
        print(f"  fault at {_run_time(summary, f['t'])}: {f['device']} {f['check']} value={f['value']} "
              f"limit={f['limit']} {f['message']}")
    for d in summary.get("degraded", ()):
        print(f"  DEGRADED at {_run_time(summary, d['t_start'])}: {d['carrier']} carrier on the observer's "
              f"estimate ({d['laser']} {d['check']}) until {_run_time(summary, d['t_end'])}: {d['end']}")
    for d in summary.get("reconfigured", ()):
        print(f"  RECONFIGURED at {_run_time(summary, d['t_start'])}: drive {d['device']} lost ({d['check']}), "
              f"{d['carrier']} carrier on its remaining wheels until {_run_time(summary, d['t_end'])}: {d['end']}")
    if summary.get("arm_failed"):
        print(f"  {summary['arm_failed']}")
    rec = summary.get("recorder")
    if rec and not rec["healthy"] and not any(f["device"] == "recorder" for f in summary["faults"]):
        print(f"  recorder: {rec['error']}")     # the log is not whole, though the run did not fault
    if summary.get("clock") == "lockstep":
        cycles = max(summary["cycles"], 1)
        print(f"timing: lockstep (simulated clock, no deadlines): {summary['wall_time_s'] * 1e3 / cycles:.3f} ms "
              f"wall-clock per cycle (runtime and simulated plant); simulated {summary.get('sim_time_s', 0.0):.1f} s "
              f"in {summary['wall_time_s']:.2f} s wall")
    else:
        lat, work = t["release_lateness_us"], t["cycle_work_us"]
        print(f"timing: lateness p50/p99/max {lat['p50']:.1f}/{lat['p99']:.1f}/{lat['max']:.1f} us, "
              f"work p50/p99/max {work['p50']:.1f}/{work['p99']:.1f}/{work['max']:.1f} us, "
              f"deadline misses {t['deadline_misses']}")
    if "steps" in summary:
        if summary.get("clock") != "lockstep":
            print(f"simulated {summary['sim_time_s']:.1f} s in {summary['wall_time_s']:.1f} s wall")
        several = len({s.get("carrier") for s in summary["steps"]}) > 1
        for s in summary["steps"]:
            def f(v, fmt):
                return format(v, fmt) if v is not None else "-"
            who = f"{s['carrier']} " if several else ""
            print(f"  {who}step {s['from_mm']:+.2f} -> {s['to_mm']:+.2f} mm at {s['t0']:.1f}s: rise {f(s['rise_time_s'], '.2f')} s, "
                  f"overshoot {f(s['overshoot_pct'], '.1f')} %, settling {f(s['settling_time_s'], '.2f')} s, "
                  f"steady-state error {f(s['steady_state_error_mm'], '+.4f')} mm")


_LIVE_OPTIONS = (
    (("--telemetry",), dict(metavar="udp://HOST:PORT", help="stream every cycle as JSON datagrams (PlotJuggler's UDP server)")),
    (("--telemetry-every",), dict(type=int, default=1, metavar="N", help="send every Nth cycle (default 1: every cycle)")),
    (("--foxglove",), dict(metavar="[HOST:]PORT", help="serve the signals to Foxglove over WebSocket (needs rig-runtime[foxglove])")),
    (("--no-panel",), dict(action="store_true", help="no live panel on the terminal (the panel needs rich)")),
    (("--ctl-socket",), dict(metavar="PATH", help="Unix socket for `rig ctl` (default: rig ctl's default path)")),
    (("--no-ctl",), dict(action="store_true", help="no `rig ctl` socket")),
    (("--hold-on-fault",), dict(action="store_true", help="after a FAULT keep the loop (no current, power stages off) "
                                                          "until `rig ctl reset-fault` arms again or a stop")),
)


def live_options(fn):
    """The live-view and operator options ``rig run`` and ``rig dry-run`` share."""
    for a, kw in reversed(_LIVE_OPTIONS):
        fn = arg(*a, **kw)(fn)
    return fn


def _live_outputs(args: argparse.Namespace, realtime: bool) -> list[tuple[str, dict]]:
    """The live views asked for: telemetry and Foxglove when given; the panel on a terminal
    (not with --json); the `rig ctl` socket in real-time runs (a lockstep run is over
    before an operator could type)."""
    from ..errors import ConfigError
    from .live import outputs_for
    if args.telemetry_every < 1:
        raise ConfigError(None, "--telemetry-every", "an integer >= 1", args.telemetry_every)
    ctl = None
    if realtime and not args.no_ctl:
        from .ctl_server import default_ctl_path
        ctl = str(args.ctl_socket or default_ctl_path())
    if args.hold_on_fault and ctl is None:      # nothing could reset or stop the held fault
        raise ConfigError(None, "--hold-on-fault", "a real-time run with a `rig ctl` socket (not lockstep, "
                          "not --no-ctl): a held fault ends only by rig ctl reset-fault or stop")
    panel = realtime and sys.stderr.isatty() and not args.json and not args.no_panel
    return outputs_for(telemetry=args.telemetry, telemetry_every=args.telemetry_every, foxglove=args.foxglove,
                       panel=panel, ctl_socket=ctl)


@command("dry-run", "run the controller against the simulated plant (lockstep by default)", stops=True)
@arg("--config", help="config file (default: configs/sim.yaml)")
@arg("--scenario", default="single-step", help="scenario name in configs/scenarios or a path (default: single-step)")
@arg("--realtime", action="store_true", help="real-time clock; the plant runs in a separate process")
@arg("--duration", type=float, help="seconds of RUNNING (default: the scenario's)")
@arg("--seed", type=int, help="random seed of the simulated sensors (default: sim.seed)")
@arg("--log", help="HDF5 log path (default: logs/dry-run-<time>.h5)")
@arg("--json", action="store_true", help="print one JSON summary object")
@arg("--report", metavar="DIR", help="write PNG plots and a Markdown summary into DIR")
@live_options
def cmd_dry_run(args: argparse.Namespace) -> int:
    from .. import config
    from ..scenario import load_scenario
    quiet_device_libraries()
    cfg = config.load(args.config)
    scenario = load_scenario(args.scenario)
    log = Path(args.log) if args.log else default_log_path("dry-run")
    preflight.check_run(cfg, scenario, args.duration, log=log, log_is_default=not args.log, report=args.report)
    outputs = _live_outputs(args, realtime=args.realtime)
    if args.realtime:
        from .metrics import steps_from_log
        from .realtime_dryrun import run_realtime_dry_run
        summary, code = run_realtime_dry_run(cfg, scenario, log, seed=args.seed, duration_s=args.duration,
                                             status=sys.stderr.isatty() and not args.json, stops=args.stops,
                                             outputs=outputs, hold_on_fault=args.hold_on_fault)
        summary["steps"] = steps_from_log(log, scenario, cfg.controller.h)
    else:
        from .dryrun import run_lockstep
        summary, code = run_lockstep(cfg, scenario, log, seed=args.seed, duration_s=args.duration, stops=args.stops,
                                     outputs=outputs, hold_on_fault=args.hold_on_fault)
    if args.report:
        from .report import write_report
        try:
            summary["report"] = [str(p) for p in write_report(log, args.report, scenario, summary)]
        except (OSError, RuntimeError) as e:     # checked before the run; a disk can still fail: keep the summary
            summary["report_error"] = str(e)
            print(f"rig dry-run: report not written: {e}", file=sys.stderr)
    _print_summary(summary, args.json)
    return code


@command("run", "run the controller on the rig (hardware devices from the config)", stops=True)
@arg("--config", default=None, help="config file (default: configs/rig.yaml)")
@arg("--scenario", help="reference profile: scenario name or path (default: hold y_ref = 0)")
@arg("--duration", type=float, help="seconds of RUNNING (default: the scenario's, else until SIGINT/SIGTERM)")
@arg("--log", help="HDF5 log path (default: logs/run-<time>.h5)")
@arg("--json", action="store_true", help="print one JSON summary object at the end")
@live_options
def cmd_run(args: argparse.Namespace) -> int:
    from .. import config
    from ..clock import RealtimeClock, apply_realtime
    from ..devices import RigDevices
    from ..memo import compute_only
    from ..scenario import load_scenario
    compute_only()          # the gate and the designs that let the power stages on: computed here, never read from disk
    quiet_device_libraries()
    cfg = config.load(args.config or config.CONFIG_DIR / "rig.yaml")
    scenario = load_scenario(args.scenario) if args.scenario else None
    log = Path(args.log) if args.log else default_log_path("run")
    preflight.check_run(cfg, scenario, args.duration, log=log, log_is_default=not args.log)
    outputs = _live_outputs(args, realtime=True)
    from .commission.record import config_hash, default_path, passed_on_record
    if not passed_on_record(cfg):       # a warning only: the checks of issue 21 are the operator's call
        print(f"rig run: warning: no passed commissioning on record for this config (hash {config_hash(cfg)} in "
              f"{default_path()}); run `rig commission` before the first closed loop (docs/commissioning.md)",
              file=sys.stderr)
    devices = RigDevices(cfg)
    rt_report = apply_realtime(cfg.realtime)
    if not args.json:
        for line in rt_report:
            print(f"realtime: {line}", file=sys.stderr)
    clock = RealtimeClock(cfg.realtime.spin_us * 1e-6)
    summary, code, _ = execute(cfg, devices, clock, scenario=scenario, duration_s=args.duration, log_path=log,
                               status=sys.stderr.isatty() and not args.json,
                               extra_attrs={"mode": "run", "realtime": "; ".join(rt_report)}, stops=args.stops,
                               outputs=outputs, hold_on_fault=args.hold_on_fault)
    summary["realtime"] = rt_report
    _print_summary(summary, args.json)
    return code


@command("export", "export a log to CSV (the same as `rig log export`)")
@arg("log", help="HDF5 log written by rig run / rig dry-run")
@arg("--csv", required=True, metavar="OUT", help="CSV file to write (events go to OUT.events.csv)")
def cmd_export(args: argparse.Namespace) -> int:
    from .log_commands import export_csv
    return export_csv(args.log, args.csv)


@command("check", "validate a config and scenario exactly as `rig run`/`rig dry-run` do before they start, "
                  "and print what would run (exit 0: all fine, 2: one line naming the cause)")
@arg("--config", help="config file (default: configs/sim.yaml; the rig PC's is configs/rig.yaml)")
@arg("--scenario", help="scenario name in configs/scenarios or a path (default: none, hold y_ref = 0)")
@arg("--duration", type=float, help="seconds of RUNNING (default: the scenario's)")
@arg("--log", help="the HDF5 log path to check (default: logs/run-<time>.h5)")
@arg("--machine", action="store_true", help="also: is this machine ready for `rig run` with this config (kernel, "
     "real-time limits, devices; default config: configs/rig.yaml); exit 2 if something would keep it from working")
def cmd_check(args: argparse.Namespace) -> int:
    from .. import config
    from ..memo import compute_only
    from ..scenario import load_scenario
    compute_only()          # writes nothing, the user's cache included: every check computed here
    # --machine asks about the rig PC: its default config is the rig's
    cfg = config.load(args.config or (config.CONFIG_DIR / "rig.yaml" if args.machine else None))
    scenario = load_scenario(args.scenario) if args.scenario else None
    log = Path(args.log) if args.log else default_log_path("run")
    plan = preflight.check_run(cfg, scenario, args.duration, log=log, log_is_default=not args.log)
    for line in preflight.describe(plan):
        print(line)
    if not args.machine:
        print("ok: every check passed")
        return EXIT_OK
    print("ok: every check of `rig check` passed")
    from .machine_check import report_machine
    return report_machine(cfg)
