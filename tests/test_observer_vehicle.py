"""The observer on the vehicle (configs/vehicle.yaml; docs/observer.md, "vehicle"): designed
per carrier from that carrier's own plant values, relation (4) with |v| in its input term, a
table of designs over the schedule's speeds from which the lane takes the one nearest v̂; the
paper's set-up keeps its single design; a lateral laser lost at v = −1 DEGRADES and ends IDLE.
Unit tests plus one short lockstep run."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.linalg import expm

from rig_runtime import config
from rig_runtime.app import observer_design as od
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.app.export import read_log
from rig_runtime.lanes import make_lanes
from rig_runtime.observer import Observer, dw_row_at
from rig_runtime.scenario import load_scenario

from .e2e import read_with_truth


@pytest.fixture(scope="module")
def vcfg():
    return config.load(config.resolve_config_path("vehicle.yaml"))


@pytest.fixture(scope="module")
def vdesigns(vcfg):
    """The per-carrier filters' speed tables (what a config with one controlled carrier on a
    schedule gets; the vehicle itself runs the joint filter, tests/test_observer_joint.py)."""
    return {c: od.speed_table(vcfg, c) for c in vcfg.controlled}


def _by_hand(p, carrier: str, v: float, D: float):
    """The carrier's (2a)/(2b) + (6) from the plant docstring (sim_backend/plant.py), written
    out: ẏ = ±a y ∓ a y_other + c̄_y v ψ + v/(2 l0) y_off + |v| F/(2 c22)."""
    a = p.c_y * v / (2 * p.l0)
    s = 1.0 if carrier == "front" else -1.0
    w2 = p.omega0 ** 2
    A = np.array([[s * a, p.c_y * v, 0.0], [0.0, 0.0, 1.0], [0.0, -w2, -2 * D * p.omega0]])
    Bc = np.array([[0.0, -s * a, abs(v) / (2 * p.c11), v / (2 * p.l0) * p.y_off],
                   [0.0, 0.0, 0.0, 0.0],
                   [p.K * w2, 0.0, 0.0, w2 * p.psi_off]])
    return A, Bc


@pytest.mark.parametrize("carrier", ["front", "rear"])
@pytest.mark.parametrize("v", [1.0, -1.0, 0.3])
def test_each_carrier_is_designed_on_its_own_plant_values(vcfg, carrier, v):
    """With a front y_off of its own (the shipped one is 0) the offset term's sign shows too."""
    plant = dataclasses.replace(vcfg.plant, front=dataclasses.replace(vcfg.plant.front, y_off=0.5e-3))
    cfg = dataclasses.replace(vcfg, plant=plant)
    p = cfg.plant.carrier(carrier)
    D = p.D_min
    A, Bc = _by_hand(p, carrier, v, D)
    A2, Bc2 = od.continuous_model(cfg, carrier, D, v)
    assert np.allclose(A2, A, rtol=1e-12, atol=0) and np.allclose(Bc2, Bc, rtol=1e-12, atol=0)
    d = od.design(cfg, carrier, v=v)
    h = cfg.controller.h
    M = np.zeros((7, 7))
    M[:3, :3], M[:3, 3:] = A, Bc
    E = expm(M * h)
    assert np.allclose(np.array(d.A).reshape(3, 3), E[:3, :3], rtol=1e-10, atol=1e-14)
    assert np.allclose(d.c, E[:3, 6], rtol=1e-10, atol=1e-16)
    assert d.v == v and d.dw_row == dw_row_at(p, v)


def test_the_carriers_designs_differ_where_their_plants_do(vdesigns, vcfg):
    f, r = vdesigns["front"], vdesigns["rear"]
    pf, pr = vcfg.plant.carrier("front"), vcfg.plant.carrier("rear")
    assert pf.omega0 != pr.omega0 and f.A[7] != r.A[7]            # ω0 in the yaw row
    assert f.A[0] > 1.0 > r.A[0]                                   # v = +1: the front leads (unstable y)


def test_relation_4s_input_term_has_abs_v(vcfg):
    p = vcfg.plant.carrier("rear")
    gy_p, gr_p, gu_p = dw_row_at(p, 1.0)
    gy_n, gr_n, gu_n = dw_row_at(p, -1.0)
    assert gu_n == gu_p == pytest.approx(p.k_tau / (p.r0 ** 2 * p.c11)) and gu_p > 0
    assert gy_n == -gy_p and gy_p == pytest.approx(p.Gamma * p.b / (2 * p.r0 ** 2))
    assert gr_n == gr_p == pytest.approx(p.b / (2 * p.r0))
    assert od.design(vcfg, "rear", v=-1.0).dw_row == (gy_n, gr_n, gu_n)


