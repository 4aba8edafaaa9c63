"""A local campaign cluster's workers are forked from a server that imported the run's
modules: a worker has them before its first run (no fresh interpreter per worker)."""

import os
import sys

from rig_runtime.app.campaign import dispatch


def _state():
    return os.getpid(), os.getppid(), all(m in sys.modules for m in dispatch.WORKER_PRELOAD)


def test_local_workers_start_with_the_run_modules_imported():
    with dispatch.connect(2, None) as client:
        states = list(client.run(_state).values())
    assert len(states) == 2
    assert all(loaded for _, _, loaded in states), states
    assert len({pid for pid, _, _ in states}) == 2
    assert all(ppid != os.getpid() for _, ppid, _ in states)     # the fork server is their parent, not this process
