"""``rig synthesize`` on the paper's set-up: real Dask processes, real lockstep runs, kept
small for the 2-core machine (one case, 11.5 s runs: the paper's 2 % settling of 10.1 s after
the step at 1 s fits; a population of 4 for 2 generations: 8 runs). No timed assertion; a
wait is bounded only so that a hang ends the test."""

from __future__ import annotations

import json
import os
import shlex
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from rig_runtime import analysis, config as rig_config
from rig_runtime.app.campaign import outcome
from rig_runtime.app.cli import main

from .test_campaign import ENV, HANG_S, finish, procs, start, started_lines, wait_for  # noqa: F401 - procs: a fixture

ROOT = Path(__file__).resolve().parent.parent
PAPER = {"controller.pipd.K_P_y": 3.0, "controller.pipd.K_I_y": 9.0, "controller.pipd.K_P_psi": 40.0,
         "controller.pipd.K_D_psi": 5.0}
# the paper's gains on the simulated plant, single-step, seed 0 (tests/test_vehicle_e2e.py's PAPER_STEP,
# measured again here from the synthesis' own first candidate, which is the paper's gains)
SMALL = {
    "name": "paper-small",
    "base": {"config": "sim.yaml"},
    "tunables": {"controller.pipd.K_P_y": [2.0, 6.0], "controller.pipd.K_I_y": [5.0, 15.0],
                 "controller.pipd.K_P_psi": [25.0, 40.0], "controller.pipd.K_D_psi": [3.0, 5.0]},
    "cases": [{"name": "step", "scenario": "single-step", "duration_s": 11.5, "seed": 0}],
    "criteria": {"design_checks_failed": {"demand": 0}, "worst_case_input_per_term_A": {"demand": 2.0},
                 "worst_case_input_sum_A": {"demand": 4.0}, "spectral_radius": {"demand": 0.9999},
                 "rise_time_s": {"demand": 1.26}, "overshoot_pct": {"demand": 6.93, "objective": True},
                 "settling_time_s": {"demand": 10.13, "objective": True}},
    "optimizer": {"method": "nsga2", "population": 4, "generations": 2, "seed": 3},
}


def rig(*args: str) -> list[str]:
    return [sys.executable, "-m", "rig_runtime", *args]


def write_spec(path: Path, **changes) -> Path:
    spec = json.loads(json.dumps(SMALL))
    spec.update(changes)
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def rows(out: Path, sql: str) -> list[dict]:
    db = sqlite3.connect(out / "campaign.sqlite")
    try:
        cur = db.execute(sql)
        cols = [d[0] for d in cur.description]
        return [dict(zip(cols, r)) for r in cur.fetchall()]
    finally:
        db.close()


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("synth")
    spec = write_spec(d / "small.yaml")
    p = subprocess.run(rig("synthesize", "run", str(spec), "--out", str(d / "out"), "--workers", "2"), cwd=d, env=ENV,
                       capture_output=True, text=True, timeout=HANG_S * 2)
    return d, spec, p


