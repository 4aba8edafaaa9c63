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
    try:
        return cli_main(argv, stops=stops)
    finally:
        _before_exit()


def _before_exit() -> None:
    """The command is done and the process ends next: what it made and the libraries it
    imported are moved out of the cyclic collector's reach (``gc.freeze``), so the
    interpreter's exit does not walk them all once more (~60 ms of CPU of a ``rig dry-run``'s
    ~0.45 s, docs/performance.md). Nothing is skipped: the atexit handlers, the threads'
    joins and every object freed by its reference count run as before; a command closes what
    it opened (logs, buses, sockets) itself."""
    import gc
    gc.freeze()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
