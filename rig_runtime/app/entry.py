"""The `rig` console script: stop signals are taken over before anything heavy is
imported, so a SIGINT/SIGTERM/SIGHUP at any instant of a run's start-up ends in a clean
stop with one line (:mod:`rig_runtime.app.signals`); commands that do not stop cleanly
(tune, export, …) get the default handlers back before they start.

The BLAS libraries under numpy start a pool of worker threads at import (one per further
CPU); the runtime's process runs a single thread, and its small matrices gain nothing from
a pool, so they are told to use one thread before numpy is imported (an operator's own
setting of these variables wins)."""

from __future__ import annotations

import os
import sys

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from .signals import StopSignals  # noqa: E402 - after the thread settings


def main(argv: list[str] | None = None) -> int:
    stops = StopSignals().install()
    try:
        from .cli import main as cli_main
    except KeyboardInterrupt:       # not ours: a handler-less thread or a second interpreter
        return 130
    return cli_main(argv, stops=stops)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
