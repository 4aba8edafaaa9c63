"""``rig log info|plot|compare|export``: look at any recorded log after the run (``rig run``,
``rig dry-run`` lockstep or real-time, a run that ended in FAULT, a log cut short).

Registered as one ``rig log`` command whose actions have parsers of their own (``rig log
plot --help``). A file that is not a rig log, a missing file or an output that cannot be
written is one line naming it and exit 2 (:class:`~rig_runtime.errors.LogError`,
:class:`~rig_runtime.errors.ConfigError`)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from ..errors import ConfigError
from . import preflight
from .command import Actions, command
from .metrics import clean

EXIT_OK = 0
ACTIONS = Actions("log")
_action, _a = ACTIONS.action, ACTIONS.arg


@command("log", "look at a recorded log: info, plot, compare, export (any log: rig run, dry runs, FAULT runs)")
def cmd_log(args: argparse.Namespace) -> int:
    return ACTIONS.dispatch(args)


# ``rig log`` takes actions with their own arguments: its parser gets sub-parsers
ACTIONS.install()


def _out_dir(path: str) -> Path:
    preflight.check_plot_dir(path, "--out")
    return Path(path)


# ---------------------------------------------------------------------------------------- info
@_action("info", "rows, duration, final state, faults in run time, DEGRADED intervals, scenario, config source, "
                 "step metrics, the control law's signals",
         _a("log", help="HDF5 log written by rig run / rig dry-run"),
         _a("--json", action="store_true", help="print one JSON object"))
def log_info(args: argparse.Namespace) -> int:
    from ..logformat import law_signals
    from . import runlog
    run = runlog.load(args.log)
    d = runlog.info(run)
    d["law_signals"] = law_signals(run.attrs)      # name -> SI unit; columns <carrier>_<name>
    if args.json:
        print(json.dumps(clean(d)))
    else:
        lines = runlog.format_info(d)
        if d["law_signals"]:
            law = run.config.get("controller", {}).get("law", "")
            lines.append(f"control law {law}: signals (columns <carrier>_<name>): "
                         + ", ".join(f"{n} [{u}]" for n, u in d["law_signals"].items()))
        print("\n".join(lines))
    return EXIT_OK


# ---------------------------------------------------------------------------------------- plot
def open_loop_carrier(run) -> str | None:
    """The carrier a log's open-loop scenario drove, if the scenario file is still there."""
    from . import runlog
    sc, _ = runlog.scenario_of(run)
    return sc.open_loop.carrier if sc is not None and sc.open_loop is not None else None


@_action("plot", "PNG figures of a log (Figs. 15-18 style, the same as --report): y, psi, dw, u with states, "
                 "faults and limits; F/T forces and moments; the observer's ŷ against y and the simulated truth "
                 "(a dry run's), DEGRADED shaded; the control law's signals by name (law.png)",
         _a("log", help="HDF5 log"),
         _a("--out", metavar="DIR", help="directory for the PNGs (default: LOG without .h5, plus '-plots')"))
def log_plot(args: argparse.Namespace) -> int:
    from . import figures, runlog
    out = _out_dir(args.out or str(Path(args.log).with_suffix("")) + "-plots")
    run = runlog.load(args.log)
    files = figures.write_all(figures.log_figures(run, open_loop_carrier(run)), out)
    for f in files:
        print(f)
    return EXIT_OK


# ---------------------------------------------------------------------------------------- compare
METRICS = (("rise_time_s", "rise (s)"), ("overshoot_pct", "overshoot (%)"), ("settling_time_s", "settling (s)"),
           ("steady_state_error_mm", "steady-state error (mm)"))


def _diff(a, b):
    if a is None or b is None or (isinstance(a, float) and math.isnan(a)) or (isinstance(b, float) and math.isnan(b)):
        return None
    return b - a


def compare_table(ia: dict, ib: dict) -> list[dict]:
    """Rows (quantity, A, B, B − A) of two ``runlog.info`` results: the run figures and the
    step metrics of steps at the same time (None where either lacks it)."""
    rows = []

    def row(name, a, b):
        rows.append({"quantity": name, "a": a, "b": b, "b_minus_a": _diff(a, b)
                     if isinstance(a, (int, float)) and isinstance(b, (int, float)) else None})
    row("rows", ia["rows"], ib["rows"])
    row("RUNNING (s)", ia["running_s"], ib["running_s"])
    row("final state", ia["final_state"], ib["final_state"])
    row("faults", len(ia["faults"]), len(ib["faults"]))
    for k in sorted(set(ia["max_abs_u_A"]) | set(ib["max_abs_u_A"])):
        row(f"max |u| {k} (A)", ia["max_abs_u_A"].get(k), ib["max_abs_u_A"].get(k))
    sa = {round(s["t0"], 6): s for s in ia["steps"]}
    sb = {round(s["t0"], 6): s for s in ib["steps"]}
    for t0 in sorted(set(sa) | set(sb)):
        for key, name in METRICS:
            row(f"step at {t0:g} s: {name}", sa.get(t0, {}).get(key), sb.get(t0, {}).get(key))
    return rows


