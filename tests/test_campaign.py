"""``rig campaign``: real Dask processes (a LocalCluster, or a `dask scheduler` and `dask
worker` processes on 127.0.0.1), real lockstep runs, kept short for the 2-core CI machine:
1.5 s runs (the reference step at 1 s included), as few runs as each check needs, one
finished campaign shared by the tests that only read it. No timed assertion: a wait for a
process or a file is bounded only so that a hang ends the test; the checks are on rows and
counts."""

from __future__ import annotations

import json
import os
import random
import shlex
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from rig_runtime.app.campaign import outcome
from rig_runtime.app.cli import main

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
HANG_S = 180            # a bound for a hang only, never a measurement
SMALL = {
    "name": "small",
    "base": {"config": "sim.yaml", "scenario": "single-step", "duration_s": 1.5},
    "parameters": {"plant.delta0": {"pct": 30}, "controller.pipd.K_P_y": {"uniform": [2.0, 4.0]},
                   "sim.laser_noise_m": {"uniform": [0.5e-6, 2e-6]}},
    "design": {"method": "lhs", "n": 6, "seed": 3},
    "pass": {"no_fault": True, "max_abs_u_A": 1.2},
    "keep_logs": "failing",
}
# what differs between two executions of the same run: where and when it ran, where its files are
VARYING = {"wall_s", "worker", "log", "finished_at", "command"}


def write_spec(path: Path, **changes) -> Path:
    spec = json.loads(json.dumps(SMALL))
    for k, v in changes.items():
        spec[k] = v
    path.write_text(yaml.safe_dump(spec))
    return path


def rig(*args: str) -> list[str]:
    return [sys.executable, "-m", "rig_runtime", *args]