def test_the_speed_table_spans_the_schedules_range_in_both_directions(vdesigns, vcfg):
    sch = vcfg.controller.schedule
    for carrier, d in vdesigns.items():
        t = d.table
        assert d.v == sch.v_design == 1.0 and t.v_ref == 1.0 and t.ratio == od.SPEED_RATIO
        speeds = [e.v for e in t.forward]
        assert speeds == pytest.approx([t.v_ref * t.ratio ** k for k in range(t.k_lo, t.k_hi + 1)], rel=1e-12)
        assert [e.v for e in t.backward] == [-v for v in speeds]
        assert speeds[0] <= od.SPEED_FLOOR * sch.v_min < speeds[1]               # into the band
        assert speeds[-2] < max(map(abs, sch.v_range)) <= speeds[-1]
        assert t.forward[-t.k_lo].v == 1.0 and t.forward[-t.k_lo].K_full == d.K_full
        assert all(e.carrier == carrier and e.table is None for e in t.forward + t.backward)
        for e in t.forward + t.backward:     # every grid point: a stable filter of its own model
            Ad = np.array(e.A).reshape(3, 3)
            C = np.array([[1.0, 0, 0], [0, 1, 0], [e.dw_row[0], 0, e.dw_row[1]]])
            K = np.array(e.K_full).reshape(3, 3)
            Kn = np.array(e.K_nolat).reshape(3, 2)
            assert max(abs(np.linalg.eigvals((np.eye(3) - K @ C) @ Ad))) < 1.0
            assert max(abs(np.linalg.eigvals((np.eye(3) - Kn @ C[1:]) @ Ad))) < 1.0


@pytest.mark.parametrize("v", [1.0, -1.0, 0.73, -0.41, 1.5, 1.9, -1.7, 0.25, -0.2, 0.11, 0.05, -1e-6])
def test_the_observer_takes_the_design_nearest_the_measured_speed(vdesigns, v):
    d = vdesigns["rear"]
    o = Observer(d)
    o.select(v)
    grid = d.table.forward if v > 0 else d.table.backward
    want = min(grid, key=lambda e: abs(math.log(abs(e.v)) - math.log(abs(v))))
    assert o.d is want                                   # one of the preallocated designs
    assert o.sigma_y == d.sigma_y_outage[0]


def test_no_speed_keeps_the_design(vdesigns):
    o = Observer(vdesigns["front"])
    o.select(-0.8)
    kept = o.d
    for v in (0.0, math.nan):
        o.select(v)
        assert o.d is kept


def test_a_switch_changes_the_gains_and_the_health_normalisation(vdesigns):
    """The step after a switch predicts with the new design's model and gains."""
    d = vdesigns["rear"]
    a, b = Observer(d), Observer(d)
    b.select(-1.0)
    for o in (a, b):
        o.step(1e-3, 0.0, 0.0, 0.0, 0.0, True)
        o.step(1e-3, 1e-3, 0.02, 0.5, 0.0, False)
    assert b.d.v == -1.0 and a.d.v == 1.0 and a.y != b.y
    assert b._is_nl == tuple(1 / math.sqrt(s) for s in b.d.S_nolat)


def test_the_lanes_schedule_hook_selects_the_design(vdesigns, vcfg):
    lanes = make_lanes(vcfg, lambda t: 0.0, observers=vdesigns)
    for lane in lanes:
        lane.schedule(-0.5)
        assert lane.observer.d.v == pytest.approx(-od.SPEED_RATIO ** round(math.log(0.5) / math.log(od.SPEED_RATIO)))
        lane.schedule(0.05)                              # inside the band: the grid's lowest speed
        assert lane.observer.d is vdesigns[lane.carrier].table.forward[0]


def test_the_paper_set_up_keeps_its_single_design():
    cfg = config.load()
    assert cfg.controller.schedule is None
    (d,) = od.designs(cfg).values()
    assert d.table is None and d.v == cfg.plant.v
    assert d == od.design(cfg, "rear")
    o = Observer(d)
    o.select(-1.0)
    assert o.d is d


# ------------------------------------------------------------------ lockstep: a dropout at v = −1
DROPOUT = """name: vehicle-degraded-dropout
duration_s: 12
speed: [{t: 0, v: -1.0}]
reference:
  front: [{t: 0, y_mm: 0}, {t: 1, y_mm: 2.0}]
  rear:  [{t: 0, y_mm: 0}, {t: 5, y_mm: 2.0}]
faults: [{kind: dropout, t: 4.0, device: b_r, duration_s: 6.0}]
"""


