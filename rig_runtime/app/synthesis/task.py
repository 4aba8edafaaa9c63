"""One case of one candidate on a Dask worker: the campaign's run of it (the very same
task: config and scenario text, the stability gate, the lockstep run, the campaign metrics)
when the case has a scenario, and the linear criteria of its config."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..campaign.task import Job, run_sample


@dataclass(frozen=True, kw_only=True)
class CaseJob:
    run_id: int
    run: Job                    # the campaign's run (config, scenario, seed, duration)
    simulate: bool              # False: a case judged on the linear criteria only
    linear: tuple[str, ...]     # the linear criteria to compute


def evaluate(job: CaseJob) -> dict:
    """The row of one (candidate, case): the campaign row (metrics, status, …) and the
    linear criteria (None where the analysis cannot compute one)."""
    from rig_runtime import config
    from .linear import linear_criteria
    if job.simulate:
        row = run_sample(job.run)
    else:
        row = {"run_id": job.run_id, "status": "pass", "why": "", "error": "", "faults": "[]"}
    if job.linear:
        try:
            with tempfile.TemporaryDirectory(prefix=f"rig-synthesize-{job.run_id:05d}-") as tmp:
                (Path(tmp) / "hardware.yaml").write_text(job.run.hardware_text)
                (Path(tmp) / "run.yaml").write_text(job.run.config_text)
                row.update(linear_criteria(config.load(Path(tmp) / "run.yaml"), job.linear))
        except Exception as e:  # noqa: BLE001 - an evaluation that raises is a row with its error
            row.update(status="error", error=f"{type(e).__name__}: {e}"[:2000])
    return row
