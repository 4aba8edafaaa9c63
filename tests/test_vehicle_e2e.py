"""The vehicle in lockstep dry runs (issue 18's acceptance for the runtime): both carriers on the
rollers and controlled with configs/vehicle.yaml, forwards, backwards, through standstill, with
the controller off; the speed rules on injected encoder offsets; the paper's set-up unchanged
bit for bit. One run per scenario, shared by its assertions.
The simulator follows a scenario's roller speed profile (``speed:``) itself."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rig_runtime import config
from rig_runtime.app.export import read_log
from rig_runtime.app.metrics import steps_from_log
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.scenario import load_scenario

from tests import e2e, paper_trace

VEHICLE = config.CONFIG_DIR / "vehicle.yaml"


@pytest.fixture(scope="module")
def vcfg():
    return config.load(VEHICLE)


def run_vehicle(cfg, scenario, log: Path):
    """A lockstep dry run of ``scenario`` (the simulator follows its speed profile).
    Returns (summary, code, columns)."""
    sc = load_scenario(scenario) if isinstance(scenario, str) else scenario
    s, code = run_lockstep(cfg, sc, log, seed=0)
    return s, code, read_log(log)["columns"]


def assert_tracks_every_step(s, code, cfg):
    assert code == 0 and s["final_state"] == "IDLE" and not s["faults"], s["faults"]
    assert s["max_abs_current_A"] <= cfg.limits.u_max == 4.0
    steps = s["steps"]
    assert sorted((st["carrier"], st["t0"]) for st in steps) == [("front", 1.0), ("front", 21.0),
                                                                  ("rear", 11.0), ("rear", 21.0)]
    for st in steps:
        size = abs(st["to_mm"] - st["from_mm"])
        assert size == pytest.approx(2.0)
        assert abs(st["steady_state_error_mm"]) < 0.02 * size, st
        assert st["settling_time_s"] is not None, st


# ------------------------------------------------------------------ forwards, via `rig dry-run`
@pytest.fixture(scope="module")
def steps_run(tmp_path_factory):
    log = tmp_path_factory.mktemp("vehicle") / "steps.h5"
    r = subprocess.run([sys.executable, "-m", "rig_runtime", "dry-run", "--config", str(VEHICLE),
                        "--scenario", "vehicle-steps", "--log", str(log), "--json"],
                       capture_output=True, text=True, timeout=300)
    return r, log


def test_vehicle_steps_tracks_every_step_on_each_carrier(steps_run, vcfg):
    r, log = steps_run
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert_tracks_every_step(s, r.returncode, vcfg)


def test_vehicle_steps_logs_speed_schedule_and_references(steps_run, vcfg):
    _, log = steps_run
    c = read_log(log)["columns"]
    run = c["state"] == 2.0
    for col in ("v_meas", "front_v", "rear_v"):
        assert np.all(np.abs(c[col][run] - 1.0) < 1e-3), col          # encoder noise only
    for lane in ("front", "rear"):
        assert np.all(c[f"{lane}_held"][run] == 0.0)
        assert np.all(np.abs(c[f"{lane}_g"][run] - 1.0) < 1e-3)
    t = c["t_run"]
    at = lambda x: int(np.argmin(np.abs(np.where(run, t, np.inf) - x)))
    assert (c["front_y_ref"][at(5)], c["rear_y_ref"][at(5)]) == (2e-3, 0.0)
    assert (c["front_y_ref"][at(15)], c["rear_y_ref"][at(15)]) == (2e-3, 2e-3)
    assert np.array_equal(c["y_ref"], c["front_y_ref"])               # the first lane's, for old tools


# ------------------------------------------------------------------ backwards
def test_vehicle_reverse_tracks_every_step_on_each_carrier(tmp_path, vcfg):
    s, code, c = run_vehicle(vcfg, "vehicle-reverse", tmp_path / "reverse.h5")
    assert_tracks_every_step(s, code, vcfg)
    run = c["state"] == 2.0
    assert np.all(np.abs(c["v_meas"][run] + 1.0) < 1e-3)
    assert np.all(np.abs(c["rear_g"][run] + 1.0) < 1e-3)              # the outer loop's sign flipped


# ------------------------------------------------------------------ through standstill
def test_vehicle_reversal_passes_standstill(tmp_path, vcfg):
    s, code, c = run_vehicle(vcfg, "vehicle-reversal", tmp_path / "reversal.h5")
    assert code == 0 and s["final_state"] == "IDLE" and not s["faults"], s["faults"]
    run = c["state"] == 2.0
    half = vcfg.limits.y_max / 2
    assert np.max(np.abs(c["y_f"][run])) < half and np.max(np.abs(c["y_r"][run])) < half
    sch = vcfg.controller.schedule
    v, held, t = c["v_meas"][run], c["front_held"][run], c["t_run"][run]
    assert v[0] == pytest.approx(1.0, abs=1e-3) and v[-1] == pytest.approx(-1.0, abs=1e-3)
    assert np.array_equal(held == 1.0, np.abs(v) < sch.v_min)        # held exactly inside the band
    assert np.array_equal(c["rear_held"][run], held)
    # the hold: ψ_ref to 0 within hold_ramp_s, the integrator frozen
    i0 = int(np.argmax(held == 1.0))
    n = round(sch.hold_ramp_s / vcfg.controller.h)
    assert np.all(c["front_psi_ref"][run][i0 + n - 1:][held[i0 + n - 1:] == 1.0] == 0.0)
    x_I = c["front_x_I"][run]
    assert np.all(x_I[held == 1.0] == x_I[i0 - 1])
    # bumpless resume: ψ_ref continuous where the hold ends
    i1 = i0 + int(np.argmax(held[i0:] == 0.0))
    assert abs(c["front_psi_ref"][run][i1] - c["front_psi_ref"][run][i1 - 1]) < 1e-4
    (front,) = [st for st in s["steps"] if st["carrier"] == "front"]
    assert abs(front["steady_state_error_mm"]) < 0.04


# ------------------------------------------------------------------ controller off
def test_vehicle_open_loop_ends_in_y_limit_with_zero_current(tmp_path, vcfg):
    r = e2e.run(tmp_path, "vehicle-open-loop", vcfg)
    s = r.summary
    assert s["final_state"] == "FAULT" and r.code == 3
    f = r.fault
    assert (f["device"], f["check"]) == ("geometry", "y_limit")
    k = r.fault_row()
    carrier = f["message"].split()[0]
    assert carrier in ("front", "rear")
    y = {"front": r.col("y_f"), "rear": r.col("y_r")}
    assert abs(y[carrier][k]) > vcfg.limits.y_max
    other = "rear" if carrier == "front" else "front"
    assert np.all(np.abs(y[other][:k]) <= vcfg.limits.y_max)            # it got there first
    assert np.all(np.abs(y[carrier][:k]) <= vcfg.limits.y_max)
    for col in ("front_u_lim", "rear_u_lim", "i_fl", "i_fr", "i_rl", "i_rr"):
        assert np.all(r.col(col)[k:] == 0.0), col
    sync_k = max(sy for sy, _, _ in r.wire)
    assert all(i == 0.0 for sy, _, i in r.wire)                        # zero input: nothing on the wire ever
    assert sync_k > 0


# ------------------------------------------------------------------ the speed rules in lockstep
def _scenario(tmp_path, name, text):
    p = tmp_path / f"{name}.yaml"
    p.write_text(f"name: {name}\n" + text)
    return load_scenario(p)


def test_encoders_disagreeing_about_v_is_a_fault(tmp_path, vcfg):
    sc = _scenario(tmp_path, "speed-disagree", """duration_s: 4
