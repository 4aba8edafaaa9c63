"""Dask distributed: a ``LocalCluster`` of N worker processes (one thread each) on
127.0.0.1, or a running scheduler by address; runs handed out a window at a time.

The window is the cluster's thread count: every run handed to Dask starts at once, so at a
stop request (SIGINT/SIGTERM) nothing is queued — the runs under way finish and are
written, nothing new starts, and ``--resume`` does the rest with no run done twice. A
worker that dies mid-run: Dask gives the run to another worker (after several deaths it
is an ``error`` row, KilledWorker). A lost scheduler ends the campaign (:class:`LostCluster`,
resume later)."""

from __future__ import annotations

import logging
import os
import uuid
from collections import deque
from contextlib import contextmanager
from typing import Callable, Iterable, Iterator, Optional

from distributed.diagnostics.plugin import WorkerPlugin

from rig_runtime.errors import ConfigError

from .task import Job, run_sample

POLL_S = 0.25       # how often the loop looks at a stop request while runs are under way
WORKER_WAIT_S = 60  # a scheduler without workers: how long to wait for the first one


class LostCluster(Exception):
    """The scheduler (or the whole cluster) went away; the campaign can be resumed."""


@contextmanager
def connect(workers: Optional[int], scheduler: Optional[str]) -> Iterator[object]:
    """A Dask client: on a running scheduler (``tcp://HOST:PORT``) or on a LocalCluster
    with ``workers`` processes (default: the machine's cores)."""
    from distributed import Client, LocalCluster
    if scheduler:
        # the client's own log lines on a lost or unreachable scheduler (reconnect attempts,
        # tracebacks from its close) would bury the campaign's one line that says so
        for name in ("distributed", "distributed.client"):     # dask's logging config sets both
            logging.getLogger(name).setLevel(logging.CRITICAL)
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as e:
            raise ConfigError(None, "--scheduler", f"a reachable Dask scheduler ({type(e).__name__}: {e})",
                              scheduler) from None
        try:
            try:
                client.wait_for_workers(1, timeout=WORKER_WAIT_S)
            except TimeoutError:
                raise ConfigError(None, "--scheduler", f"a scheduler with workers (none joined within "
                                  f"{WORKER_WAIT_S} s)", scheduler) from None
            yield client
        finally:
            client.close()
        return
    import dask
    n = workers or os.cpu_count() or 1
    with dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"}):
        _preload_forkserver()
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=None, silence_logs=logging.ERROR)
        try:
            client = Client(cluster)
            try:
                _register(client, IgnoreInterrupt())
                yield client
            finally:
                client.close()
        finally:
            cluster.close()


# What a local worker process needs for a run, imported once in the fork server its worker
# processes are forked from (not again in each worker, nor in the worker's first run).
WORKER_PRELOAD = ("distributed", "numpy", "scipy.linalg", "h5py", "can", "canopen", "yaml",
                  "rig_runtime.app.campaign.task", "rig_runtime.app.preflight", "rig_runtime.app.dryrun",
                  "rig_runtime.app.observer_design", "sim_backend.rig")


def _preload_forkserver() -> None:
    """The local cluster's worker processes are forked from a fork server (Dask's
    ``forkserver`` method) that imported :data:`WORKER_PRELOAD` once: a worker starts
    without a fresh interpreter importing Dask and the runtime (about a second of CPU per
    worker here). The server is a clean process of its own (no threads of this one) and
    inherits this process's environment (``OPENBLAS_NUM_THREADS`` … set by the CLI's entry).
    A server already running (an earlier campaign in this process) keeps its modules."""
    from distributed.utils import get_mp_context
    get_mp_context().set_forkserver_preload(list(WORKER_PRELOAD))


class IgnoreInterrupt(WorkerPlugin):
    """A worker plugin for the local cluster's worker processes: they ignore SIGINT. A
    Ctrl-C on the terminal goes to the whole process group; the campaign process turns it
    into a clean stop (the runs under way finish), which needs its workers alive. They are
    still ended by the cluster's close (SIGTERM, then SIGKILL)."""

    name = "rig-campaign-ignore-sigint"
    idempotent = True

    def setup(self, worker) -> None:
        import signal
        import threading
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def _register(client, plugin) -> None:
    reg = getattr(client, "register_plugin", None) or client.register_worker_plugin
    reg(plugin)


def threads(client) -> int:
    return sum(client.nthreads().values())


def run_all(client, jobs: Iterable[Job], *, on_dispatch: Callable[[int], None],
            on_row: Callable[[Job, dict], None], stop_requested: Callable[[], bool],
            task: Callable[[Job], dict] = run_sample) -> bool:
    """Run ``task(job)`` for each of ``jobs`` (anything with a ``run_id``; a campaign's run
    by default, ``rig synthesize`` gives its own task); ``on_row`` gets each finished run's
    row as it arrives. Returns True if every job ran, False if a stop request ended it early
    (the runs under way were still finished and handed to ``on_row``)."""
    from distributed import wait
    from distributed.scheduler import KilledWorker
    tag = uuid.uuid4().hex[:8]
    queue = deque(jobs)
    flying: dict = {}
    while queue or flying:
        with _on_cluster():
            if not stop_requested():
                cap = max(1, threads(client)) if queue else 0
                while queue and len(flying) < cap:
                    job = queue.popleft()
                    on_dispatch(job.run_id)
                    flying[client.submit(task, job, key=f"rig-run-{tag}-{job.run_id}", pure=False)] = job
            elif not flying or threads(client) == 0:
                break                       # stopped; with no worker left the runs under way are the resume's
            try:
                done, _ = wait(list(flying), timeout=POLL_S, return_when="FIRST_COMPLETED")
            except TimeoutError:
                continue
        for fut in done:
            job = flying.pop(fut)
            try:
                with _on_cluster():
                    row = fut.result()
            except KilledWorker as e:
                row = {"run_id": job.run_id, "status": "error", "error": f"KilledWorker: {e}"[:2000]}
            except LostCluster:
                raise
            except Exception as e:  # noqa: BLE001 - what the task did not catch is still a row, not the end
                row = {"run_id": job.run_id, "status": "error", "error": f"{type(e).__name__}: {e}"[:2000]}
            fut.release()
            on_row(job, row)
    return not queue


@contextmanager
def _on_cluster() -> Iterator[None]:
    """Around calls to the Dask client: a lost scheduler shows as cancelled futures (the
    client cancels what was under way when its connection goes) or a closed comm; either
    is :class:`LostCluster`, named in one line. A wait's timeout is not a loss."""
    from concurrent.futures import CancelledError
    try:
        yield
    except TimeoutError:
        raise
    except CancelledError as e:
        groups = getattr(e, "error_groups", None) or [e]      # several futures cancelled, or one
        reasons = sorted({str(g.reason) for g in groups if getattr(g, "reason", None)})
        raise LostCluster("the runs under way were cancelled: " + (", ".join(reasons) or "by the scheduler")) \
            from None
    except OSError as e:
        raise LostCluster(f"{type(e).__name__}: " + " ".join(str(e).split())[:300]) from None
