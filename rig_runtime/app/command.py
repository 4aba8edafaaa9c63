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