reference: [{t: 0, y_mm: 0}, {t: 0.5, y_mm: 1.0}]
faults: [{kind: offset, t: 2.0, device: fl, amount: 4.0, duration_s: 2.0}]
""")
    r = e2e.run(tmp_path, sc, vcfg)
    assert r.summary["final_state"] == "FAULT" and r.code == 3
    f = r.fault
    assert (f["device"], f["check"]) == ("encoders", "speed_disagree")
    assert "front" in f["message"] and "rear" in f["message"]
    assert 2.0 < f["t"] - r.summary["run_started_t"] < 2.2                # the 2 Hz filter's delay
    k = r.fault_row()
    for col in ("front_u_lim", "rear_u_lim", "i_fl", "i_fr", "i_rl", "i_rr"):
        assert np.all(r.col(col)[k:] == 0.0), col
    assert np.any(r.col("front_u_lim")[:k] != 0.0)


def test_speed_beyond_the_hardware_v_max_is_a_fault(tmp_path, cfg):
    # the paper's set-up: the rear carrier alone measures v; both its encoders off by +20 rad/s
    sc = _scenario(tmp_path, "speed-range", """duration_s: 4
reference: [{t: 0, y_mm: 0}, {t: 0.5, y_mm: 1.0}]
faults:
  - {kind: offset, t: 2.0, device: rl, amount: 20.0, duration_s: 2.0}
  - {kind: offset, t: 2.0, device: rr, amount: 20.0, duration_s: 2.0}
""")
    r = e2e.run(tmp_path, sc, cfg)
    e2e.assert_safe_stop(r, "encoders", "speed_range")
    assert r.fault["limit"] == cfg.hardware.ceilings.v_max
    assert r.fault["value"] > cfg.hardware.ceilings.v_max


# ------------------------------------------------------------------ the paper's set-up unchanged
# single-step with configs/sim.yaml, seed 0, as 318336a (before the vehicle) ran it: its step
# metrics, and its trace stored every 10th cycle (tests/paper_trace.py, tests/data/paper_trace.json)
PAPER_STEP = {"t0": 1.0, "from_mm": 0.0, "to_mm": 2.0, "rise_time_s": 1.26, "overshoot_pct": 6.925575067055778,
              "settling_time_s": 10.125000000000002, "steady_state_error_mm": 0.005281030230267903}


def test_the_paper_set_up_is_bit_identical(tmp_path, cfg):
    assert cfg.controller.schedule is None
    s, code = run_lockstep(cfg, load_scenario("single-step"), tmp_path / "paper.h5", seed=0)
    assert code == 0 and s["cycles"] == paper_trace.CYCLES
    assert s["steps"] == [{"carrier": "rear", **PAPER_STEP}]
    c = read_log(tmp_path / "paper.h5")["columns"]
    changed = paper_trace.differences(c)
    assert not changed, "the paper's set-up changed:\n" + "\n".join(changed)
    assert np.all(c["rear_g"] == 1.0) and np.all(c["rear_held"] == 0.0)


def test_a_changed_paper_trace_is_named_with_where_and_by_how_much():
    stored = paper_trace.load()
    idx = paper_trace.rows(paper_trace.CYCLES)
    c = {}
    for k in paper_trace.COLUMNS:
        c[k] = np.zeros(paper_trace.CYCLES)
        c[k][idx] = stored[k]
    assert paper_trace.differences(c) == []
    c["y_r"][idx[50]] += 1e-9
    (line,) = paper_trace.differences(c)
    assert line.startswith(f"y_r: first at cycle {idx[50]} ") and "largest |difference| 1e-09" in line
    assert paper_trace.differences({k: v[:-1] for k, v in c.items()}) == [f"{paper_trace.CYCLES - 1} cycles, "
                                                                          f"stored {paper_trace.CYCLES}"]
