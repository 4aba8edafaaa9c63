"""The control law's signals by name (issue 25): each law declares its signals once
(``law.signals``, rig_runtime/control.py) and the log's columns, the ``law_signals``
attribute, the live panel, UDP telemetry, Foxglove and ``rig log plot`` follow from it.

The values are checked by hand against the law's definition (docs/vehicle.md): the
decoupled law's cross-carrier term is recomputed from the logged y_f − y_r through the
Tustin differentiator, its feed term from the reference and the schedule's factor."""

from __future__ import annotations

import dataclasses
import json
import socket
import subprocess
import sys

import numpy as np
import pytest

from rig_runtime import config
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.app.export import read_log
from rig_runtime.app.telemetry import UdpTelemetry
from rig_runtime.damping import YawDamping
from rig_runtime.control import DecoupledLaw, PIPDLaw, PLaw, make_controller
from rig_runtime.lanes import law_signals, signal_getter
from rig_runtime.logformat import LAW_SIGNALS_ATTR
from rig_runtime.loop import LANE_FIELDS, log_columns
from rig_runtime.scenario import load_scenario
from rig_runtime.safety import State
from tests.test_telemetry import LogInfo

VEHICLE = config.CONFIG_DIR / "vehicle.yaml"
RUNNING = int(State.RUNNING)


@pytest.fixture(scope="module")
def vcfg():
    return config.load(VEHICLE)


def lockstep(cfg, duration_s: float, path):
    """``vehicle-steps`` (a 2 mm front step at 1 s, v = +1), cut to ``duration_s``, seed 0."""
    sc = dataclasses.replace(load_scenario("vehicle-steps"), duration_s=duration_s)
    s, code = run_lockstep(cfg, sc, path, seed=0)
    assert code == 0 and not s["faults"], s["faults"]
    return read_log(path)


@pytest.fixture(scope="module")
def vlog(vcfg, tmp_path_factory):
    path = tmp_path_factory.mktemp("law") / "vehicle.h5"
    return path, lockstep(vcfg, 3.0, path)


def test_each_law_declares_its_signals():
    assert tuple(PIPDLaw.SIGNALS) == ("e_y", "x_I", "psi_ref", "e_psi", "de_psi", "u_unsat")
    assert tuple(PLaw.SIGNALS) == ("e_y", "u_unsat")
    assert tuple(DecoupledLaw.SIGNALS) == tuple(PIPDLaw.SIGNALS) + ("w", "w_cross", "x_I_psi")
    law = DecoupledLaw(6.0, 6.0, 160.0, 20.0, 0.03, 0.005, b_y=0.0, K_x_y=3.6, T_x_y=0.1)
    assert "x_I_psi" not in law.signals                       # K_I_psi = 0: no yaw integrator
    assert "x_I_psi" in dataclasses.replace(law, K_I_psi=10.0).signals


def test_paper_set_up_columns_unchanged_and_p_law_has_only_its_own():
    cfg = config.load(config.CONFIG_DIR / "sim.yaml")
    rear = [c for c in log_columns(cfg, [], []) if c.startswith("rear_") and c != "rear_v"]
    assert rear[:11] == ["rear_e_y", "rear_x_I", "rear_psi_ref", "rear_e_psi", "rear_de_psi", "rear_u_unsat",
                         "rear_u_cmd", "rear_u_lim", "rear_y_ref", "rear_g", "rear_held"]
    p = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, law="p"))
    assert [c for c in log_columns(p, [], []) if c.startswith("rear_") and c != "rear_v"][:2 + len(LANE_FIELDS)] == \
        ["rear_e_y", "rear_u_unsat"] + [f"rear_{f}" for f in LANE_FIELDS]


