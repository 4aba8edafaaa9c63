"""Degraded mode in lockstep dry runs (docs/observer.md): a lost lateral laser with
``degraded.on_lateral_loss: observe`` keeps the carrier under control on the observer's ŷ,
visibly, under tighter limits, for at most ``max_s``, and readmits the laser once it agrees;
with ``stop`` (the default) the same loss is the channel rule's fault, as before."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rig_runtime import config
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.config import ConfigError
from rig_runtime.scenario import load_scenario

from .e2e import read_with_rear_truth


@pytest.fixture(scope="module")
def ocfg():
    return config.load(config.resolve_config_path("sim-observer.yaml"))


def test_degraded_dropout_ends_idle_on_the_estimate_and_readmits_b_r(tmp_path, ocfg):
    """The acceptance of issue 19 for degraded-dropout: IDLE, not FAULT; |y_true| below
    y_max/2 during the outage; the steps taken during it within 10 % of the step 3.9 s
    after they were taken; the DEGRADED interval in the log and the summary; b_r readmitted."""
    sc = load_scenario("degraded-dropout")
    drop = sc.faults[0]
    summary, code = run_lockstep(ocfg, sc, tmp_path / "run.h5")
    assert summary["final_state"] == "IDLE" and not summary["faults"] and code == 0, summary["faults"]
    (iv,) = summary["degraded"]
    t0 = summary["run_started_t"]
    assert iv["carrier"] == "rear" and iv["laser"] == "b_r" and iv["check"] == "stale"
    # (the simulator's scenario clock starts up to a few cycles before RUNNING is seen)
    assert drop.t - 0.05 < iv["t_start"] - t0 < drop.t + 0.1
    readmit = ocfg.degraded.readmit_s
    back = drop.t + drop.duration_s
    assert back + readmit - 0.05 <= iv["t_end"] - t0 < back + readmit + 0.5
    assert iv["end"] == "b_r readmitted"
    data, y_true, messages = read_with_rear_truth(tmp_path / "run.h5")
    assert any(m.startswith("DEGRADED: b_r stale") for m in messages)
    assert any(m.startswith("b_r readmitted") for m in messages)
    t_run = data["t_run"]
    during = (t_run >= iv["t_start"] - t0) & (t_run < iv["t_end"] - t0)
    assert np.all(data["rear_obs_degraded"][during] == 1.0) and np.all(data["rear_obs_lat_used"][during] == 0.0)
    assert np.all(data["rear_obs_degraded"][t_run > iv["t_end"] - t0 + 0.01] == 0.0)
    y_max = ocfg.degraded.limits.y_max
    assert np.max(np.abs(y_true[during])) < y_max / 2
    assert np.max(np.abs(data["rear_u_lim"][during])) <= ocfg.degraded.limits.u_max
    steps = [(r.t, r.y_mm) for r in sc.reference if drop.t < r.t < drop.t + drop.duration_s]
    assert len(steps) == 2
    prev = {r.t: r.y_mm for r in sc.reference}
    before = [p for p in sorted(prev) if p < steps[0][0]][-1]
    last_ref = prev[before]
    for t_step, y_mm in steps:
        k = np.argmin(np.abs(t_run - (t_step + 3.9)))
        assert during[k]
        err = abs(y_true[k] * 1e3 - y_mm)
        assert err < 0.1 * abs(y_mm - last_ref), (t_step, err)
        last_ref = y_mm


def test_with_stop_the_same_dropout_is_the_stale_fault(tmp_path, ocfg):
    cfg = dataclasses.replace(ocfg, degraded=config.Degraded())
    summary, code = run_lockstep(cfg, load_scenario("degraded-dropout"), tmp_path / "run.h5", duration_s=9.0)
    assert summary["final_state"] == "FAULT" and code == 3
    f = summary["faults"][0]
    assert (f["check"], f["device"]) == ("stale", "b_r") and "degraded" not in summary


def test_max_s_ends_the_degraded_run_in_a_fault(tmp_path, ocfg):
    """DEGRADED for longer than max_s: the fault names the isolated laser."""
    cfg = dataclasses.replace(ocfg, degraded=dataclasses.replace(ocfg.degraded, max_s=1.0))
    sc = load_scenario("degraded-dropout")
    sc = dataclasses.replace(sc, faults=(dataclasses.replace(sc.faults[0], t=2.0),))
    summary, code = run_lockstep(cfg, sc, tmp_path / "run.h5", duration_s=4.0)
    assert summary["final_state"] == "FAULT"
    f = summary["faults"][0]
    assert (f["check"], f["device"]) == ("degraded", "b_r")
    assert 1.0 < f["t"] - summary["degraded"][0]["t_start"] < 1.01
    assert summary["degraded"][0]["end"] == "FAULT"


def test_observe_needs_an_observer_and_degraded_limits_are_never_looser(tmp_path, ocfg):
    """degraded.limits above limits are capped at them (sim.yaml observes: a config that
    tightens its limits need not tighten degraded.limits too)."""
    from rig_runtime.app.observer_design import design
    from rig_runtime.observer import Observer
    from rig_runtime.safety import Supervisor
    with pytest.raises(ConfigError, match="observer"):
        dataclasses.replace(ocfg, observer=None)
    lim = dataclasses.replace(ocfg.limits, u_max=1.0, y_max=0.003)
    cfg = dataclasses.replace(ocfg, limits=lim)          # degraded u_max 2.5 A, y_max 5 mm: looser
    sup = Supervisor(cfg.limits, cfg.controller.h, [], ["rear"], None,
                     observers=[Observer(design(cfg, "rear"))], degraded=cfg.degraded)
    assert (sup.degraded_limits.u_max, sup.degraded_limits.y_max) == (1.0, 0.003)
    sup = Supervisor(ocfg.limits, ocfg.controller.h, [], ["rear"], None,
                     observers=[Observer(design(ocfg, "rear"))], degraded=ocfg.degraded)
    assert (sup.degraded_limits.u_max, sup.degraded_limits.y_max) == (2.5, 0.005)
