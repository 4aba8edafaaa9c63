"""The `rig` console script: stop signals are taken over before anything heavy is
imported, so a SIGINT/SIGTERM/SIGHUP at any instant of a run's start-up ends in a clean
stop with one line (:mod:`rig_runtime.app.signals`); commands that do not stop cleanly
(tune, export, …) get the default handlers back before they start."""

from __future__ import annotations

import sys

from .signals import StopSignals


def main(argv: list[str] | None = None) -> int:
    stops = StopSignals().install()
    try:
        from .cli import main as cli_main
    except KeyboardInterrupt:       # not ours: a handler-less thread or a second interpreter
        return 130
    return cli_main(argv, stops=stops)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
