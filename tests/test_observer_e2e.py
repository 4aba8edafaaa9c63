"""The observer in lockstep dry runs against the simulated truth: the estimate's accuracy,
the drift a rule could not see found and named in time, and no false alarm without a fault
(a few seeds here; benchmarks/observer_false_alarms.py and docs/observer.md have the longer
measurement), also under the robustness scenario's force pulses and side wind, which the
filter takes as a known input from the F/T sensors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rig_runtime import config
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.scenario import SCENARIO_DIR, load_scenario

from .e2e import read_with_truth


@pytest.fixture(scope="module")
def ocfg():
    return config.load(config.resolve_config_path("sim-observer.yaml"))


def _log(path):
    data, truth, attrs, _ = read_with_truth(path)
    return data, truth, attrs["simulation"]


def test_estimate_follows_the_truth_and_no_false_alarm(tmp_path, ocfg):
    """single-step with the rule on: ends IDLE; ŷ within the acceptance bounds of the truth
    after 2 s (0.1 mm RMS, 0.3 mm at every sample: it does far better, docs/observer.md)."""
    sc = load_scenario("single-step")
    summary, code = run_lockstep(ocfg, sc, tmp_path / "run.h5", duration_s=8.0)
    assert summary["final_state"] == "IDLE" and not summary["faults"], summary["faults"]
    assert "degraded" not in summary
    data, truth, marked = _log(tmp_path / "run.h5")
    assert "SIMULATION" in str(marked)
    idx = np.clip(np.searchsorted(truth["t"], data["t"] - 1e-9), 0, len(truth["t"]) - 1)
    assert np.allclose(truth["t"][idx], data["t"])        # one truth row per cycle, same time
    sel = (data["state"] == 2.0) & (data["t_run"] >= 2.0)
    err = data["rear_obs_y_hat"][sel] - truth["y_r"][idx][sel]
    assert sel.sum() > 1000
    assert np.sqrt(np.mean(err ** 2)) < 0.1e-3 and np.max(np.abs(err)) < 0.3e-3
    assert np.all(data["rear_obs_lat_used"][sel] == 1.0)
    for m in ("lat", "psi", "dw"):
        assert np.nanmax(data[f"rear_obs_T_{m}"]) < ocfg.limits.innovation_chi2


@pytest.mark.parametrize("seed", [1, 2])
def test_no_false_alarm_on_a_fault_free_scenario(tmp_path, ocfg, seed):
    sc = load_scenario("sine-hysteresis" if seed == 1 else "step-sequence")
    summary, code = run_lockstep(ocfg, sc, tmp_path / "run.h5", seed=seed, duration_s=12.0)
    assert summary["final_state"] == "IDLE" and not summary["faults"], summary["faults"]
    assert "degraded" not in summary        # with observe, a lateral finding would DEGRADE, not trip


def test_drift_is_found_and_named_before_the_bias_reaches_0_3_mm(tmp_path, ocfg):
    """With degraded.on_lateral_loss: stop the finding is the fault (tests/test_observer_degraded_e2e.py
    has observe: the lasers are isolated and the run continues DEGRADED)."""
    sc = load_scenario("fault-drift")
    f = sc.faults[0]
    cfg = dataclasses.replace(ocfg, degraded=config.Degraded())
    summary, code = run_lockstep(cfg, sc, tmp_path / "run.h5", duration_s=14.0)
    assert summary["final_state"] == "FAULT" and code == 3
    fault = summary["faults"][0]
    assert fault["check"] == "innovation" and fault["device"].split("/")[0] == "b_r", fault
    bias_mm = f.rate_mm_s * (fault["t"] - summary["run_started_t"] - f.t)
    assert 0.0 < bias_mm < 0.3, bias_mm


def test_the_same_drift_passes_every_other_rule(tmp_path, ocfg):
    """Without the innovation rule, the drift is invisible: the run ends IDLE."""
    cfg = dataclasses.replace(ocfg, limits=dataclasses.replace(ocfg.limits, innovation_chi2=None))
    summary, code = run_lockstep(cfg, load_scenario("fault-drift"), tmp_path / "run.h5", duration_s=14.0)
    assert summary["final_state"] == "IDLE" and not summary["faults"]


def test_force_pulse_and_side_wind_raise_no_alarm(tmp_path, ocfg):
    """robustness with the rule on, its largest pulse (500 N) and the side wind (100 N) moved
    to 3 s and 4.5 s to keep the run short: the F/T sensors' lateral force is a known input
    of the filter, so y moving without ψ is no disagreement (sim-observer.yaml refreshes the F/T
    sensors at 100 Hz: at 10 Hz the lagging force leaves T ≈ 300 at this pulse,
    docs/observer.md)."""
    sc = load_scenario("robustness")
    pulse = next(d for d in sc.disturbances if d.kind == "pulse" and d.F_y == 500)
    wind = next(d for d in sc.disturbances if d.kind == "constant")
    sc = dataclasses.replace(sc, disturbances=(dataclasses.replace(pulse, t=3.0),
                                               dataclasses.replace(wind, t=4.5)))
    summary, code = run_lockstep(ocfg, sc, tmp_path / "run.h5", duration_s=7.0)
    assert summary["final_state"] == "IDLE" and not summary["faults"], summary["faults"]
    assert "degraded" not in summary
    data, truth, _ = _log(tmp_path / "run.h5")
    force = data["ft_rl_fy"] + data["ft_rr_fy"]
    assert np.nanmax(force) > 400 and np.any(np.abs(force - 100) < 20)     # both were applied
    assert np.nanmax(data["rear_obs_T_lat"]) < ocfg.limits.innovation_chi2 / 3
    idx = np.clip(np.searchsorted(truth["t"], data["t"] - 1e-9), 0, len(truth["t"]) - 1)
    y_moved = np.ptp(truth["y_r"][idx][data["t_run"] >= 2.0])
    assert y_moved > 0.2e-3, y_moved                     # the pulse moved y by a fair fraction of a mm


def test_without_the_force_input_the_pulse_looks_like_a_laser_fault(tmp_path, ocfg, monkeypatch):
    """The same pulse with the F/T sensors unknown to the filter (no ft_sensors in its
    design): the rule names the lateral lasers — what the force input removes."""
    from rig_runtime.app import observer_design as od
    from rig_runtime.app import runner
    sc = load_scenario("robustness")
    pulse = next(d for d in sc.disturbances if d.kind == "pulse" and d.F_y == 500)
    sc = dataclasses.replace(sc, disturbances=(dataclasses.replace(pulse, t=3.0),))
    orig = od.designs
    monkeypatch.setattr(runner, "observer_designs",
                        lambda cfg: {c: dataclasses.replace(d, ft_sensors=()) for c, d in orig(cfg).items()})
    cfg = dataclasses.replace(ocfg, degraded=config.Degraded())     # the finding as a fault (observe: DEGRADED)
    summary, code = run_lockstep(cfg, sc, tmp_path / "run.h5", duration_s=5.0)
    assert summary["final_state"] == "FAULT"
    assert summary["faults"][0]["check"] == "innovation" and summary["faults"][0]["device"].startswith("b_r")


_FAULT_SCENARIOS = sorted(p.stem for p in SCENARIO_DIR.glob("fault-*.yaml") if p.stem != "fault-drift")


@pytest.mark.parametrize("name", _FAULT_SCENARIOS)
def test_with_the_rule_on_every_fault_scenario_keeps_its_fault(tmp_path, ocfg, name):
    """The channel rules name their faults first: the innovation rule waits while a channel
    rule gathers evidence on one of the carrier's sensors (fault-stuck: a frozen yaw laser
    disagrees with the model ~0.7 s into its stuck second, and the test alone named the
    lateral lasers). sim-observer.yaml's degraded mode is switched back to stop: a lateral
    laser's dropout is a fault then (tests/test_degraded_e2e.py has the other case)."""
    sc = load_scenario(name)
    cfg = dataclasses.replace(ocfg, degraded=config.Degraded())     # a lost laser stops (the default)
    summary, code = run_lockstep(cfg, sc, tmp_path / "run.h5")
    assert summary["faults"] and summary["faults"][0]["check"] == sc.expect_fault, summary["faults"][:1]


def test_no_observer_for_a_lifted_carrier(tmp_path, ocfg):
    """ident-free-response lifts the rear carrier off the rollers: no (2b), no (4), so no
    filter for it (it would take the free yaw swing for a sensor fault)."""
    summary, code = run_lockstep(ocfg, load_scenario("ident-free-response"), tmp_path / "run.h5",
                                 duration_s=2.0)
    assert summary["final_state"] == "IDLE" and not summary["faults"]
    data, _, _ = _log(tmp_path / "run.h5")
    assert not any(c.startswith("rear_obs_") for c in data)


def test_the_false_alarm_benchmark_takes_every_fault_free_scenario():
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parent.parent / "benchmarks" / "observer_false_alarms.py"
    spec = importlib.util.spec_from_file_location("observer_false_alarms", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    names = mod.fault_free()
    assert {"robustness", "step-sequence", "single-step", "sine-hysteresis"} <= set(names)
    assert not any(n.startswith("fault-") for n in names)
