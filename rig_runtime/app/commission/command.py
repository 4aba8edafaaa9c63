"""``rig commission [--config PATH] [--only CHECK,…] [--yes]``: the wiring checks before the
first closed loop, against the devices of the config (the rig, or ``rig sim``'s generated
config), with a report and a line on the commissioning record (docs/commissioning.md)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..command import arg, command
from ..quiet import quiet_device_libraries
from . import CHECKS

EXIT_PASS, EXIT_SETUP, EXIT_FAILED = 0, 2, 3


def _checks(only: str | None) -> tuple[str, ...] | str:
    """The checks asked for, or the one-line complaint about an unknown name."""
    if only is None:
        return CHECKS
    names = [n.strip() for n in only.split(",") if n.strip()]
    bad = [n for n in names if n not in CHECKS]
    if bad or not names:
        return (f"unknown check {bad[0]!r} in --only" if bad else "--only names no check") + \
            f" (known: {', '.join(CHECKS)})"
    return tuple(c for c in CHECKS if c in names)


def _confirm(yes: bool):
    def confirm(text: str) -> bool:
        print(f"rig commission: {text}", file=sys.stderr, flush=True)
        if yes:
            print("rig commission: go (--yes)", file=sys.stderr, flush=True)
            return True
        try:
            return input("Ready? [y/N] ").strip().lower() in ("y", "yes")
        except EOFError:
            return False
    return confirm


@command("commission", "wiring checks before the first closed loop: the lasers by hand (power stages off), "
                       "short current bumps through the supervisor's ARM with the carriers lifted, the "
                       "encoders and the bumps on the rollers; a report recorded as a normal log, and a "
                       "record (exit 0 all passed, 3 a check failed, 2 bad input)", stops=True)
@arg("--config", default=None, help="config file (default: configs/rig.yaml; for `rig sim`: its generated config)")
@arg("--only", metavar="CHECK,…", help=f"run only these checks (of {', '.join(CHECKS)})")
@arg("--yes", action="store_true", help="no prompts: the operator has prepared every step (needed without a terminal)")
@arg("--passive-s", type=float, default=None, help="the operator's window for the passive motions (default 8 s)")
@arg("--report", metavar="PATH", help="write the report as JSON (default: logs/commission-<time>.json; the "
                                      "commissioning's log beside it, .h5)")
@arg("--record", metavar="PATH", help="the commissioning record file (default: see docs/commissioning.md)")
@arg("--json", action="store_true", help="print the report as one JSON object")
def cmd_commission(args: argparse.Namespace) -> int:
    from ... import config
    from ...clock import RealtimeClock, apply_realtime
    from ...devices import RigDevices
    from ..runner import default_log_path
    from . import procedure, record
    checks = _checks(args.only)
    if isinstance(checks, str):
        print(f"rig commission: error: {checks}", file=sys.stderr)
        return EXIT_SETUP
    if not args.yes and not sys.stdin.isatty():
        print("rig commission: error: the checks need the operator's go at each prompt but stdin is not a "
              "terminal; run it from a terminal or pass --yes", file=sys.stderr)
        return EXIT_SETUP
    passive_s = procedure.PASSIVE_S if args.passive_s is None else args.passive_s
    if not 0.5 <= passive_s <= 120:
        print(f"rig commission: error: --passive-s {passive_s} is not within 0.5..120 s", file=sys.stderr)
        return EXIT_SETUP
    quiet_device_libraries()
    cfg = config.load(args.config or config.CONFIG_DIR / "rig.yaml")
    report_path = Path(args.report) if args.report else default_log_path("commission").with_suffix(".json")
    report_path.parent.mkdir(parents=True, exist_ok=True)
    devices = RigDevices(cfg)
    for line in apply_realtime(cfg.realtime):
        print(f"realtime: {line}", file=sys.stderr)
    rep = procedure.run(cfg, devices, RealtimeClock(cfg.realtime.spin_us * 1e-6), checks,
                        confirm=_confirm(args.yes), say=lambda s: print(f"rig commission: {s}", file=sys.stderr),
                        passive_s=passive_s, stops=args.stops, log_prefix=report_path.with_suffix(""),
                        config_hash=record.config_hash(cfg), prompts_wait=not args.yes)
    if args.stops.requested:
        raise args.stops.interrupted("during commissioning: power stages off, no result on record")
    d = rep.as_dict()
    d.update(config_source=cfg.source, config_hash=record.config_hash(cfg))
    report_path.write_text(json.dumps(d, indent=1, default=str) + "\n")
    rec = record.append(cfg, rep.passed, rep.checks, Path(args.record) if args.record else None)
    if args.json:
        print(json.dumps(d, default=str))
    else:
        print(rep.text())
        print(f"report: {report_path}   log: {rep.log}   record: {rec}")
    return EXIT_PASS if rep.passed else EXIT_FAILED