def test_signal_getter_reads_what_the_step_computed(vcfg):
    """Step the decoupled controller by hand: the getter returns the law's own arithmetic."""
    c = make_controller(vcfg.controller, 4.0)

    class Pair:                         # the cross-lane stage's interface: y by carrier
        yf, yr = 0.0, 0.0

        def y(self, carrier):
            return self.yf if carrier == "front" else self.yr

    pair = Pair()
    c.couple(pair)
    names = tuple(c.law.signals)
    get = signal_getter(c, names)
    c.start(0.0, 0.0, 0.0)
    law = c.law
    d_prev, dd = 0.0, 0.0
    for k, (yf, yr, y_ref) in enumerate([(1e-4, -2e-4, 1e-3), (3e-4, -1e-4, 1e-3), (2e-4, 0.0, 5e-4)]):
        pair.yf, pair.yr = yf, yr
        c.step(y_ref, yf, 1e-4 * k)
        d = yf - yr
        dd = law.a * dd + law.b * (d - d_prev)
        d_prev = d
        v = dict(zip(names, get(c)))
        cross = law.K_x_y * (d + law.T_x_y * dd)
        assert v["w_cross"] == pytest.approx(cross, rel=1e-12, abs=1e-15)
        assert v["w"] == pytest.approx(law.K_P_y * c.g * (1 - law.b_y) * y_ref + cross, rel=1e-12, abs=1e-15)
        assert v["u_unsat"] == c.st.u_unsat and v["psi_ref"] == c.st.psi_ref
    with pytest.raises(AttributeError, match="no signal nope"):
        signal_getter(c, ("e_y", "nope"))


def test_vehicle_log_has_the_law_signals_with_the_values_the_law_computed(vcfg, vlog):
    _, log = vlog
    c, attrs = log["columns"], log["attrs"]
    law = DecoupledLaw.of(vcfg.controller.decoupled, vcfg.controller.h)
    assert vcfg.controller.decoupled.K_I_psi == 0.0
    declared = dict(law_signals(vcfg))
    assert "D_hat" in declared and "D_hat" not in law.signals     # the damping schedule's D̂ (needs the yaw parameters)
    assert json.loads(attrs[LAW_SIGNALS_ATTR]) == declared == dict(law_signals(vcfg))
    for k in ("front", "rear"):
        cols = [x for x in c if x.startswith(f"{k}_") and x[len(k) + 1:] in {*declared, *LANE_FIELDS}]
        assert cols == [f"{k}_{n}" for n in (*declared, *LANE_FIELDS)]
        assert f"{k}_x_I_psi" not in c                      # the shipped law has no yaw integrator
    i = np.flatnonzero(c["state"] == RUNNING)
    assert len(i) > 500 and np.all(np.diff(i) == 1)
    # K_x,y (d + T_x,y d̂'), d = y_f − y_r, d̂' the Tustin differentiator from 0 at the start
    d = (c["y_f"] - c["y_r"])[i]
    dd = np.zeros_like(d)
    for n in range(1, len(d)):
        dd[n] = law.a * dd[n - 1] + law.b * (d[n] - d[n - 1])
    decouple = law.K_x_y * (d + law.T_x_y * dd)
    assert np.max(np.abs(decouple)) > 1e-3                  # the term acts (mrad), not a column of zeros
    for k in ("front", "rear"):
        # the trailing carrier (the rear at v > 0) also follows the leading one: − K_t,y |g| d
        trails = np.array([DecoupledLaw.of(vcfg.controller.decoupled, vcfg.controller.h, carrier=k).trailing(g)
                           for g in c[f"{k}_g"][i]])
        cross = decouple - np.where(trails, law.K_t_y * np.abs(c[f"{k}_g"][i]) * d, 0.0)
        np.testing.assert_allclose(c[f"{k}_w_cross"][i], cross, rtol=0, atol=1e-12)
        w = law.K_P_y * c[f"{k}_g"][i] * (1.0 - law.b_y) * c[f"{k}_y_ref"][i] + cross
        np.testing.assert_allclose(c[f"{k}_w"][i], w, rtol=0, atol=1e-12)
        # the inner PD on ψ_ref (with w subtracted): u before saturation, K_P,ψ as scheduled at the logged D̂
        own = DecoupledLaw.of(vcfg.controller.decoupled, vcfg.controller.h, k, YawDamping.of(vcfg.plant.carrier(k)))
        kp = np.array([own.yaw_gains(D)[0] for D in c[f"{k}_D_hat"][i]])
        assert np.all(c[f"{k}_D_hat"][i] == vcfg.plant.carrier(k).D_min)     # the current moves every cycle
        u = kp * c[f"{k}_e_psi"][i] + law.K_D_psi * c[f"{k}_de_psi"][i]
        np.testing.assert_allclose(c[f"{k}_u_unsat"][i], u, rtol=0, atol=1e-12)
    # the front's 2 mm step at 1 s moves its feed term by K_P,y (1 − b_y) Δy_ref
    j = np.searchsorted(c["t_run"][i], 1.0)
    assert c["front_w"][i][j] - c["front_w"][i][j - 1] == pytest.approx(
        law.K_P_y * (1 - law.b_y) * 2e-3, abs=2e-4)


