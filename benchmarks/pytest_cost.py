"""A pytest plugin that measures the suite's cost per test: wall time (setup + call +
teardown), this process's CPU time and the CPU time of the child processes it waited for,
the load average at the end; and the in-process lockstep dry runs (count, wall, simulated s).
On the shared 2-core VM the wall time follows the other agents' load; the CPU time much less
(docs/performance.md, "The test suite's time").

    PYTHONPATH=benchmarks CPUTIME_OUT=/tmp/cost.json python -m pytest -p pytest_cost [ARGS]

writes /tmp/cost-main.json (one row per test; -<worker>.json per pytest-xdist worker) and
/tmp/cost-lockstep-main.json.
"""

from __future__ import annotations

import json
import os
import resource
import time

import pytest

_rows: list[dict] = []


def _cpu() -> tuple[float, float]:
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime, c.ru_utime + c.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    w0 = time.monotonic(); s0, c0 = _cpu()
    yield
    s1, c1 = _cpu()
    _rows.append({"id": item.nodeid, "wall": round(time.monotonic() - w0, 2), "cpu": round(s1 - s0, 2),
                  "child_cpu": round(c1 - c0, 2), "load": round(os.getloadavg()[0], 1)})


def pytest_sessionfinish(session):
    out = os.environ.get("CPUTIME_OUT")
    if out and _rows:
        out = out.replace(".json", "-" + os.environ.get("PYTEST_XDIST_WORKER", "main") + ".json")
        with open(out, "w") as f:
            json.dump(_rows, f, indent=0)


_lock = {"n": 0, "wall": 0.0, "sim_s": 0.0}


def pytest_configure(config):
    """Count lockstep dry runs in this process (tests import run_lockstep after plugins load)."""
    try:
        from rig_runtime.app import dryrun
    except Exception:
        return
    orig = dryrun.run_lockstep

    def counted(*a, **kw):
        t0 = time.monotonic()
        try:
            summary, code = orig(*a, **kw)
        finally:
            _lock["n"] += 1
            _lock["wall"] += time.monotonic() - t0
        _lock["sim_s"] += float(summary.get("sim_time_s") or 0.0)
        return summary, code
    dryrun.run_lockstep = counted


def pytest_unconfigure(config):
    out = os.environ.get("CPUTIME_OUT")
    if out:
        out = out.replace(".json", "-lockstep-" + os.environ.get("PYTEST_XDIST_WORKER", "main") + ".json")
        with open(out, "w") as f:
            json.dump(_lock, f)
