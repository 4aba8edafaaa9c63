"""The ``rig`` command: ``rig tune``, ``rig dry-run``, ``rig run``, ``rig sim``, ``rig export``.

Errors the operator can act on (a bad config, a missing device) end the program with a
one-line message naming the cause and exit code 2; nothing starts before the config is valid.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable

from .errors import RigError

Command = Callable[[argparse.Namespace], int]
_COMMANDS: dict[str, tuple[Command, Callable[[argparse.ArgumentParser], None], str]] = {}


def command(name: str, help: str):
    """Register a subcommand: ``fn(args) -> exit code``, with ``fn.add_args(parser)``."""
    def deco(fn):
        def add(p: argparse.ArgumentParser) -> None:
            for a, kw in getattr(fn, "_args", []):
                p.add_argument(*a, **kw)
        _COMMANDS[name] = (fn, add, help)
        return fn
    return deco


def arg(*a, **kw):
    def deco(fn):
        fn._args = [(a, kw)] + getattr(fn, "_args", [])
        return fn
    return deco


def _fmt_ev(ev) -> str:
    out = []
    for e in ev:
        out.append(f"{e.real:9.3f}" + (f"{e.imag:+.3f}j" if abs(e.imag) > 1e-9 else ""))
    return "[" + ", ".join(s.strip() for s in out) + "]"


@command("tune", "eigenvalues and design checks of Sec. 5.1/5.2.3 for the configured gains")
@arg("--config", help="config file (default: the shipped simulated rig, configs/sim.yaml)")
@arg("--json", action="store_true", help="print one JSON object instead of a table")
@arg("--plot", metavar="DIR", help="write root-locus and eigenvalue PNGs into DIR (needs matplotlib)")
@arg("--design", action="store_true", help="design the PI-PD gains for the configured plant (Sec. 5.2.3)")
@arg("--write", metavar="CONTROLLER.yaml", help="with --design: write a controller: fragment with the proposal")
def cmd_tune(args: argparse.Namespace) -> int:
    from . import analysis, config
    cfg = config.load(args.config)
    if args.design or args.write:
        from .app.design_command import run_design
        return run_design(cfg, args)
    r = analysis.tune(cfg)
    files = analysis.plot(cfg, r, args.plot) if args.plot else []
    if args.json:
        out = analysis.to_json(r)
        if files:
            out["plots"] = [str(f) for f in files]
        print(json.dumps(out))
        return 0
    P = analysis.PAPER
    rows = [
        ("inner loop (15)", r.inner, P["inner"]),
        ("inner loop with differentiator (16)", r.inner_filtered, P["inner_filtered"]),
        (f"outer loop (17) [{cfg.tuning.outer_lateral_form}]", r.outer, P["outer"]),
        ("complete closed loop (19)", r.closed_loop, P["closed_loop"]),
        ("sampled loop as implemented (h, Tustin)", r.closed_loop_sampled, None),
        ("open-loop poles of (10)", r.open_loop_poles, None),
    ]
    print(f"config: {cfg.source}")
    pr = r.params
    print(f"plant: omega0={pr['omega0']:g} 1/s  D={pr['D']:g}  K={pr['K']:g} rad/A  c_y={pr['c_y']:.5f}  "
          f"lateral pole (10)={-pr['a_lat']:.4f} 1/s, (17)={-pr['a_outer']:.4f} 1/s")
    g = cfg.controller.pipd
    print(f"gains: K_P,y={g.K_P_y:g} K_I,y={g.K_I_y:g} K_P,psi={g.K_P_psi:g} K_D,psi={g.K_D_psi:g} T_f,psi={g.T_f_psi:g} s\n")
    w = max(len(n) for n, _, _ in rows)
    print(f"{'eigenvalues (1/s)':<{w}}  {'computed':<50} paper")
    for name, ev, paper in rows:
        print(f"{name:<{w}}  {_fmt_ev(ev):<50} {paper if paper else ''}")
    print(f"\nP control (Sec. 5.1): stability boundary K_P = {r.stability_boundary_kp:.0f} A/m (paper: 18605)")
    print("\ndesign checks (Sec. 5.2.3):")
    for k, c in r.checks.items():
        print(f"  {'ok  ' if c['ok'] else 'FAIL'} {k:<28} {c['value']:.4g} (limit {c['limit']:g})")
    if files:
        print("\nplots: " + ", ".join(str(f) for f in files))
    return 0


def build_parser() -> argparse.ArgumentParser:
    from . import __version__
    # subcommands that live in other modules register themselves on import
    from . import commands  # noqa: F401
    from . import sim_command  # noqa: F401
    from .app import ident_commands  # noqa: F401
    p = argparse.ArgumentParser(prog="rig", description="rig-runtime: control runtime for the 1:5 IRDW roller rig")
    p.add_argument("--version", action="version", version=f"rig-runtime {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (fn, add, help) in _COMMANDS.items():
        sp = sub.add_parser(name, help=help, description=help)
        add(sp)
        sp.set_defaults(_fn=fn)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args._fn(args)
    except RigError as e:
        print(f"rig {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    # run through the imported module so subcommands register in one registry
    from rig_runtime.cli import main as _main
    sys.exit(_main())
