"""The running gear's filter (docs/observer.md, "One filter for the running gear"): both
carriers and their coupling in one state, each lateral laser a measurement of its own (one
laser measures a combination of y_f and y_r), a precomputed gain set per lost laser; the
lanes of a vehicle share it. Unit tests; the lockstep runs are in tests/test_observer_vehicle.py."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from rig_runtime import config
from rig_runtime.app import observer_design as od
from rig_runtime.geometry import ideal_readings, pose_from_carriers
from rig_runtime.lanes import make_lanes
from rig_runtime.observer import JOINT_SETS, CarrierView, JointCarrier, JointObserver


@pytest.fixture(scope="module")
def vcfg():
    return config.load(config.resolve_config_path("vehicle.yaml"))


@pytest.fixture(scope="module")
def joint(vcfg):
    """The linear filter (the hysteresis and damping law left out: tests/test_observer_yaw_model.py)."""
    return od.joint_design(vcfg, dataclasses.replace(vcfg.observer, yaw_model=False), v=1.0)


def test_the_vehicle_gets_one_filter_for_both_carriers(vcfg):
    ds = od.designs(vcfg)
    assert set(ds) == {"front", "rear"} and all(isinstance(d, JointCarrier) for d in ds.values())
    assert ds["front"].joint is ds["rear"].joint and ds["front"].joint.table is not None
    lanes = make_lanes(vcfg, lambda t: 0.0, observers=ds)
    views = [l.observer for l in lanes]
    assert all(isinstance(v, CarrierView) for v in views) and views[0].joint is views[1].joint
    assert lanes[0].lateral_lasers == ("b_f", "b_r") and lanes[1].lateral_lasers == ("b_r", "b_f")


def test_the_paper_set_up_keeps_its_per_carrier_design():
    cfg = config.load()
    (d,) = od.designs(cfg).values()
    assert not isinstance(d, JointCarrier) and d == od.design(cfg, "rear")


def test_the_joint_model_is_both_carriers_models_coupled(vcfg):
    pf, pr = vcfg.plant.carrier("front"), vcfg.plant.carrier("rear")
    A, Bc = od.joint_model(pf, pr, pf.D_min, pr.D_min, 1.0)
    Af, Bf = od.continuous_model(vcfg, "front", pf.D_min, 1.0)
    Ar, Br = od.continuous_model(vcfg, "rear", pr.D_min, 1.0)
    assert np.array_equal(A[:3, :3], Af) and np.array_equal(A[3:, 3:], Ar)
    assert np.array_equal(A[:3, 3], Bf[:, 1]) and np.array_equal(A[3:, 0], Br[:, 1])   # the coupling
    assert np.array_equal(Bc[:3, 0], Bf[:, 0]) and np.array_equal(Bc[3:, 1], Br[:, 0])
    assert not Bc[:3, 1].any() and not Bc[3:, 0].any()


def test_one_laser_measures_a_combination_of_both_carriers(vcfg):
    g = vcfg.geometry
    (ff, fr), (rf, rr) = od.laser_rows(g)
    y_f, y_r = 1.3e-3, -0.4e-3
    r = ideal_readings(pose_from_carriers(y_f, y_r, 0.0, 0.0, g), g)
    # the small-angle rows: 6 nm off at 1.7 mm between the carriers (the lasers' noise: 1 µm)
    assert r.b_f - g.b0 == pytest.approx(ff * y_f + fr * y_r, abs=1e-8)
    assert r.b_r - g.b0 == pytest.approx(rf * y_f + rr * y_r, abs=1e-8)
    assert fr != 0.0 and rf != 0.0


def test_every_gain_set_is_a_stable_filter_and_ignores_the_lost_laser(joint, vcfg):
    Ad = np.array(joint.A).reshape(6, 6)
    pf, pr = vcfg.plant.carrier("front"), vcfg.plant.carrier("rear")
    C = od._joint_C(vcfg.geometry, od.dw_row_at(pf, 1.0), od.dw_row_at(pr, 1.0))
    for used, K in zip(JOINT_SETS, joint.K):
        K = np.array(K).reshape(6, 6)
        unused = [m for m in range(6) if m not in used]
        assert not K[:, unused].any()
        assert max(abs(np.linalg.eigvals((np.eye(6) - K @ C) @ Ad))) < 1.0


@pytest.mark.parametrize("v", [1.0, -1.0])
def test_a_single_lost_laser_keeps_sigma_far_below_the_bound(vcfg, v):
    """The finding that keeps the vehicle running: with one lateral laser lost the joint
    filter's σ_y levels off at a few µm (both carriers, both directions) — the per-carrier
    filters' leading carrier, which drops both lasers, levels off 5× higher (near the bound
    with q_psi_acc 0.2; it passed 0.1 mm within 0.1 s at 0.5, before the hysteresis was in the model)."""
    j = od.joint_design(vcfg, v=v)
    bound = vcfg.degraded.sigma_y_max
    worst = 0.0
    for s in (1, 2):
        for tab in j.sigma_y[s]:
            assert max(tab) < 0.2 * bound
            worst = max(worst, max(tab))
    per_carrier = [od.design(vcfg, c, v=v).sigma_y_outage for c in ("front", "rear")]
    assert max(max(t) for t in per_carrier) > 5 * worst


def test_the_step_estimates_both_carriers_from_one_laser(joint, vcfg):
    """A still vehicle at (y_f, y_r): with b_r lost the filter still converges on both from b_f,
    the yaw lasers and Δω; the views carry each carrier's values."""
    g = vcfg.geometry
    o = JointObserver(joint)
    (ff, fr), (rf, rr) = joint.laser_rows
    y_f, y_r = 0.0, 0.0
    for k in range(4000):
        o.step(g.b0 + ff * y_f + fr * y_r, g.b0 + rf * y_f + rr * y_r, True, k < 100, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert abs(o.front.y) < 1e-6 and abs(o.rear.y) < 1e-6
    assert o.set == 1 and o.front.lat_used == 1.0 and o.rear.lat_used == 0.0 and math.isnan(o.rear.nu_lat)
    assert o.front.sigma_y == joint.sigma_y[1][0][-1] and o.front.outage == 3900


def test_select_swaps_the_design_and_the_views_parts(vcfg):
    j = od.joint_speed_table(vcfg)
    o = JointObserver(j)
    o.select(-0.5)
    assert o.d.v < 0 and o.front.d is o.d.front and o.rear.d is o.d.rear
    kept = o.d
    o.select(0.0)
    o.select(math.nan)
    assert o.d is kept


def test_select_keeps_the_nearest_grid_speed_along_a_speed_profile(vcfg):
    """Select skips its computation while v stays inside the current grid point's interval:
    along a speed profile (reversals through 0, the grid's ends, its boundaries ± rounding) it
    picks the design a fresh observer picks for the same v."""
    j = od.joint_speed_table(vcfg)
    t = j.table
    o = JointObserver(j)
    rng = np.random.default_rng(5)
    bounds = [t.v_ref * t.ratio ** (k + 0.5) for k in range(t.k_lo - 1, t.k_hi + 1)]
    speeds = list(np.linspace(-2.0, 2.0, 801)) + [s * b * (1 + e) for b in bounds for s in (1, -1)
                                                   for e in (-1e-12, 0.0, 1e-12)]
    speeds += list(rng.uniform(-1.6, 1.6, 500)) + [0.0, math.nan, 1e-4, -1e-4, 5.0, -5.0]
    fresh = JointObserver(j)
    for v in speeds + speeds[::-1]:
        o.select(float(v))
        fresh.d, fresh._lo, fresh._hi = None, 0.0, 0.0     # nothing kept: the design for this v alone
        fresh.select(float(v))
        if fresh.d is not None:
            assert o.d is fresh.d, v


@pytest.mark.parametrize("j", range(6))
def test_the_bias_test_names_the_biased_measurement(joint, vcfg, j):
    """A constant bias on one measurement of a still vehicle: once the window is on it, the
    bias test's statistic is largest for that measurement — except that a lateral laser's
    bias cannot be told from the other lateral laser's (their signatures are 99.6 % alike: both
    are isolated on a lateral finding); without a bias it stays near 0."""
    g = vcfg.geometry
    bias = [50e-6, 50e-6, 100e-6, 100e-6, 20e-3, 20e-3]     # each well past its test's 30
    o, ref = JointObserver(joint), JointObserver(joint)
    for k in range(3 * joint.window):
        meas = [g.b0, g.b0, 0.0, 0.0, 0.0, 0.0]
        ref.step(*meas[:2], True, True, *meas[2:], 0.0, 0.0)
        if k > joint.window // 2:
            meas[j] += bias[j]
        o.step(*meas[:2], True, True, *meas[2:], 0.0, 0.0)
    assert max(ref.T) < 0.01              # (the model's offsets: a still vehicle at 0 is nearly its rest)
    best = max(range(6), key=lambda m: o.T[m])
    assert best == j or {best, j} == {0, 1}
    assert o.T[j] > 30.0


def test_the_views_publish_the_carriers_statistics(joint):
    o = JointObserver(joint)
    for _ in range(joint.window + 2):
        o.step(joint.b0 + 1e-6, joint.b0, True, True, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    f, r = o.front, o.rear
    assert f.window_full and r.window_full
    assert (f.T_lat, r.T_lat, f.T_psi, r.T_psi, f.T_dw, r.T_dw) == tuple(o.T)
    assert f.log_values()[0] == o.x[0] and r.log_values()[0] == o.x[3]


@pytest.mark.parametrize("v", [1.0, -0.3, 0.093])
def test_the_doubling_riccati_solution_is_scipys(vcfg, v):
    """The joint design solves its Riccati equations by doubling (faster); the same gains and
    covariances as scipy's solver, for every measurement set."""
    pf, pr = vcfg.plant.carrier("front"), vcfg.plant.carrier("rear")
    o, g = vcfg.observer, vcfg.geometry
    Ac, Bc = od.joint_model(pf, pr, pf.D_min, pr.D_min, v)
    q = [o.q_y ** 2, 0.0, o.q_psi_acc ** 2]
    Ad, _, Qd = od.discretise(Ac, Bc, np.diag(q + q), vcfg.controller.h)
    C = od._joint_C(g, od.dw_row_at(pf, v), od.dw_row_at(pr, v))
    n = o.noise
    R = np.diag([n.lateral_laser_m ** 2] * 2 + [2 * n.yaw_laser_m ** 2 / g.d0 ** 2] * 2 + [2 * n.encoder_rad_s ** 2] * 2)
    for used in JOINT_SETS:
        i = list(used)
        K1, S1, P1 = od.steady_state(Ad, C[i], Qd, R[np.ix_(i, i)])
        K2, S2, P2 = od.steady_state_sda(Ad, C[i], Qd, R[np.ix_(i, i)])
        assert np.allclose(K2, K1, rtol=1e-8, atol=1e-10 * np.max(np.abs(K1)))
        assert np.allclose(P2, P1, rtol=1e-8, atol=1e-10 * np.max(np.abs(P1)))


def test_both_carriers_finding_the_lasers_name_each_laser_once():
    """On the vehicle both carriers' lateral statistics cross together (b_f and b_r alike): the
    second finding isolates the same lasers in the other order; the interval names each once."""
    from rig_runtime.safety.reconfig import Reconfiguration
    r = Reconfiguration("DEGRADED", {"b_f": ["front", "rear"], "b_r": ["front", "rear"]}, device_key="laser")
    r.isolate(1.0, ("b_f", "b_r"), "innovation", readmit=False)
    r.isolate(1.0, ("b_r", "b_f"), "innovation", readmit=False)
    assert [e["laser"] for e in r.log] == ["b_f/b_r", "b_f/b_r"]


@pytest.mark.parametrize("j", range(6))
def test_the_drift_test_names_the_drifting_measurement(joint, vcfg, j):
    """A ramp on one measurement of a still vehicle (a drifting sensor): once the bias test
    passes its gate the published statistics are the drift test's, the largest is that
    measurement's (or the other lateral laser's), and the views name it as the lead."""
    from rig_runtime.observer import DRIFT_GATE, JOINT_LEAD
    g = vcfg.geometry
    rate = [0.5e-6, 0.5e-6, 1e-6, 1e-6, 0.2e-3, 0.2e-3]     # per cycle
    o = JointObserver(joint)
    k0 = joint.window
    for k in range(3 * joint.window):
        meas = [g.b0, g.b0, 0.0, 0.0, 0.0, 0.0]
        if k > k0:
            meas[j] += rate[j] * (k - k0)
        o.step(*meas[:2], True, True, *meas[2:], 0.0, 0.0)
    assert max(o.T) > DRIFT_GATE
    best = max(range(6), key=lambda m: o.T[m])
    assert best == j or {best, j} == {0, 1}
    assert o.lead == best
    car, kind = JOINT_LEAD[best]
    assert o.view(car).lead == kind and o.view("rear" if car == "front" else "front").lead == ""


def test_the_time_weighted_window_sums_are_the_windows(joint, vcfg):
    """The drift test's Σ k ν_k (k = 0 for the oldest sample): summed over the window when the
    bias test's gate opens, then kept by a running update while the drift test runs — equal to
    the sum over the window's innovations as stored; below the gate it is not kept at all."""
    g = vcfg.geometry
    o = JointObserver(joint)
    rng = np.random.default_rng(3)
    k0, kept = joint.window + 20, []
    for k in range(joint.window + 157):
        o.step(g.b0 + 1e-6 * rng.standard_normal(), g.b0 + 1e-6 * rng.standard_normal(), True, True,
               1e-5 * rng.standard_normal() + (2e-6 * (k - k0) if k > k0 else 0.0),   # ψ_f drifts
               1e-5 * rng.standard_normal(), 0.003 * rng.standard_normal(),
               0.003 * rng.standard_normal(), 0.0, 0.0)
        if k == k0:
            assert o._n == joint.window and not o._kept     # nothing found: the drift test has nothing to do
        kept.append(o._kept)
    assert all(kept[-20:])                        # the gate opened 20 cycles ago or more, the sums kept since
    N, i = joint.window, o._i                     # o._i: the oldest sample's slot
    for m in range(6):
        ring = o._raw[m]
        ordered = ring[i:] + ring[:i]
        assert o._rsum1[m] == pytest.approx(sum(k * v for k, v in enumerate(ordered)), rel=1e-9, abs=1e-15)
        assert o._rsum[m] == pytest.approx(sum(ordered), rel=1e-9, abs=1e-15)
