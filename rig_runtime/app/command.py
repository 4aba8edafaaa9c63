"""The table of ``rig`` subcommands and the decorators that fill it (a leaf module: the
command modules import it, :mod:`rig_runtime.app.cli` imports them)."""

from __future__ import annotations

import argparse
from typing import Callable

Command = Callable[[argparse.Namespace], int]
COMMANDS: dict[str, tuple[Command, Callable[[argparse.ArgumentParser], None], str]] = {}


def command(name: str, help: str, stops: bool = False):
    """Register a subcommand: ``fn(args) -> exit code``; its arguments come from :func:`arg`.
    ``stops``: SIGINT/SIGTERM/SIGHUP request a clean stop (``args.stops``, a
    :class:`~rig_runtime.app.signals.StopSignals` installed before the command starts)
    instead of ending the process."""
    def deco(fn):
        fn.handles_stops = stops
        def add(p: argparse.ArgumentParser) -> None:
            for a, kw in getattr(fn, "_args", []):
                p.add_argument(*a, **kw)
        COMMANDS[name] = (fn, add, help)
        return fn
    return deco


def arg(*a, **kw):
    """One ``add_argument`` of a subcommand (decorators apply bottom-up; order is kept)."""
    def deco(fn):
        fn._args = [(a, kw)] + getattr(fn, "_args", [])
        return fn
    return deco


class Actions:
    """A subcommand whose actions take their own arguments (``rig log info|plot|…``,
    ``rig campaign run|report``): ``@actions.action(name, help, actions.arg(...), …)`` fills
    the table, :meth:`install` makes the subcommand's parser take them as sub-parsers and
    :meth:`dispatch` runs the one asked for."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._dest = f"_{name}_action_fn"
        self._table: dict[str, tuple[Command, str, list]] = {}

    def action(self, name: str, help: str, *args: tuple[tuple, dict]):
        def deco(fn):
            self._table[name] = (fn, help, list(args))
            return fn
        return deco

    @staticmethod
    def arg(*a, **kw) -> tuple[tuple, dict]:
        return a, kw

    def _add(self, p: argparse.ArgumentParser) -> None:
        sub = p.add_subparsers(dest=f"{self.name}_action", required=True, metavar="ACTION")
        for name, (fn, help, args) in self._table.items():
            q = sub.add_parser(name, help=help, description=help)
            for a, kw in args:
                q.add_argument(*a, **kw)
            q.set_defaults(**{self._dest: fn})

    def dispatch(self, args: argparse.Namespace) -> int:
        return getattr(args, self._dest)(args)

    def install(self) -> None:
        """The registered subcommand ``name`` parses its actions (call after ``@command``)."""
        fn, _, help = COMMANDS[self.name]
        COMMANDS[self.name] = (fn, self._add, help)