def test_yaw_integrator_gets_a_column_when_the_law_has_one(vcfg, tmp_path):
    c0 = vcfg.controller
    cfg = dataclasses.replace(vcfg, controller=dataclasses.replace(
        c0, decoupled=dataclasses.replace(c0.decoupled, K_I_psi=20.0)))
    c = lockstep(cfg, 1.5, tmp_path / "ki.h5")["columns"]
    law = DecoupledLaw.of(cfg.controller.decoupled, cfg.controller.h)
    i = np.flatnonzero(c["state"] == RUNNING)     # the damping schedule at D̂ = D_min throughout
    for k in ("front", "rear"):
        assert np.all(c[f"{k}_D_hat"][i] == cfg.plant.carrier(k).D_min)
        x = c[f"{k}_x_I_psi"][i]
        assert np.max(np.abs(x)) > 0.0
        # x_Iψ⁺ = x_Iψ + (h/2)(e_ψ + e_ψ,prev) (no saturation here) and u = PD + K_I,ψ x_Iψ⁺
        e = c[f"{k}_e_psi"][i]
        np.testing.assert_allclose(np.diff(x), law.half_h * (e[1:] + e[:-1]), rtol=0, atol=1e-15)
        u = law.K_P_psi * e + law.K_D_psi * c[f"{k}_de_psi"][i] + law.K_I_psi * x
        np.testing.assert_allclose(c[f"{k}_u_unsat"][i], u, rtol=0, atol=1e-12)


def test_log_info_and_plot_show_the_law_signals(vlog, tmp_path):
    path, _ = vlog
    r = subprocess.run([sys.executable, "-m", "rig_runtime", "log", "info", str(path)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "control law decoupled: signals" in r.stdout and "w_cross [rad]" in r.stdout
    out = tmp_path / "plots"
    r = subprocess.run([sys.executable, "-m", "rig_runtime", "log", "plot", str(path), "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert (out / "law.png").stat().st_size > 10_000 and str(out / "law.png") in r.stdout


def test_law_figure_has_a_panel_per_signal(vlog):
    from rig_runtime.app import figures, runlog
    path, _ = vlog
    run = runlog.load(path)
    fig = figures.law(run)
    try:
        gids = {ln.get_gid() for a in fig.axes for ln in a.get_lines()}
        labels = [a.get_ylabel() for a in fig.axes]
    finally:
        figures.pyplot().close(fig)
    names = list(json.loads(run.attrs[LAW_SIGNALS_ATTR]))
    assert len(labels) == len(names) and labels[names.index("w_cross")] == "w_cross (mrad)"
    assert {f"{n}:{k}" for n in names for k in ("front", "rear")} <= gids


def test_telemetry_sends_the_law_signals_in_a_datagram_of_their_own(vlog):
    _, log = vlog
    cols = tuple(log["columns"])
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    out = UdpTelemetry(LogInfo("run.h5", cols, {LAW_SIGNALS_ATTR: log["attrs"][LAW_SIGNALS_ATTR]}),
                       port=rx.getsockname()[1])
    try:
        k = int(np.flatnonzero(log["columns"]["state"] == RUNNING)[300])
        block = np.column_stack([log["columns"][n] for n in cols])[k:k + 1]
        out.rows(block)
        main, law = json.loads(rx.recv(65536)), json.loads(rx.recv(65536))
    finally:
        out.close()
        rx.close()
    assert out.sent == out.sent_law == 1 and "front_law" not in main
    assert set(law) == {"timestamp", "front_law", "rear_law"} and law["timestamp"] == main["timestamp"]
    for carrier in ("front", "rear"):
        assert list(law[f"{carrier}_law"]) == list(json.loads(log["attrs"][LAW_SIGNALS_ATTR]))
        for n, v in law[f"{carrier}_law"].items():
            assert v == log["columns"][f"{carrier}_{n}"][k]