def _cell(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


@_action("compare", "overlay figure of two logs and a table of their metric differences (B - A)",
         _a("a", metavar="A", help="first HDF5 log"),
         _a("b", metavar="B", help="second HDF5 log"),
         _a("--out", metavar="DIR", help="directory for compare.png and compare.md (default: no files, table only)"),
         _a("--json", action="store_true", help="print one JSON object"))
def log_compare(args: argparse.Namespace) -> int:
    from . import figures, runlog
    out = _out_dir(args.out) if args.out else None
    ra, rb = runlog.load(args.a), runlog.load(args.b)
    ia, ib = runlog.info(ra), runlog.info(rb)
    table = compare_table(ia, ib)
    files: list[Path] = []
    if out is not None:
        files = figures.write_all({"compare": figures.compare([ra, rb], [f"A {ra.path.name}", f"B {rb.path.name}"])}, out)
        md = out / "compare.md"
        lines = [f"# {ra.path.name} (A) vs {rb.path.name} (B)", "", "| quantity | A | B | B − A |", "|---|---|---|---|"]
        lines += [f"| {r['quantity']} | {_cell(r['a'])} | {_cell(r['b'])} | {_cell(r['b_minus_a'])} |" for r in table]
        lines += ["", "Figure: `compare.png`", ""]
        try:
            md.write_text("\n".join(lines))
        except OSError as e:
            raise ConfigError(str(md), "", f"a writable output file ({e.strerror})") from None
        files.append(md)
    if args.json:
        print(json.dumps(clean({"a": str(ra.path), "b": str(rb.path), "table": table, "files": [str(f) for f in files]})))
        return EXIT_OK
    print(f"A: {ra.path}\nB: {rb.path}")
    w = max(len(r["quantity"]) for r in table)
    print(f"{'':<{w}}  {'A':>12} {'B':>12} {'B - A':>12}")
    for r in table:
        print(f"{r['quantity']:<{w}}  {_cell(r['a']):>12} {_cell(r['b']):>12} {_cell(r['b_minus_a']):>12}")
    for f in files:
        print(f)
    return EXIT_OK


# ---------------------------------------------------------------------------------------- export
def export_csv(log: str, out: str) -> int:
    """``rig log export`` and ``rig export``: the log as CSV with units in the header and state
    names, the events beside it as ``OUT.events.csv``; prints what it wrote."""
    from ..errors import LogError
    from .export import events_path_for, to_csv
    if not Path(log).exists():
        raise LogError(log, "no such file")
    ev = events_path_for(out)
    for p, what in ((Path(out), "--csv"), (ev, "--csv (its events file)")):
        if p.resolve() == Path(log).resolve():
            raise ConfigError(None, what, "a file other than the log itself", str(p))
        preflight.check_output_file(p, what)
    n = to_csv(log, out)
    print(f"{n} rows -> {out}; events -> {ev}")
    return EXIT_OK


def export_mcap(log: str, out: str) -> int:
    """``rig log export --mcap``: the log for Foxglove, with the live server's topics."""
    from ..errors import LogError
    from .foxglove_out import export_mcap as write_mcap
    if not Path(log).exists():
        raise LogError(log, "no such file")
    if Path(out).resolve() == Path(log).resolve():
        raise ConfigError(None, "--mcap", "a file other than the log itself", out)
    preflight.check_output_file(Path(out), "--mcap")
    n = write_mcap(log, out)
    print(f"{n} rows -> {out}")
    return EXIT_OK


@_action("export", "the log as CSV (units in the header, state names; events to OUT.events.csv) "
                   "and/or as MCAP for Foxglove",
         _a("log", help="HDF5 log"),
         _a("--csv", metavar="OUT", help="CSV file to write (events go to OUT.events.csv)"),
         _a("--mcap", metavar="OUT", help="MCAP file to write (needs rig-runtime[foxglove])"))
def log_export(args: argparse.Namespace) -> int:
    if not args.csv and not args.mcap:
        raise ConfigError(None, "rig log export", "--csv OUT and/or --mcap OUT")
    if args.csv:
        export_csv(args.log, args.csv)
    if args.mcap:
        export_mcap(args.log, args.mcap)
    return EXIT_OK
