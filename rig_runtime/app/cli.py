"""The ``rig`` command: ``rig tune``, ``rig dry-run``, ``rig run``, ``rig sim``, ``rig export``.

Errors the operator can act on (a bad config, a missing device) end the program with a
one-line message naming the cause and exit code 2; nothing starts before the config is valid.
"""

from __future__ import annotations

import argparse
import sys

from ..errors import RigError
from .signals import Interrupted, StopSignals
from . import commands, ctl_command, ident_commands, latency, log_commands, sim_command, tune_command  # noqa: F401 - each registers its subcommands
from .campaign import command as _campaign_command  # noqa: F401 - registers `rig campaign`
from .synthesis import command as _synthesis_command  # noqa: F401 - registers `rig synthesize`
from .commission import command as _commission_command  # noqa: F401 - registers `rig commission`
from .command import COMMANDS


class _Parser(argparse.ArgumentParser):
    """A usage error is one line and exit 2, like every other operator mistake."""

    def error(self, message: str):  # noqa: D102 - argparse hook
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    p = _Parser(prog="rig", description="rig-runtime: control runtime for the 1:5 IRDW roller rig")
    p.add_argument("--version", action="version", version=f"rig-runtime {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (fn, add, help) in COMMANDS.items():
        sp = sub.add_parser(name, help=help, description=help)
        add(sp)
        sp.set_defaults(_fn=fn)
    return p


def main(argv: list[str] | None = None, stops: StopSignals | None = None) -> int:
    """``stops``: handlers already installed by the console script (rig_runtime.app.entry)."""
    stops = stops if stops is not None else StopSignals().install()
    try:
        args = build_parser().parse_args(argv)
    except SystemExit:
        stops.restore()
        raise
    args.stops = stops
    if not args._fn.handles_stops:
        stops.restore()             # default signal behaviour for commands without a clean stop
        if stops.requested:
            print(f"rig {args.command}: stopped by {stops.name} before it started", file=sys.stderr)
            return 128 + (stops.signum or 0)
    try:
        if args._fn.handles_stops:
            with args.stops:
                return args._fn(args)
        return args._fn(args)
    except RigError as e:
        print(f"rig {args.command}: error: {e}", file=sys.stderr)
        return 2
    except Interrupted as e:
        print(f"rig {args.command}: {e}", file=sys.stderr)
        return e.code
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
