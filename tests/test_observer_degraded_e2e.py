"""Degraded mode, the parts issue 19 left open (lockstep dry runs, docs/observer.md): a laser
the innovation test isolates DEGRADES the carrier (not a fault) with ``observe``; the
estimate's outage covariance beyond ``degraded.sigma_y_max`` ends the degraded run in the
normal clean stop; DEGRADED in the summary, ``rig log info`` and ``rig log plot`` (ŷ against
y and the simulated truth, the interval shaded); the step metrics on the y the lane
controlled on; and the shipped ``sim.yaml`` observes (its fault scenarios on a lateral laser
DEGRADE and end IDLE)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from rig_runtime import config
from rig_runtime.app import figures, runlog
from rig_runtime.app import observer_design as od
from rig_runtime.app.cli import main
from rig_runtime.app.commands import _print_summary
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.app.metrics import step_info
from rig_runtime.scenario import Reference, load_scenario

from .e2e import read_with_rear_truth


@pytest.fixture(scope="module")
def ocfg():
    return config.load(config.resolve_config_path("sim-observer.yaml"))


def test_a_drifting_laser_found_by_the_innovation_test_degrades_the_carrier(tmp_path, ocfg):
    """fault-drift (b_r creeps at 0.1 mm/s from 10 s) with observe: the innovation test's
    finding isolates the lateral lasers (named b_r/b_f: the test cannot tell them apart)
    before the bias reaches 0.3 mm; the run goes on DEGRADED on ŷ, which stays on the truth
    while the laser walks away, and ends IDLE (with stop: the innovation fault,
    tests/test_observer_e2e.py)."""
    sc = load_scenario("fault-drift")
    f = sc.faults[0]
    summary, code = run_lockstep(ocfg, sc, tmp_path / "run.h5", duration_s=13.0)
    assert summary["final_state"] == "IDLE" and not summary["faults"] and code == 0, summary["faults"]
    (iv,) = summary["degraded"]
    assert (iv["carrier"], iv["laser"], iv["check"]) == ("rear", "b_r/b_f", "innovation")
    bias_mm = f.rate_mm_s * (iv["t_start"] - summary["run_started_t"] - f.t)
    assert 0.0 < bias_mm < 0.3, bias_mm
    assert iv["end"] == "IDLE"                      # not readmitted: a lying laser does not come back
    data, y_true, messages = read_with_rear_truth(tmp_path / "run.h5")
    assert any(m.startswith("DEGRADED: b_r/b_f innovation") and "not readmitted" in m for m in messages)
    t_run = data["t_run"]
    after = (data["state"] == 2.0) & (t_run > iv["t_start"] - summary["run_started_t"] + 0.01)
    assert np.all(data["rear_obs_degraded"][after] == 1.0) and np.all(data["rear_obs_lat_used"][after] == 0.0)
    bias_end = f.rate_mm_s * (t_run[after][-1] - f.t) * 1e-3
    assert np.max(np.abs(data["y_r"][after] - y_true[after])) > 0.5 * bias_end      # the laser walked on …
    assert np.max(np.abs(data["rear_obs_y_hat"][after] - y_true[after])) < 0.1e-3   # … ŷ did not


def test_the_estimates_covariance_bound_ends_degraded_mode_in_a_clean_stop(tmp_path, ocfg):
    """degraded-dropout with degraded.sigma_y_max between the estimate's σ at the start of the
    outage and where it levels off: the supervisor asks for the clean stop in the cycle after
    the observer reports σ(k) beyond the bound — k from the design's table — and the run ramps
    down to IDLE (no fault), the interval closed with the reason."""
    d = od.design(ocfg, "rear")
    tab = np.array(d.sigma_y_outage)
    assert np.all(np.diff(tab) >= -1e-15) and tab[-1] > 5 * tab[0]        # it grows, then levels off
    k = 100
    bound = 0.5 * (tab[k] + tab[k + 1])                                     # first beyond it: k + 1
    cfg = dataclasses.replace(ocfg, degraded=dataclasses.replace(ocfg.degraded, sigma_y_max=float(bound)))
    summary, code = run_lockstep(cfg, load_scenario("degraded-dropout"), tmp_path / "run.h5", duration_s=10.0)
    assert summary["final_state"] == "IDLE" and not summary["faults"] and code == 0, summary["faults"]
    (iv,) = summary["degraded"]
    assert iv["end"].startswith("IDLE (sigma_y")
    run = runlog.load(tmp_path / "run.h5")
    h = run.h
    (stop,) = [e for e in run.events if e.kind == "degraded" and e.message.startswith("DEGRADED ends")]
    assert "beyond degraded.sigma_y_max" in stop.message and "clean stop" in stop.message
    t_deg = iv["t_start"] - run.t_start
    assert stop.t_run == pytest.approx(t_deg + (k + 1) * h, abs=0.5 * h)
    changes = run.state_changes()
    assert [(a, b) for _, a, b in changes][-2:] == [("RUNNING", "STOPPING"), ("STOPPING", "IDLE")]
    assert changes[-2][0] == pytest.approx(stop.t_run + h, abs=0.5 * h)
    assert changes[-1][0] < 9.0                       # well before the 10 s duration: the bound stopped it
    c = run.columns
    k_stop = int(np.argmin(np.abs(run.t_rel - stop.t_run)))
    assert c["rear_obs_sigma_y"][k_stop - 1] > bound >= c["rear_obs_sigma_y"][k_stop - 2]


@pytest.fixture(scope="module")
def dropout(tmp_path_factory, ocfg):
    """degraded-dropout up to 1.5 s after b_r's readmission (b_r out from 8 s to 18 s)."""
    log = tmp_path_factory.mktemp("dropout") / "dropout.h5"
    summary, code = run_lockstep(ocfg, load_scenario("degraded-dropout"), log, duration_s=20.5)
    assert summary["final_state"] == "IDLE" and code == 0, summary["faults"]
    return log, summary