def test_finds_gains_meeting_the_design_checks_with_steps_at_least_as_good_as_the_papers(small_run, tmp_path):
    d, _, p = small_run
    assert p.returncode == 0, p.stderr
    cands = rows(d / "out", "SELECT * FROM candidates ORDER BY candidate")
    assert len(cands) == 8
    paper = rows(d / "out", "SELECT * FROM case_runs WHERE candidate = 0")[0]
    assert {k: paper[f"p:{k}"] for k in PAPER} == PAPER                 # the first candidate: the paper's gains
    r = subprocess.run(rig("synthesize", "report", str(d / "out"), "--write", str(tmp_path / "ctl.yaml")), cwd=d,
                       env=ENV, capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 0, r.stderr
    assert "meets every demand in every case" in r.stdout
    chosen = int(r.stdout.split("chosen candidate #")[1].split(" ")[0])
    run = rows(d / "out", f"SELECT * FROM case_runs WHERE candidate = {chosen}")[0]
    for m in ("rise_time_s", "overshoot_pct", "settling_time_s"):
        assert run[m] is not None and run[m] <= paper[m] + 1e-9, (m, run[m], paper[m])
    # the written controller section gives a config whose design checks hold (rig tune's verdict)
    frag = yaml.safe_load((tmp_path / "ctl.yaml").read_text())
    gains = frag["controller"]["pipd"]
    assert {f"controller.pipd.{k}": gains[k] for k in ("K_P_y", "K_I_y", "K_P_psi", "K_D_psi")} == \
        {k: run[f"p:{k}"] for k in PAPER}
    cfg_text = (ROOT / "configs/sim.yaml").read_text()
    (tmp_path / "sim.yaml").write_text(cfg_text)
    for inc in ("hardware.yaml", "plant.yaml", "controller.yaml", "geometry.yaml", "irdw-drive.eds"):
        if (ROOT / "configs" / inc).exists():
            (tmp_path / inc).write_text((ROOT / "configs" / inc).read_text())
    ctl = yaml.safe_load((tmp_path / "controller.yaml").read_text())
    ctl["controller"] = frag["controller"]
    (tmp_path / "controller.yaml").write_text(yaml.safe_dump(ctl))
    cfg = rig_config.load(tmp_path / "sim.yaml")
    assert cfg.controller.pipd.K_P_y == gains["K_P_y"]
    assert analysis.tune_failures(cfg, analysis.tune(cfg)) == []
    md = (d / "out" / "report" / "report.md").read_text()
    assert (d / "out" / "report" / "pareto.png").stat().st_size > 10_000
    assert "| `overshoot_pct` (objective) | ≤ 6.93 |" in md and "**The worst case:**" in md


def test_a_row_reproduced_by_its_command_gives_identical_metrics(small_run, tmp_path):
    d, _, _ = small_run
    row = rows(d / "out", "SELECT * FROM case_runs WHERE candidate = 7")[0]
    cmd = shlex.split(row["command"])
    assert cmd[:2] == ["rig", "dry-run"]
    log = tmp_path / "again.h5"
    p = subprocess.run(rig(*cmd[1:], "--log", str(log), "--json"), cwd=tmp_path, env=ENV, capture_output=True,
                       text=True, timeout=HANG_S)
    assert p.returncode == 0, p.stderr
    assert outcome.metrics(json.loads(p.stdout), log, 0.0) == {m: row[m] for m in outcome.METRICS}


def test_sigint_then_resume_evaluates_nothing_twice(small_run, tmp_path, procs):  # noqa: F811
    d, spec, _ = small_run
    out = tmp_path / "out"
    p = start(rig("synthesize", "run", str(spec), "--out", str(out), "--workers", "2"), tmp_path)
    procs.append(p)
    wait_for(lambda: len(started_lines(out)) >= 3, "three runs started")
    os.killpg(p.pid, signal.SIGINT)
    code, _, err = finish(p)
    assert code == 130, err
    assert "stopped by SIGINT" in err and "--resume" in err
    first = len(rows(out, "SELECT run_id FROM results"))
    assert 3 <= first < 8
    code, _, err = finish(start(rig("synthesize", "run", str(spec), "--out", str(out), "--workers", "2", "--resume"),
                                tmp_path))
    assert code == 0, err
    starts = [int(l[0]) for l in started_lines(out)]
    skipped = [r["run_id"] for r in rows(out, "SELECT run_id FROM results WHERE status = 'skipped'")]
    assert sorted(starts + skipped) == list(range(8))       # every run started exactly once, or skipped (cheap first)
    # the same candidates and metrics as the run that was never interrupted
    keep = ("candidate", "x", "worst", "objectives", "violation", "feasible")
    again = [{k: c[k] for k in keep} for c in rows(out, "SELECT * FROM candidates ORDER BY candidate")]
    whole = [{k: c[k] for k in keep} for c in rows(d / "out", "SELECT * FROM candidates ORDER BY candidate")]
    assert again == whole


@pytest.mark.parametrize("change, key", [
    ({"tunables": {"controller.pipd.K_P_y": [6.0, 2.0]}}, "tunables.controller.pipd.K_P_y"),
    ({"tunables": {"plant.delta0": [0.05, 0.07]}}, "tunables.plant.delta0"),
    ({"criteria": {"overshoot_pct": {"demand": 5}}}, "criteria"),                       # no objective
    ({"criteria": {"banana": {"demand": 1, "objective": True}}}, "criteria.banana"),
    ({"criteria": {"held_excursion_pct": {"demand": 10, "objective": True}}}, "criteria.held_excursion_pct"),
    ({"cases": [{"name": "x", "scenario": "no-such-scenario"}]}, "cases[0].scenario"),
    ({"cases": [{"name": "x", "scenario": "single-step", "set": {"limits.u_max": 50.0}}]}, "cases.x"),
    ({"optimizer": {"method": "simplex"}}, "optimizer.method"),
])
def test_a_bad_spec_is_refused_before_anything_runs(tmp_path, capsys, change, key):
    spec = write_spec(tmp_path / "bad.yaml", **change)
    out = tmp_path / "out"
    code = main(["synthesize", "run", str(spec), "--out", str(out), "--workers", "2"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert key in err and str(spec.resolve()) in err
    assert not out.exists()


def test_a_lost_scheduler_ends_the_synthesis_and_resume_completes_it(tmp_path, procs):  # noqa: F811
    from .test_campaign import dask_cluster
    spec = write_spec(tmp_path / "s.yaml", optimizer={"method": "nsga2", "population": 2, "generations": 2, "seed": 5})
    out = tmp_path / "out"
    address = dask_cluster(tmp_path, procs, 1)
    scheduler = procs[0]
    p = start(rig("synthesize", "run", str(spec), "--out", str(out), "--scheduler", address), tmp_path)
    procs.append(p)
    wait_for(lambda: len(started_lines(out)) >= 2, "two runs started")     # one worker thread: run 0 has its row
    os.killpg(scheduler.pid, signal.SIGKILL)
    code, _, err = finish(p)
    assert code == 1, err
    assert "Traceback" not in err
    said = [l for l in err.splitlines() if "--resume" in l]
    assert len(said) == 1 and "lost the Dask cluster" in said[0]
    before = rows(out, "SELECT run_id FROM results")
    assert 1 <= len(before) < 4
    code, _, err = finish(start(rig("synthesize", "run", str(spec), "--out", str(out), "--workers", "1", "--resume"),
                                tmp_path))
    assert code == 0, err
    assert [r["run_id"] for r in rows(out, "SELECT run_id FROM results ORDER BY run_id")] == list(range(4))
    starts = [int(l[0]) for l in started_lines(out)]
    skipped = {r["run_id"] for r in rows(out, "SELECT run_id FROM results WHERE status = 'skipped'")}
    assert set(starts) | skipped == set(range(4)) and not set(starts) & skipped     # skipped: cheap first
    assert all(starts.count(r["run_id"]) == 1 for r in before if r["run_id"] not in skipped)   # not run again


def test_a_candidate_that_breaks_a_linear_constraint_is_not_simulated(tmp_path):
    """Cheap first: K_P_psi 80 (4 A per term > 2 A) is decided by the analysis; its lockstep run
    gets a ``skipped`` row with the linear values and is not dispatched; within the checks it is."""
    from rig_runtime.app.campaign import materialize
    from rig_runtime.app.synthesis import optimize, store as sstore
    from rig_runtime.app.synthesis.spec import load_spec
    spec = load_spec(write_spec(tmp_path / "s.yaml", tunables={**SMALL["tunables"],
                                                               "controller.pipd.K_P_psi": [25.0, 80.0]}))
    out = tmp_path / "out"
    store = sstore.create(spec, out)
    try:
        base = materialize.config_base(spec.config, {})
        texts = {0: sstore.case_scenario(out, 0).read_text()}
        seen = []
        bad = optimize._jobs(spec, out, store, base, texts, 0, 0, {**PAPER, "controller.pipd.K_P_psi": 80.0})
        good = optimize._jobs(spec, out, store, base, texts, 1, 0, dict(PAPER))
        res = optimize.Outcome(finished=False)
        kept = optimize._linear_first(spec, store, bad + good, seen.append, res)
        assert [j.run_id for j in kept] == [good[0].run_id] and res.skipped == 1
        assert seen[0]["status"] == "skipped" and "design_checks_failed = 2 > 0" in seen[0]["why"]
        assert seen[0]["worst_case_input_per_term_A"] == 4.0
        assert store.done_ids() == {bad[0].run_id}
    finally:
        store.close()


@pytest.mark.parametrize("cmd", ["campaign", "synthesize"])
def test_run_scaffolding_is_shared(tmp_path, capsys, cmd):
    """`rig campaign run` and `rig synthesize run` (campaign.command.run_spec): --workers with
    --scheduler, and a non-empty --out without --resume, are one line and exit 2 before anything runs."""
    spec = (ROOT / "configs" / ("campaigns/vehicle-steps.yaml" if cmd == "campaign" else "synthesis/paper-pipd.yaml"))
    code = main([cmd, "run", str(spec), "--out", str(tmp_path / "o"), "--workers", "1", "--scheduler", "tcp://x:1"])
    err = capsys.readouterr().err
    assert code == 2 and "either --workers (local cluster) or --scheduler, not both" in err
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    code = main([cmd, "run", str(spec), "--out", str(tmp_path / "full"), "--workers", "1"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "a new or empty directory" in err
    assert (f"continues a {'campaign' if cmd == 'campaign' else 'synthesis'}") in err
