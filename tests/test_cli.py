"""The `rig` command as a user runs it: summaries, exports, and one-line errors that name
the cause before anything is armed."""

import csv
import json
import subprocess
import sys


RIG = [sys.executable, "-m", "rig_runtime"]


def rig(*args, cwd=None, timeout=120):
    return subprocess.run(RIG + list(args), capture_output=True, text=True, cwd=cwd, timeout=timeout)


def test_dry_run_json_summary_and_export(tmp_path):
    log = tmp_path / "run.h5"
    r = rig("dry-run", "--duration", "3", "--log", str(log), "--json", "--report", str(tmp_path / "rep"))
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    for k in ("final_state", "faults", "cycles", "max_abs_current_A", "timing", "log", "sim_time_s", "wall_time_s", "steps"):
        assert k in d
    for k in ("release_lateness_us", "cycle_work_us"):
        assert set(d["timing"][k]) >= {"p50", "p99", "p999", "max"}
    assert "deadline_misses" in d["timing"]
    assert d["final_state"] == "IDLE" and d["log"] == str(log)
    assert set(d["steps"][0]) == {"carrier", "t0", "from_mm", "to_mm", "rise_time_s", "overshoot_pct",
                                  "settling_time_s", "steady_state_error_mm"}
    assert d["steps"][0]["carrier"] == "rear"
    assert (tmp_path / "rep" / "response.png").stat().st_size > 10000
    assert "Steps" in (tmp_path / "rep" / "summary.md").read_text()
    out = tmp_path / "run.csv"
    e = rig("export", str(log), "--csv", str(out))
    assert e.returncode == 0, e.stderr
    rows = list(csv.reader(out.open()))
    assert rows[0][:3] == ["t [s]", "t_run [s]", "lateness [s]"] and len(rows) == d["cycles"] + 1


def test_run_with_unreachable_device_stops_before_arming(tmp_path):
    r = rig("run", "--duration", "1", "--log", str(tmp_path / "x.h5"))
    assert r.returncode == 2
    lines = [l for l in r.stderr.splitlines() if l.startswith("rig run: error")]
    assert len(lines) == 1 and "laser b_f" in lines[0] and "/dev/ttyUSB0" in lines[0]
    assert not (tmp_path / "x.h5").exists()


def test_malformed_config_is_one_line(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("include: [" + str((tmp_path / "missing.yaml")) + "]\n")
    r = rig("run", "--config", str(p))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "missing.yaml" in r.stderr
    r = rig("dry-run", "--scenario", "no-such-scenario")
    assert r.returncode == 2 and "known scenarios" in r.stderr and "single-step" in r.stderr


def test_fault_scenario_exit_code(tmp_path):
    # a yaw laser's dropout (a lateral laser's is DEGRADED with sim.yaml's degraded mode)
    r = rig("dry-run", "--scenario", "fault-during-step", "--log", str(tmp_path / "f.h5"), "--json")
    assert r.returncode == 3
    d = json.loads(r.stdout)
    assert d["final_state"] == "FAULT" and d["faults"][0]["device"] == "s_rl"