def test_summary_shows_the_degraded_interval(dropout, capsys):
    log, summary = dropout
    _print_summary(dict(summary), as_json=False)
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if "DEGRADED" in ln)
    assert "rear carrier on the observer's estimate (b_r stale)" in line and "b_r readmitted" in line
    (iv,) = summary["degraded"]
    t0 = summary["run_started_t"]
    assert f"at t={iv['t_start'] - t0:+.3f} s" in line and f"until t={iv['t_end'] - t0:+.3f} s" in line
    assert 8.0 < iv["t_start"] - t0 < 8.1 and 19.0 - 0.05 < iv["t_end"] - t0 < 19.1


def test_log_info_lists_the_degraded_interval(dropout, capsys):
    log, summary = dropout
    (d,) = runlog.info(runlog.load(log))["degraded"]
    (s,) = summary["degraded"]
    t0 = summary["run_started_t"]
    assert d["carrier"] == "rear"
    assert d["t_start"] == pytest.approx(s["t_start"] - t0, abs=1e-9)
    assert d["t_end"] == pytest.approx(s["t_end"] - t0, abs=1e-9)
    assert d["why"].startswith("DEGRADED: b_r stale") and d["end"].startswith("b_r readmitted")
    assert main(["log", "info", str(log)]) == 0
    out = capsys.readouterr().out
    i = out.splitlines().index("DEGRADED (run time; the carrier ran on the observer's estimate):")
    nxt = out.splitlines()[i + 1:i + 3]
    assert nxt[0].startswith(f"  rear {d['t_start']:+.3f} s -> {d['t_end']:+.3f} s") and "b_r stale" in nxt[0]
    assert nxt[1].startswith("    ended: b_r readmitted")
    assert main(["log", "info", str(log), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["degraded"][0]["carrier"] == "rear"


def test_a_log_without_degradation_has_no_interval(dropout, tmp_path):
    summary, _ = run_lockstep(config.load(), load_scenario("single-step"), tmp_path / "run.h5", duration_s=0.5)
    assert runlog.info(runlog.load(tmp_path / "run.h5"))["degraded"] == []


def test_log_plot_draws_the_estimate_the_truth_and_the_degraded_interval(dropout, tmp_path, capsys):
    log, summary = dropout
    run = runlog.load(log)
    truth = runlog.truth(run)
    assert set(truth) >= {"t", "y_r"} and len(truth["y_r"]) == run.rows
    fig = figures.observer(run, truth)
    lines = {ln.get_gid(): ln for a in fig.axes for ln in a.get_lines()}
    for gid in ("y:rear", "y_hat:rear", "y_true:rear", "err:rear", "T_lat:rear"):
        assert gid in lines, gid
    assert np.allclose(lines["y_hat:rear"].get_ydata(), run.columns["rear_obs_y_hat"] * 1e3)
    assert np.allclose(lines["y_true:rear"].get_ydata(), truth["y_r"] * 1e3)
    bands = [b for a in fig.axes for b in a.collections if b.get_gid() == "sigma_y:rear"]   # ±σ_y on the error panel
    assert len(bands) == 1
    top = max(p.vertices[:, 1].max() for p in bands[0].get_paths())
    assert top == pytest.approx(np.nanmax(run.columns["rear_obs_sigma_y"]) * 1e3)
    spans = [p for a in fig.axes for p in a.patches if p.get_gid() == "degraded:rear"]
    assert len(spans) == len(fig.axes)
    (iv,) = runlog.degraded_intervals(run)
    x0 = spans[0].get_x() if hasattr(spans[0], "get_width") else min(spans[0].get_xy()[:, 0])
    x1 = x0 + spans[0].get_width() if hasattr(spans[0], "get_width") else max(spans[0].get_xy()[:, 0])
    assert x0 == pytest.approx(iv["t_start"]) and x1 == pytest.approx(iv["t_end"])
    figures.pyplot().close(fig)
    # the command writes it beside the others
    assert main(["log", "plot", str(log), "--out", str(tmp_path / "plots")]) == 0
    out = capsys.readouterr().out
    assert str(tmp_path / "plots" / "observer.png") in out and (tmp_path / "plots" / "observer.png").stat().st_size > 0


def test_a_log_without_truth_plots_the_estimate_against_y(tmp_path):
    """rig run's logs have no sim_truth group: ŷ against the measured y, no truth line."""
    import h5py
    summary, _ = run_lockstep(config.load(), load_scenario("single-step"), tmp_path / "run.h5", duration_s=0.5)
    with h5py.File(tmp_path / "run.h5", "a") as f:
        del f[runlog.TRUTH_GROUP]
    run = runlog.load(tmp_path / "run.h5")
    assert runlog.truth(run) == {}
    figs = figures.log_figures(run)
    gids = {ln.get_gid() for a in figs["observer"].axes for ln in a.get_lines()}
    assert {"y:rear", "y_hat:rear", "err:rear"} <= gids and "y_true:rear" not in gids
    for f in figs.values():
        figures.pyplot().close(f)


def test_step_metrics_during_an_outage_use_the_estimate(dropout):
    """The steps taken while b_r is out (at 10 s and 14 s) are judged on ŷ, the y the lane
    controlled on — the measured y is b_r's last value then, frozen at the 8 s position."""
    log, summary = dropout
    sc = load_scenario("degraded-dropout")
    run = runlog.load(log)
    c = run.columns
    during = [s for s in summary["steps"] if 8.0 < s["t0"] < 18.0]
    assert [s["t0"] for s in during] == [10.0, 14.0]
    sel = c["t_run"] > 0
    measured = step_info(c["t_run"][sel], c["y_r"][sel], Reference(sc.reference).steps(),
                         t_end=float(c["t_run"][sel][-1]) + run.h, h=run.h)
    for s in during:
        assert abs(s["steady_state_error_mm"]) < 0.1 * abs(s["to_mm"] - s["from_mm"]), s
    # the step at 10 s is judged over 13–14 s, inside the outage: on the stale laser's y it failed
    m = next(x for x in measured if x["t0"] == 10.0)
    assert abs(m["steady_state_error_mm"]) > 1.0, m
    # before the outage ŷ is not used: the first step's rise (0.1 → 0.9 within 1–3 s) is the measured one's
    first = next(s for s in summary["steps"] if s["t0"] == 1.0)
    assert first["rise_time_s"] == next(x for x in measured if x["t0"] == 1.0)["rise_time_s"]


@pytest.mark.parametrize("name, laser, check", [("fault-dropout", "b_f", "stale"),
                                                ("fault-out_of_range", "b_r", "invalid")])
def test_shipped_sim_yaml_degrades_on_a_lost_lateral_laser(tmp_path, cfg, name, laser, check):
    """sim.yaml ships degraded.on_lateral_loss: observe: the lateral-laser fault scenarios
    (FAULT with stop, tests/test_faults_e2e.py) DEGRADE, readmit the laser readmit_s after it
    came back and end IDLE."""
    assert cfg.degraded.on_lateral_loss == "observe"
    sc = load_scenario(name)
    f = sc.faults[0]
    summary, code = run_lockstep(cfg, sc, tmp_path / "run.h5")
    assert summary["final_state"] == "IDLE" and not summary["faults"] and code == 0, summary["faults"]
    (iv,) = summary["degraded"]
    t0 = summary["run_started_t"]
    assert (iv["carrier"], iv["laser"], iv["check"], iv["end"]) == ("rear", laser, check, f"{laser} readmitted")
    assert f.t - 0.05 < iv["t_start"] - t0 < f.t + 0.1     # (the scenario clock starts a few cycles early)
    back = f.t + f.duration_s + cfg.degraded.readmit_s
    assert back - 0.05 < iv["t_end"] - t0 < back + 0.2
