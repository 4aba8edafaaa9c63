"""``rig log info|plot|compare|export``, the figures they share with ``--report`` and
``rig tune --plot``, and the end-of-run summary — on real logs made here: a lockstep dry run,
a dry run that ends in FAULT, one with both carriers controlled, and (slow) ``rig run``
against ``rig sim``."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest

from rig_runtime import analysis, config
from rig_runtime.app import figures, runlog
from rig_runtime.app.cli import main
from rig_runtime.app.commands import _print_summary
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.app.export import column_header, column_unit, state_name
from rig_runtime.safety import State
from rig_runtime.scenario import load_scenario

from sim_backend.launcher import start_sim_process

from .e2e import realtime_config, realtime_sim_config
from .test_sim_process import _finish, _start_run

STATES = {"IDLE", "ARMED", "RUNNING", "STOPPING", "FAULT"}


def _lockstep(tmp_path_factory, name, scenario, duration, cfg=None):
    log = tmp_path_factory.mktemp(name) / f"{name}.h5"
    summary, code = run_lockstep(cfg or config.load(), load_scenario(scenario), log, duration_s=duration)
    return log, summary, code


@pytest.fixture(scope="module")
def step_log(tmp_path_factory):
    return _lockstep(tmp_path_factory, "step", "single-step", 1.5)


@pytest.fixture(scope="module")
def fault_log(tmp_path_factory):
    return _lockstep(tmp_path_factory, "fault", "fault-during-step", None)


@pytest.fixture(scope="module")
def both_log(tmp_path_factory):
    cfg = dataclasses.replace(config.load(), controlled=("front", "rear"))
    return _lockstep(tmp_path_factory, "both", "single-step", 1.2, cfg)


def rig(capsys, *args) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def _by_gid(fig, prefix: str) -> list:
    return [a for ax in fig.axes for a in ax.get_children() if (a.get_gid() or "").startswith(prefix)]


def _gid(fig, gid: str) -> list:
    return [a for ax in fig.axes for a in ax.get_children() if a.get_gid() == gid]


# --------------------------------------------------------------------------------- info
def test_info_of_a_lockstep_run(step_log):
    log, summary, code = step_log
    d = runlog.info(runlog.load(log))
    assert code == 0 and d["rows"] == summary["recorder"]["rows"] and d["final_state"] == "IDLE"
    assert d["faults"] == [] and d["scenario"] == "single-step" and d["config_source"].endswith("configs/sim.yaml")
    assert [s["to"] for s in d["states"]] == ["ARMED", "RUNNING", "STOPPING", "IDLE"]
    assert d["states"][1]["t_run"] == 0.0 and d["running_s"] == pytest.approx(1.5, abs=1e-9)
    assert d["clock"] == "lockstep" and d["timing_us"] is None
    assert d["steps"] == summary["steps"] and len(d["steps"]) == 1 and d["steps"][0]["to_mm"] == 2.0
    assert d["max_abs_u_A"]["rear"] == pytest.approx(summary["max_abs_current_A"])
    assert d["max_abs_wire_current_A"] == pytest.approx(summary["max_abs_wire_current_A"])


def test_info_of_a_fault_run_in_run_time(fault_log, capsys):
    log, summary, code = fault_log
    assert code == 3
    c, out, _ = rig(capsys, "log", "info", log, "--json")
    d = json.loads(out)
    assert c == 0 and d["final_state"] == "FAULT"
    (f,) = d["faults"]
    assert (f["device"], f["check"]) == ("s_rl", "stale")
    # the scenario silences s_rl at 1.4 s of run time; stale after 20 ms
    assert 1.4 < f["t_run"] <= 1.45
    assert f["t_run"] == pytest.approx(summary["faults"][0]["t"] - summary["run_started_t"])
    c, out, _ = rig(capsys, "log", "info", log)
    assert "t=+1.4" in out and "s_rl stale" in out and "final state: FAULT" in out


# --------------------------------------------------------------------------------- figures
def test_response_figure_markers_limits_labels(fault_log):
    run = runlog.load(fault_log[0])
    fig = figures.response(run)
    try:
        ax = fig.axes
        assert [a.get_ylabel() for a in ax] == ["lateral displacement y (mm)", "yaw angle ψ (mrad)",
                                              "Δω = ω_left − ω_right (rad/s)", "differential current u (A)"]
        assert "RUNNING" in ax[-1].get_xlabel()
        u_max, y_max = run.limits["u_max"], run.limits["y_max"]
        lim = {l.get_gid(): l.get_ydata()[0] for l in _by_gid(fig, "limit:")}
        assert lim["limit:+u_max"] == u_max and lim["limit:-u_max"] == -u_max
        assert lim["limit:+y_max"] == pytest.approx(y_max * 1e3) and lim["limit:-y_max"] == pytest.approx(-y_max * 1e3)
        # |u| stays below u_max / 2: the axes keep the data's scale and a note names the limit
        assert ax[3].get_ylim()[1] < u_max and _gid(fig, "limit-note:u_max")
        assert "4 A" in _gid(fig, "limit-note:u_max")[0].get_text()
        fault = run.faults()[0]
        marks = _gid(fig, "fault:s_rl:stale")
        assert len(marks) == 4 and all(m.get_xdata()[0] == pytest.approx(fault.t_run) for m in marks)
        running = [m for m in _gid(fig, "state:RUNNING") if m in ax[0].get_children()]
        assert len(running) == 1 and running[0].get_xdata()[0] == 0.0
        labels = [t.get_text() for t in _by_gid(fig, "state-label:")]
        assert [n for lab in labels for n in lab.split("→")] == ["ARMED", "RUNNING", "FAULT"]
        y = next(l for l in ax[0].get_lines() if l.get_gid() == "y:rear")
        np.testing.assert_allclose(y.get_ydata(), run.columns["y_r"] * 1e3)
        u = next(l for l in ax[3].get_lines() if l.get_gid() == "u:rear")
        assert np.all(u.get_xdata()[u.get_ydata() != 0] <= fault.t_run + 1e-9)   # no current after the fault
        assert not _gid(fig, "y:front")                                         # front neither controlled nor driven
    finally:
        figures.pyplot().close(fig)


def test_limit_lines_in_view_near_the_limit():
    plt = figures.pyplot()
    fig, (a, b) = plt.subplots(2)
    try:
        a.plot([0, 1, 2], [0.0, 3.5, -1.0])
        figures._limit(a, 4.0, 1.0, "u_max", "A")
        lo, hi = a.get_ylim()
        assert lo <= -4.0 and hi >= 4.0 and not _gid(fig, "limit-note:u_max")
        b.plot([0, 1, 2], [0.0, 0.5, -0.2])
        figures._limit(b, 0.008, 1e3, "y_max", "mm")
        assert b.get_ylim()[1] < 8.0 and _gid(fig, "limit-note:y_max") and len(_gid(fig, "limit:+y_max")) == 1
    finally:
        plt.close(fig)


def test_both_carriers_and_forces_on_their_own_axes(both_log):
    run = runlog.load(both_log[0])
    assert run.carriers_in_use == ["front", "rear"]
    fig = figures.response(run)
    try:
        for k in ("front", "rear"):
            assert len(_gid(fig, f"y:{k}")) == 1 and len(_gid(fig, f"u:{k}")) == 1
    finally:
        figures.pyplot().close(fig)
    fig = figures.forces(run)
    try:
        fy, mz, y = fig.axes
        assert {l.get_gid().split(":")[0] for l in fy.get_lines() if l.get_gid() and ":" in l.get_gid()
                and not l.get_gid().startswith(("state", "fault"))} == {"fy"}
        assert {l.get_gid() for l in mz.get_lines() if (l.get_gid() or "").startswith("mz:")} == \
            {"mz:ft_fl", "mz:ft_fr", "mz:ft_rl", "mz:ft_rr"}
        assert fy.get_ylabel().endswith("(N)") and mz.get_ylabel().endswith("(N m)")
    finally:
        figures.pyplot().close(fig)


def test_plot_cli_and_report_write_the_same_figures(step_log, tmp_path, capsys):
    from rig_runtime.app.report import write_report
    log, summary, _ = step_log
    c, out, _ = rig(capsys, "log", "plot", log, "--out", tmp_path / "plots")
    assert c == 0
    plotted = sorted(p.name for p in (tmp_path / "plots").iterdir())
    # observer.png: sim.yaml has an observer (tests/test_observer_degraded_e2e.py looks inside it)
    # law.png: the PI-PD's signals as the law declares them (the log's law_signals)
    assert plotted == ["forces.png", "law.png", "observer.png", "response.png"] and \
        out.split() == [str(tmp_path / "plots" / n) for n in ("response.png", "forces.png", "observer.png",
                                                               "law.png")]
    rep = write_report(log, tmp_path / "rep", load_scenario("single-step"), summary)
    assert sorted(p.name for p in rep) == plotted + ["summary.md"]


# --------------------------------------------------------------------------------- compare
def test_compare_table_and_overlay(step_log, fault_log, tmp_path, capsys):
    c, out, _ = rig(capsys, "log", "compare", step_log[0], fault_log[0], "--out", tmp_path, "--json")
    d = json.loads(out)
    assert c == 0 and sorted(p.rsplit("/", 1)[1] for p in d["files"]) == ["compare.md", "compare.png"]
    rows = {r["quantity"]: r for r in d["table"]}
    assert rows["final state"]["a"] == "IDLE" and rows["final state"]["b"] == "FAULT"
    assert rows["faults"]["b_minus_a"] == 1
    r = rows["RUNNING (s)"]
    assert (r["a"], r["b"]) == (pytest.approx(1.5), pytest.approx(1.415)) and r["b_minus_a"] == pytest.approx(-0.085)
    assert rows["max |u| rear (A)"]["b_minus_a"] is not None
    assert "step at 1 s: steady-state error (mm)" in rows
    fig = figures.compare([runlog.load(step_log[0]), runlog.load(fault_log[0])], ["A", "B"])
    try:
        assert {l.get_gid() for l in fig.axes[0].get_lines()} >= {"y:rear:0", "y:rear:1", "y_ref:0", "y_ref:1"}
        assert len(_gid(fig, "fault:s_rl:stale:1")) == 3 and not _gid(fig, "fault:s_rl:stale:0")
    finally:
        figures.pyplot().close(fig)


# --------------------------------------------------------------------------------- export
def test_export_units_state_names_and_events_path(fault_log, tmp_path, capsys):
    log = fault_log[0]
    out = tmp_path / "run.csv"
    c, text, _ = rig(capsys, "log", "export", log, "--csv", out)
    assert c == 0
    rows = list(csv.reader(out.open()))
    head = rows[0]
    assert head[:6] == ["t [s]", "t_run [s]", "lateness [s]", "work [s]", "state", "y_ref [m]"]
    assert {"y_r [m]", "psi_ar [rad]", "dw_r [rad/s]", "rear_u_lim [A]", "i_rl [A]", "ft_rr_fy [N]",
            "ft_rr_mz [N m]", "rear_x_I [m s]"} <= set(head)
    states = [r[4] for r in rows[1:]]
    assert set(states) <= STATES and states[-1] == "FAULT" and "RUNNING" in states
    ev = tmp_path / "run.csv.events.csv"          # OUT.events.csv, as README and --help say
    assert str(ev) in text
    ev_rows = list(csv.reader(ev.open()))
    assert ev_rows[0] == ["t", "kind", "device", "check", "value", "limit", "message"]
    assert any(r[1] == "fault" and r[2] == "s_rl" for r in ev_rows[1:])
    # `rig export` is the same code
    c, _, _ = rig(capsys, "export", log, "--csv", tmp_path / "alias.csv")
    assert c == 0 and (tmp_path / "alias.csv").read_text() == out.read_text()
    assert (tmp_path / "alias.csv.events.csv").read_text() == ev.read_text()


def test_units_and_state_names():
    assert [column_unit(n) for n in ("t", "b_f_age", "y_ref", "s_rl", "psi_m", "front_de_psi", "omega_rl",
                                     "front_u_cmd", "i_fr", "ft_fl_fz", "ft_fl_mx", "state", "mystery")] == \
        ["s", "s", "m", "m", "rad", "rad/s", "rad/s", "A", "A", "N", "N m", "", ""]
    assert column_header("mystery") == "mystery" and column_header("y_f") == "y_f [m]"
    assert [state_name(x) for x in (0.0, 2.0, 4.0, math.nan, 9.0)] == ["IDLE", "RUNNING", "FAULT", "NaN", "9.0"]


# --------------------------------------------------------------------------------- bad input
def test_bad_input_is_one_line_exit_2(step_log, tmp_path, capsys):
    text = tmp_path / "notes.h5"
    text.write_text("not a log\n")
    blocker = tmp_path / "file"
    blocker.write_text("")
    for args, needle in ((("log", "info", tmp_path / "missing.h5"), "no such file"),
                         (("log", "plot", text), "not a readable rig log"),
                         (("log", "compare", step_log[0], text), "not a readable rig log"),
                         (("log", "plot", step_log[0], "--out", blocker / "sub"), "--out"),
                         (("log", "plot", step_log[0], "--out", blocker), "--out"),
                         (("log", "export", step_log[0], "--csv", blocker / "x.csv"), "--csv")):
        c, out, err = rig(capsys, *args)
        assert c == 2 and err.count("\n") == 1 and needle in err and err.startswith("rig log: error:"), (args, err)
    with pytest.raises(SystemExit) as e:
        main(["log"])
    assert e.value.code == 2 and "ACTION" in capsys.readouterr().err


# --------------------------------------------------------------------------------- summaries
def test_lockstep_summary_reports_wall_cost_and_run_time_faults(fault_log, capsys):
    _, summary, _ = fault_log
    _print_summary(dict(summary, faults=[dict(f) for f in summary["faults"]]), as_json=False)
    out = capsys.readouterr().out
    assert "lateness" not in out and "wall-clock per cycle" in out
    assert "max |u| (differential current per carrier)" in out and "per wheel (wire current" in out
    t_run = summary["faults"][0]["t"] - summary["run_started_t"]
    assert f"fault at t={t_run:+.3f} s: s_rl stale" in out


def test_realtime_summary_fault_times_are_run_relative(capsys):
    summary = {"final_state": "FAULT", "cycles": 300, "max_abs_current_A": 1.3, "max_abs_wire_current_A": 0.65,
               "log": "x.h5", "run_started_t": 9944.363, "wall_time_s": 1.6,
               "faults": [{"t": 9945.783, "device": "s_rl", "check": "stale", "value": 0.02, "limit": 0.02,
                           "message": "no data for 20 ms"}],
               "timing": {"release_lateness_us": {"p50": 1.0, "p99": 20.0, "max": 40.0},
                          "cycle_work_us": {"p50": 250.0, "p99": 600.0, "max": 1000.0}, "deadline_misses": 0}}
    _print_summary(json.loads(json.dumps(summary)), as_json=False)
    out = capsys.readouterr().out
    assert "fault at t=+1.420 s" in out and "9945" not in out and "lateness p50/p99/max 1.0/20.0/40.0 us" in out
    _print_summary(json.loads(json.dumps(summary)), as_json=True)
    assert json.loads(capsys.readouterr().out)["faults"][0]["t_run"] == pytest.approx(1.42)


# --------------------------------------------------------------------------------- rig tune --plot
def test_tune_figures_gain_labels_boundary_and_paper_overlay():
    cfg = config.load()
    r = analysis.tune(cfg)
    figs = figures.tune_figures(cfg, r, analysis.PAPER)
    try:
        rl = figs["root_locus"]
        (b,) = _gid(rl, "boundary")
        re, im = b.get_xdata(), b.get_ydata()
        assert len(re) == 2 and np.all(np.abs(re) < 0.05) and sorted(np.sign(im)) == [-1, 1]   # on the imaginary axis
        assert "18605" in b.get_label() and f"{r.stability_boundary_kp:.0f}" in b.get_label()
        labels = [t.get_text() for t in _by_gid(rl, "gain-label:")]
        assert labels == [f"K_P={f * r.stability_boundary_kp:.0f}" for f in (0.1, 0.25, 0.5, 0.75)]
        assert _by_gid(rl, "locus-unstable:")
        ev = figs["eigenvalues"]
        for key in ("inner", "inner_filtered", "outer", "closed_loop"):
            (p,) = _gid(ev, f"paper:{key}")
            np.testing.assert_array_equal(p.get_xdata(), analysis.PAPER[key])
        assert not _gid(ev, "paper:closed_loop_sampled")      # the paper prints no sampled loop
        (bd,) = _gid(figs["p_slowest_vs_D"], "boundary")
        assert bd.get_xdata()[0] == r.stability_boundary_kp
    finally:
        for f in figs.values():
            figures.pyplot().close(f)


# --------------------------------------------------------------------------------- rig run (slow)
@pytest.mark.slow
def test_log_tools_on_a_rig_run_log(tmp_path, capsys):
    with start_sim_process(config=realtime_sim_config(tmp_path), workdir=tmp_path / "sim",
                           extra_args=["--rt-priority", "50", "--runtime-rt-priority", "80"]) as sim:
        # the real-time tests' stated tolerance (tests/e2e.py): the machine's scheduling is not
        # what this test checks
        config_path = realtime_config(sim.config_path, tmp_path / "rig-run.yaml")
        proc, log = _start_run(config_path, tmp_path, "logtools", "--duration", "2")
        summary = _finish(sim, proc, log, 30)
    c, out, _ = rig(capsys, "log", "info", log, "--json")
    d = json.loads(out)
    assert c == 0 and d["mode"] == "run" and d["final_state"] == "IDLE" and d["clock"] == "realtime"
    assert d["rows"] == summary["recorder"]["rows"]
    # RUNNING lasted the --duration: it stopped at the first cycle at or after 2 s of it. Real
    # time, so that cycle's release may be late (or periods skipped before it): the rows
    # around the stop bracket it rather than a tolerance on the time
    run = runlog.load(log)
    state, rel = run.columns["state"], run.t_rel
    j = int(np.argmax(state == float(State.STOPPING)))
    assert state[j] == float(State.STOPPING) and state[j - 1] == float(State.RUNNING), state[j - 1:j + 1]
    assert d["running_s"] == pytest.approx(float(rel[j]), abs=1e-9)        # the STOPPING row's time
    assert rel[j - 1] < 2.0 <= d["running_s"] + 1e-9, (rel[j - 1], d["running_s"])
    assert [s["to"] for s in d["states"]][:2] == ["ARMED", "RUNNING"] and d["states"][1]["t_run"] == 0.0
    assert d["timing_us"]["work"]["p50"] > 0 and d["steps"] and d["steps"][0]["t0"] == 1.0
    assert d["config_source"] == str(config_path)
    c, _, _ = rig(capsys, "log", "plot", log, "--out", tmp_path / "p")
    assert c == 0 and (tmp_path / "p" / "response.png").stat().st_size > 10000
    c, _, _ = rig(capsys, "log", "export", log, "--csv", tmp_path / "r.csv")
    rows = list(csv.reader((tmp_path / "r.csv").open()))
    assert c == 0 and len(rows) == d["rows"] + 1 and rows[0][0] == "t [s]"
    fig = figures.response(run)
    try:
        assert len(_gid(fig, "state:RUNNING")) == 4 and _by_gid(fig, "state:STOPPING")
        assert fig.axes[0].get_lines()[0].get_gid() == "y_ref"
    finally:
        figures.pyplot().close(fig)


def test_a_minimal_or_empty_log_still_summarises(tmp_path, capsys):
    """A log with only a few columns (another tool's) or no rows at all (killed before its
    first flush): info and plot say what there is instead of failing."""
    from rig_runtime.recorder import Recorder
    small, empty = tmp_path / "small.h5", tmp_path / "empty.h5"
    rec = Recorder(small, ["t", "y", "state"], attrs={})
    rec.open()
    for i in range(100):
        rec.append((i * 0.005, 0.001, 2.0 if i > 10 else 1.0))
    rec.event(0.055, "state", message="ARMED -> RUNNING")
    rec.close()
    rec = Recorder(empty, ["t", "t_run", "state", "y_r", "i_rl", "i_rr"], attrs={"config": "{}"})
    rec.open()
    rec.close()
    d = runlog.info(runlog.load(small))
    assert d["final_state"] == "RUNNING" and d["running_s"] == pytest.approx(0.445) and d["max_abs_u_A"] == {}
    d = runlog.info(runlog.load(empty))
    assert d["rows"] == 0 and not d["reached_running"] and d["final_state"] == "-"
    for log in (small, empty):
        c, out, _ = rig(capsys, "log", "plot", log, "--out", tmp_path / log.stem)
        assert c == 0 and (tmp_path / log.stem / "response.png").exists()


def test_export_mcap_for_foxglove(step_log, tmp_path, capsys):
    step_log = step_log[0]
    pytest.importorskip("foxglove")
    mcap_reader = pytest.importorskip("mcap.reader")
    out = tmp_path / "run.mcap"
    code, o, e = rig(capsys, "log", "export", step_log, "--mcap", out)
    assert code == 0 and o.startswith(f"{runlog.load(step_log).rows} rows -> "), e
    with open(out, "rb") as f:
        topics = {ch.topic for _, ch, _ in mcap_reader.make_reader(f).iter_messages()}
    assert {"/rig/state", "/rig/rear", "/rig/currents"} <= topics
    code, o, e = rig(capsys, "log", "export", step_log)
    assert code == 2 and "--csv OUT and/or --mcap OUT" in e and e.count("\n") == 1