def start(args: list[str], cwd: Path) -> subprocess.Popen:
    """A process in its own session (its process group gets the signals a terminal would send)."""
    return subprocess.Popen(args, cwd=cwd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def finish(p: subprocess.Popen) -> tuple[int, str, str]:
    try:
        out, err = p.communicate(timeout=HANG_S)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        out, err = p.communicate()
        pytest.fail(f"{p.args} hung: {err[-2000:]}")
    return p.returncode, out, err


@pytest.fixture
def procs():
    """Every process a test starts is ended, even when the test fails."""
    started: list[subprocess.Popen] = []
    yield started
    for p in started:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
                p.wait(timeout=15)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                p.wait()


def dask_cluster(cwd: Path, procs: list, n_workers: int) -> str:
    """A `dask scheduler` and ``n_workers`` `dask worker` processes on 127.0.0.1, started
    together (a worker waits for the scheduler file); returns the scheduler's address once
    every worker has joined, so that a campaign sees them all from its first run."""
    from distributed import Client
    sched_file = cwd / "scheduler.json"
    procs.append(start([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                        "--scheduler-file", str(sched_file)], cwd))
    for _ in range(n_workers):
        procs.append(start([str(BIN / "dask"), "worker", "--scheduler-file", str(sched_file), "--nthreads", "1",
                            "--host", "127.0.0.1", "--no-dashboard"], cwd))
    wait_for(lambda: sched_file.exists() and sched_file.stat().st_size > 0, "the scheduler file")
    address = json.loads(sched_file.read_text())["address"]
    assert address.startswith("tcp://127.0.0.1:")
    with Client(address, timeout=f"{HANG_S}s") as c:
        c.wait_for_workers(n_workers, timeout=HANG_S)
    return address


def wait_for(pred, what: str) -> None:
    deadline = time.monotonic() + HANG_S
    while not pred():
        if time.monotonic() > deadline:
            pytest.fail(f"never happened: {what}")
        time.sleep(0.05)


def started_lines(out: Path) -> list[list[str]]:
    f = out / "started.log"
    return [l.split() for l in f.read_text().splitlines()] if f.exists() else []


def table(out: Path) -> list[dict]:
    db = sqlite3.connect(out / "campaign.sqlite")
    try:
        cur = db.execute("SELECT * FROM runs ORDER BY run_id")
        cols = [d[0] for d in cur.description]
        return [dict(zip(cols, r)) for r in cur.fetchall()]
    finally:
        db.close()


def count(out: Path, sql: str) -> int:
    db = sqlite3.connect(out / "campaign.sqlite")
    try:
        return db.execute(sql).fetchone()[0]
    finally:
        db.close()


@pytest.fixture(scope="module")
def local_run(tmp_path_factory):
    """The small campaign on a LocalCluster of 2 worker processes."""
    d = tmp_path_factory.mktemp("local")
    spec = write_spec(d / "small.yaml")
    p = subprocess.run(rig("campaign", "run", str(spec), "--out", str(d / "out"), "--workers", "2"), cwd=d, env=ENV,
                       capture_output=True, text=True, timeout=HANG_S)
    return d, spec, p


def test_local_campaign_two_workers_one_row_per_run(local_run):
    d, _, p = local_run
    assert p.returncode == 0, p.stderr
    rows = table(d / "out")
    assert [r["run_id"] for r in rows] == list(range(6))
    assert count(d / "out", "SELECT COUNT(*) FROM dispatches") == 6
    assert sorted(int(l[0]) for l in started_lines(d / "out")) == list(range(6))
    assert len({r["worker"] for r in rows}) == 2                     # both workers ran something
    assert {r["status"] for r in rows} == {"pass", "fail"}        # these samples give both verdicts
    assert all(r["max_abs_e_y_mm"] is not None and r["final_state"] == "IDLE" for r in rows)
    for r in rows:      # the verdict follows the spec's criterion; a failing run kept its log
        assert (r["status"] == "pass") == (r["max_abs_u_A"] <= 1.2)
        assert bool(r["log"]) == (r["status"] == "fail") and (not r["log"] or Path(r["log"]).is_file())
    assert "6 of 6 rows" in p.stdout


def test_a_row_reproduced_by_its_command_gives_identical_metrics(local_run, tmp_path):
    d, _, _ = local_run
    row = random.Random(os.getpid()).choice(table(d / "out"))
    cmd = shlex.split(row["command"])
    assert cmd[:2] == ["rig", "dry-run"]
    log = tmp_path / "again.h5"
    p = subprocess.run(rig(*cmd[1:], "--log", str(log), "--json"), cwd=tmp_path, env=ENV, capture_output=True,
                       text=True, timeout=HANG_S)
    assert p.returncode == 0, p.stderr
    again = outcome.metrics(json.loads(p.stdout), log, 0.0)
    assert again == {m: row[m] for m in outcome.METRICS}


def test_remote_scheduler_and_two_workers_give_the_same_table(local_run, tmp_path, procs):
    d, spec, _ = local_run
    address = dask_cluster(tmp_path, procs, 2)
    code, out, err = finish(start(rig("campaign", "run", str(spec), "--out", str(tmp_path / "out"),
                                      "--scheduler", address), tmp_path))
    assert code == 0, err
    remote = [{k: v for k, v in r.items() if k not in VARYING} for r in table(tmp_path / "out")]
    local = [{k: v for k, v in r.items() if k not in VARYING} for r in table(d / "out")]
    key = lambda r: r["run_id"]  # noqa: E731
    assert sorted(remote, key=key) == sorted(local, key=key)
    assert len({r["worker"] for r in table(tmp_path / "out")}) == 2


def test_sigint_halfway_then_resume_runs_every_run_exactly_once(tmp_path, procs):
    spec = write_spec(tmp_path / "s.yaml", design={"method": "lhs", "n": 8, "seed": 5})
    out = tmp_path / "out"
    p = start(rig("campaign", "run", str(spec), "--out", str(out), "--workers", "2"), tmp_path)
    procs.append(p)
    wait_for(lambda: len(started_lines(out)) >= 3, "three runs started")
    os.killpg(p.pid, signal.SIGINT)             # as Ctrl-C: the whole process group
    code, _, err = finish(p)
    assert code == 130, err
    assert "stopped by SIGINT" in err and "--resume" in err
    first = count(out, "SELECT COUNT(*) FROM results")
    assert 3 <= first < 8
    # the runs under way were finished: every run started has its row, none is missing or twice
    assert sorted(int(l[0]) for l in started_lines(out)) == sorted(r["run_id"] for r in table(out))
    code, _, err = finish(start(rig("campaign", "run", str(spec), "--out", str(out), "--workers", "2", "--resume"),
                                tmp_path))
    assert code == 0, err
    assert [r["run_id"] for r in table(out)] == list(range(8))
    assert sorted(int(l[0]) for l in started_lines(out)) == list(range(8))    # each run started once
    assert count(out, "SELECT COUNT(*) FROM dispatches") == 8
    assert count(out, "SELECT COUNT(*) FROM results WHERE status = 'error'") == 0


def test_a_killed_worker_still_gives_every_row_once(tmp_path, procs):
    spec = write_spec(tmp_path / "s.yaml", design={"method": "lhs", "n": 4, "seed": 7})
    out = tmp_path / "out"
    p = start(rig("campaign", "run", str(spec), "--out", str(out), "--workers", "2"), tmp_path)
    procs.append(p)
    wait_for(lambda: len(started_lines(out)) >= 2, "two runs started")
    victim_run, _, pid = started_lines(out)[0]
    os.kill(int(pid), signal.SIGKILL)           # a worker process dies mid-run (or just after it)
    code, _, err = finish(p)
    assert code == 0, err
    rows = table(out)
    assert [r["run_id"] for r in rows] == list(range(4))
    assert all(r["status"] in ("pass", "fail") for r in rows), [r["error"] for r in rows]
    starts = [int(l[0]) for l in started_lines(out)]
    assert set(starts) == set(range(4)) and len(starts) <= 5     # at most the killed run started again


def test_a_lost_scheduler_ends_the_campaign_and_resume_completes_it(tmp_path, procs):
    spec = write_spec(tmp_path / "s.yaml", design={"method": "lhs", "n": 4, "seed": 11})
    out = tmp_path / "out"
    address = dask_cluster(tmp_path, procs, 1)
    scheduler = procs[0]
    p = start(rig("campaign", "run", str(spec), "--out", str(out), "--scheduler", address), tmp_path)
    procs.append(p)
    # one worker thread: run 1 is handed out only after run 0's row was written
    wait_for(lambda: len(started_lines(out)) >= 2, "two runs started")
    os.killpg(scheduler.pid, signal.SIGKILL)
    code, _, err = finish(p)
    assert code == 1, err
    assert "Traceback" not in err
    said = [l for l in err.splitlines() if "--resume" in l]
    assert len(said) == 1 and "lost the Dask cluster" in said[0] and said[0] == err.strip().splitlines()[-1]
    before = table(out)                         # the table is intact: whole rows of finished runs only
    assert 1 <= len(before) < 4 and all(r["status"] in ("pass", "fail") for r in before)
    code, _, err = finish(start(rig("campaign", "run", str(spec), "--out", str(out), "--workers", "1", "--resume"),
                                tmp_path))
    assert code == 0, err
    assert [r["run_id"] for r in table(out)] == list(range(4))
    assert count(out, "SELECT COUNT(*) FROM results") == 4
    starts = [int(l[0]) for l in started_lines(out)]
    assert set(starts) == set(range(4))
    assert all(starts.count(r["run_id"]) == 1 for r in before)    # a run with a row was not run again
    assert [{k: v for k, v in r.items() if k not in VARYING} for r in table(out) if r["run_id"] < len(before)] == \
        [{k: v for k, v in r.items() if k not in VARYING} for r in before]


@pytest.mark.parametrize("change, key", [
    ({"parameters": {"plant.no_such": {"pct": 10}}}, "parameters.plant.no_such"),
    ({"parameters": {"limits.u_max": {"uniform": [2.0, 20.0]}}}, "parameters.limits.u_max"),
    ({"parameters": {"plant.v": {"normal": {"mean": 1.0, "sd": -0.1}}}}, "parameters.plant.v.normal.sd"),
    ({"pass": {"no_fault": True, "max_abs_banana": 1.0}}, "pass.max_abs_banana"),
    ({"pass": {"settling_time_s": 5.0}, "base": {"scenario": "robustness"}}, "pass.settling_time_s"),
    ({"design": {"method": "sobol", "n": 6}}, "design.n"),
])
def test_a_bad_spec_is_refused_before_any_run(tmp_path, capsys, change, key):
    spec = write_spec(tmp_path / "bad.yaml", **change)
    out = tmp_path / "out"
    code = main(["campaign", "run", str(spec), "--out", str(out), "--workers", "2"])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert key in err and str(spec.resolve()) in err
    assert not out.exists()                     # nothing drawn, written or run


def test_report_on_reduced_robust_gains(tmp_path):
    """The shipped spec with n = 2 (2 · (8 + 2) = 20 runs instead of 2560) on the robustness
    scenario shortened to its first rail-irregularity pulse, moved from 10 s to 3.5 s (the
    start-up settling is over by 3 s), so that a run simulates 4.1 s instead of 65 s."""
    spec = yaml.safe_load((ROOT / "configs/campaigns/robust-gains.yaml").read_text())
    scenario = yaml.safe_load((ROOT / "configs/scenarios/robustness.yaml").read_text())
    pulse = dict(scenario["disturbances"][0], t=3.5)
    assert pulse["kind"] == "pulse" and pulse["F_y"] > 0
    scenario.update(name="robustness-short", duration_s=4.1, disturbances=[pulse])
    (tmp_path / "robustness-short.yaml").write_text(yaml.safe_dump(scenario))
    spec["base"].update(scenario="robustness-short.yaml", settle_s=3.0)
    spec["design"]["n"] = 2
    spec["pass"]["max_abs_e_y_mm"] = 0.2        # tight enough that some conditions fail
    (tmp_path / "rg.yaml").write_text(yaml.safe_dump(spec))
    out = tmp_path / "rg"
    p = subprocess.run(rig("campaign", "run", str(tmp_path / "rg.yaml"), "--out", str(out), "--workers", "2"),
                       cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=HANG_S)
    assert p.returncode == 0, p.stderr
    assert count(out, "SELECT COUNT(*) FROM results") == 20
    assert count(out, "SELECT COUNT(DISTINCT status) FROM results WHERE status IN ('pass', 'fail')") == 2
    p = subprocess.run(rig("campaign", "report", str(out)), cwd=tmp_path, env=ENV, capture_output=True, text=True,
                       timeout=HANG_S)
    assert p.returncode == 0, p.stderr
    answer = p.stdout.splitlines()[0]
    assert answer.startswith("the gains hold in ") and "% [" in answer and "sampled conditions" in answer
    md = (out / "report" / "report.md").read_text()
    assert f"**Answer:** {answer}." in md
    for png in ("pass-fail.png", "sobol.png"):
        assert (out / "report" / png).stat().st_size > 10_000
    # Sobol' indices with their intervals, for each metric the spec asks for
    for m in ("max_abs_e_y_mm", "rms_e_y_mm", "pass"):
        assert f"`{m}`" in md
    assert md.count(" ± ") >= 2 * 8
    assert "rig dry-run --config" in md
    assert "## Where it fails" in md
