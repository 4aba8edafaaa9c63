"""One campaign run on a Dask worker: the sample's config and scenario text written to a
private directory, then exactly what ``rig dry-run`` (lockstep) does with them — load the
config and scenario, ``preflight.check_run`` (the stability gate among its checks), then
:func:`~rig_runtime.app.dryrun.run_lockstep` — and the metrics from its summary and log.

What a lockstep run starts: the simulated devices in this process (ptys, a python-can bus,
Modbus TCP on 127.0.0.1), the recording sidecar as a ``subprocess`` (allowed in Dask's
daemonic worker processes, unlike a ``multiprocessing`` child; :mod:`.spec` refuses a base
config whose F/T poller is the multiprocessing one). A run that the gate refuses is a
``refused`` row; a run that raises is an ``error`` row; neither ends the campaign."""

from __future__ import annotations

import json
import os
import shutil
import socket
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from ...memo import without_disk
from ..quiet import quiet_device_libraries
from .outcome import METRICS, verdict


@dataclass(frozen=True, kw_only=True)
class Job:
    run_id: int
    config_text: str
    hardware_text: str
    scenario_text: str
    seed: int
    duration_s: Optional[float]
    settle_s: float
    criteria: dict
    no_fault: bool
    keep_logs: str                  # none | failing | all
    audit_path: Optional[str]       # DIR/started.log: a line per run started (where the worker sees DIR)


def _audit(job: Job) -> None:
    """One line per run started, appended atomically (O_APPEND, one write); skipped where
    the worker does not see the campaign directory (another machine)."""
    if not job.audit_path or not os.path.isdir(os.path.dirname(job.audit_path)):
        return
    line = f"{job.run_id} {socket.gethostname()} {os.getpid()}\n".encode()
    try:
        fd = os.open(job.audit_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line)
        finally:
            os.close(fd)
    except OSError:
        pass


def run_sample(job: Job) -> dict:
    """The row of one run (without the client's columns: parameters, command, log path).
    ``log_bytes``: the HDF5 log when the spec keeps it (the client writes it into DIR)."""
    with without_disk():        # a sampled config is run once: nothing of it kept for another process
        return _run_sample(job)


def _run_sample(job: Job) -> dict:
    from rig_runtime import config
    from rig_runtime.app import preflight
    from rig_runtime.analysis import UnstableLoopError
    from rig_runtime.scenario import load_scenario
    from ..dryrun import run_lockstep_read

    _audit(job)
    quiet_device_libraries()
    t0 = time.monotonic()
    row: dict = {"run_id": job.run_id, "status": "error", "why": "", "error": "", "final_state": "",
                 "exit_code": None, "faults": "[]", "sim_s": None, "worker": f"{socket.gethostname()}:{os.getpid()}",
                 "log_bytes": None, **{m: None for m in METRICS}}
    tmp = Path(tempfile.mkdtemp(prefix=f"rig-campaign-run-{job.run_id:05d}-"))
    try:
        (tmp / "hardware.yaml").write_text(job.hardware_text)
        (tmp / "run.yaml").write_text(job.config_text)
        (tmp / "scenario.yaml").write_text(job.scenario_text)
        cfg = config.load(tmp / "run.yaml")
        scenario = load_scenario(tmp / "scenario.yaml")
        log = tmp / "run.h5"
        try:
            preflight.check_run(cfg, scenario, job.duration_s, log=log)
        except UnstableLoopError as e:
            row.update(status="refused", why=str(e))
            return row
        summary, code, read = run_lockstep_read(cfg, scenario, log, seed=job.seed, duration_s=job.duration_s)
        from .outcome import metrics
        values = metrics(summary, read if read is not None else log, job.settle_s)     # the log read once
        passed, why = verdict(values, summary["final_state"], code, job.criteria, job.no_fault)
        row.update(values)
        row.update(status="pass" if passed else "fail", why=why, final_state=summary["final_state"], exit_code=code,
                   faults=json.dumps([{k: f.get(k) for k in ("t", "device", "check", "message")}
                                      for f in summary["faults"]], default=str),
                   sim_s=summary.get("sim_time_s"))
        if job.keep_logs == "all" or (job.keep_logs == "failing" and not passed):
            row["log_bytes"] = log.read_bytes()
        return row
    except Exception as e:  # noqa: BLE001 - a run that raises is a row with its error, not the campaign's end
        row.update(status="error", error=f"{type(e).__name__}: {e}"[:2000])
        return row
    finally:
        row["wall_s"] = time.monotonic() - t0
        shutil.rmtree(tmp, ignore_errors=True)