def test_a_lateral_laser_lost_at_v_minus_1_degrades_and_the_run_goes_on(tmp_path, vcfg):
    """b_r drops out at v = −1 (the rear carrier leads) for 6 s: both carriers (b_r feeds both
    y) go DEGRADED; the running gear's joint filter keeps using b_f (a combination of y_f and
    y_r) with both carriers' ψ and Δω, its σ_y (the design's outage table for "b_r lost") stays
    far below degraded.sigma_y_max, and b_r is readmitted after it comes back: IDLE, no fault.
    (The per-carrier filters dropped both lateral lasers and ended this run in the clean stop
    11 cycles after the loss.)"""
    p = tmp_path / "dd.yaml"
    p.write_text(DROPOUT)
    summary, code = run_lockstep(vcfg, load_scenario(p), tmp_path / "run.h5", seed=0)
    assert code == 0 and summary["final_state"] == "IDLE" and not summary["faults"], summary["faults"]
    t0 = summary["run_started_t"]
    ivs = {iv["carrier"]: iv for iv in summary["degraded"]}
    assert set(ivs) == {"front", "rear"}
    for iv in ivs.values():
        assert (iv["laser"], iv["check"]) == ("b_r", "stale")
        assert 4.0 < iv["t_start"] - t0 < 4.1
        assert iv["end"] == "b_r readmitted" and 10.0 < iv["t_end"] - t0 < 11.2
    data, truth, _, _ = read_with_truth(tmp_path / "run.h5")
    idx = np.clip(np.searchsorted(truth["t"], data["t"] - 1e-9), 0, len(truth["t"]) - 1)
    j = od.joint_design(vcfg, v=-1.0)
    for car, key in (("front", "y_f"), ("rear", "y_r")):
        deg = (data["state"] == 2.0) & (data[f"{car}_obs_degraded"] == 1.0)
        assert deg.sum() > 1000
        e = data[f"{car}_obs_y_hat"][deg] - truth[key][idx][deg]
        assert np.max(np.abs(e)) < 0.1e-3                       # the acceptance; measured: 2.4 µm
        sig = data[f"{car}_obs_sigma_y"][deg]
        assert np.max(sig) <= max(j.sigma_y[1][0 if car == "front" else 1]) * (1 + 1e-9)
        assert np.max(sig) < vcfg.degraded.sigma_y_max
    assert data["rear_u_lim"][-1] == 0.0 and data["front_u_lim"][-1] == 0.0


# ------------------------------------------------------------------ lockstep: through standstill
def test_through_the_reversal_the_estimate_follows_and_the_innovation_test_stays_quiet(tmp_path, vcfg):
    """vehicle-reversal (+1 → −1 through standstill, then a 2 mm step at −1 at 16 s) with the
    innovation rule on (sim-observer.yaml's 30 over 200 cycles): no finding, no degradation, and
    ŷ on the simulated truth. A design for the wrong direction would predict Δω's y-term with
    the wrong sign (2 Γ|v|b/(2r0²)·2 mm ≈ 0.05 rad/s off, σ of the Δω innovation ≈ 0.06 rad/s):
    T_dw over a 1 s window would pass 30 after the step."""
    lim = dataclasses.replace(vcfg.limits, innovation_chi2=30.0, innovation_window=200)
    cfg = dataclasses.replace(vcfg, limits=lim)
    summary, code = run_lockstep(cfg, load_scenario("vehicle-reversal"), tmp_path / "run.h5", seed=0,
                                 duration_s=21.0)
    assert code == 0 and summary["final_state"] == "IDLE" and not summary["faults"], summary["faults"]
    assert not summary.get("degraded")
    data, truth, _, _ = read_with_truth(tmp_path / "run.h5")
    idx = np.clip(np.searchsorted(truth["t"], data["t"] - 1e-9), 0, len(truth["t"]) - 1)
    run = (data["state"] == 2.0) & (data["t_run"] > 2.0)
    assert np.min(data["v_meas"][run]) < -0.99                 # it got to −1 …
    for car, key in (("front", "y_f"), ("rear", "y_r")):
        e = data[f"{car}_obs_y_hat"][run] - truth[key][idx][run]
        assert np.max(np.abs(e)) < 0.01e-3                     # 10 µm (measured: 2.7 µm)
        assert np.nanmax(data[f"{car}_obs_T_dw"][run]) < 10.0   # … and the Δω innovation stayed χ²(1)-sized
    k_end = np.nonzero(run)[0][-1]
    assert abs(data["y_f"][k_end] - 2e-3) < 0.1e-3 and abs(data["y_r"][k_end] - 2e-3) < 0.1e-3   # the step at −1
