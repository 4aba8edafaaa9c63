"""The coupled loop of the vehicle (rig_runtime/coupled.py) and the stability gate over the
speed range in both directions: the paper's set-up is unchanged, the physics of (2a)/(2b),
the schedule law, and the refusals of `rig check` / `rig dry-run` / `rig ctl set`."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.linalg import expm as scipy_expm

from rig_runtime import analysis, config, coupled, tuning
from rig_runtime.gains import TuningError
from tests.vehicle_configs import write_vehicle

from .conftest import ROOT


@pytest.fixture(scope="module")
def veh_path(tmp_path_factory):
    return write_vehicle(tmp_path_factory.mktemp("veh"))


@pytest.fixture(scope="module")
def veh(veh_path):
    return config.load(veh_path)


def _rig(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "rig_runtime", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


# ------------------------------------------------------------------ the paper's set-up is unchanged
@pytest.mark.parametrize("which", ["D_min", "D_max"])
def test_front_lifted_is_todays_sampled_loop(cfg, which):
    """Front lifted, fixed gains: the coupled builder gives the eigenvalues of
    analysis.sampled_closed_loop (plant (10), Tustin PI-PD) — to the ZOH's precision."""
    D = getattr(cfg.plant, which)
    h = cfg.controller.h
    want = np.sort_complex(analysis.sampled_closed_loop(cfg, D))
    got = np.sort_complex(analysis._continuous(np.linalg.eigvals(coupled.sampled_matrix(cfg, cfg.plant.v, {"rear": D})), h))
    assert coupled.layout(cfg).carriers == ("rear",) and not coupled.applies(cfg)
    assert len(got) == len(want)
    slow = np.abs(want) < 100            # poles near z = 0 (ln z / h of a tiny z) carry the ZOH's rounding
    assert np.max(np.abs(got[slow] - want[slow])) < 1e-9
    assert np.max(np.abs(got - want) / np.abs(want)) < 1e-6


def test_default_gate_and_tune_json_unchanged(cfg):
    assert analysis.sampled_instability(cfg) is None
    out = json.loads(_rig("tune", "--json").stdout)
    assert "coupled" not in out and "coupled_sampled" not in out
    assert out["closed_loop"]["eigenvalues"] == analysis.pairs(analysis.tune(cfg).closed_loop)


def test_expm_agrees_with_scipy(veh):
    lay = coupled.layout(veh)
    for D in coupled.all_damping_cases(veh, lay.carriers):
        A, B = coupled.plant_matrices(veh, -1.5, D, lay)
        M = np.block([[A, B], [np.zeros((2, 8))]]) * veh.controller.h
        assert np.max(np.abs(coupled.expm(M) - scipy_expm(M))) < 1e-12


# ------------------------------------------------------------------ physics of (2a)/(2b)
@pytest.mark.parametrize("v", [1.0, -0.7])
def test_lateral_pair_is_a_jordan_block_at_zero(veh, v):
    """Both carriers in contact, equal carriers: the lateral block [[a, −a], [a, −a]] has a
    double eigenvalue 0 with one eigenvector (ψ_m integrates), not one stable, one unstable pole."""
    lay = coupled.layout(veh)
    A, _ = coupled.plant_matrices(veh, v, coupled.d_min(veh, lay.carriers), lay)
    L = A[:2, :2]
    a = veh.plant.c_y * v / (2 * veh.plant.l0)
    assert L == pytest.approx(np.array([[a, -a], [a, -a]]))
    assert np.allclose(np.linalg.eigvals(L), 0) and not np.allclose(L, 0) and np.allclose(L @ L, 0)
    # y_r held at 0: the front is unstable for v > 0, stable for v < 0 (Sec. 4.1.1)
    assert np.sign(L[0, 0]) == np.sign(v)


def test_schedule_keeps_the_loop_over_the_range(veh):
    """g = v_d/v: with equal carriers the continuous eigenvalues are the same at every speed and
    both signs (the loop gain c̄_y v g K is c̄_y v_d K), the held band is reported, not analysed."""
    r = coupled.analyse(veh)
    vs = [p.v for p in r.points]
    assert min(vs) == -1.5 and max(vs) == 1.5 and 1.0 in vs and -1.0 in vs and 0.2 in vs and -0.2 in vs
    assert all(abs(v) >= 0.2 for v in vs) and r.band == (-0.2, 0.2)
    for side in ([v for v in vs if v < 0], [v for v in vs if v > 0]):
        assert np.max(np.diff(side)) <= coupled.GRID_STEP + 1e-9
    ref = np.sort_complex(r.points[0].eigenvalues)
    for p in r.points:
        assert p.stable and p.sampled_stable
        assert p.g == pytest.approx(1.0 / p.v)
        assert np.sort_complex(p.eigenvalues) == pytest.approx(ref, abs=1e-6)


def test_without_schedule_negative_speed_is_positive_feedback(cfg):
    """The paper's fixed gains at v = −1 (front lifted): the outer loop's sign flips, the gate refuses."""
    neg = dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, v=-1.0))
    bad = analysis.sampled_instability(neg)
    assert bad is not None and bad.v == -1.0 and abs(bad.z) > 1
    with pytest.raises(analysis.UnstableLoopError, match="plant \\(10\\) with D = "):
        analysis.stability_gate(neg)


def test_uncontrolled_leading_carrier_is_refused(veh):
    """The front in contact but not controlled (Δu_f = 0): the rear cannot hold the leading
    front, whose own lateral pole is unstable at v > 0."""
    rear_only = dataclasses.replace(veh, controlled=("rear",))
    assert coupled.layout(rear_only).controlled == ("rear",)
    bad = analysis.sampled_instability(rear_only)
    assert bad is not None and bad.v > 0


def test_continuous_and_sampled_agree_at_small_h(veh):
    """ln(z)/h of the sampled loop tends to the continuous loop's eigenvalues (slow poles)."""
    fine = dataclasses.replace(veh, controller=dataclasses.replace(veh.controller, h=1e-4))
    lay = coupled.layout(fine)
    D = coupled.d_min(fine, lay.carriers)
    s = np.linalg.eigvals(coupled.continuous_matrix(fine, -1.0, D, lay))
    z = np.linalg.eigvals(coupled.sampled_matrix(fine, -1.0, D, lay))
    zs = np.log(z[np.abs(z) > 1e-6].astype(complex)) / 1e-4
    slow = np.sort(s.real[s.real > -10])
    assert np.sort(zs.real[zs.real > -10]) == pytest.approx(slow, rel=0.01)


# ------------------------------------------------------------------ the gate, both directions
@pytest.fixture(scope="module")
def asym_path(tmp_path_factory):
    """Stable at v = +1, unstable at v = −1: the rear's own l0 (ESTIMATE-free: a test plant)
    makes its lateral pole as the leading carrier (v < 0) too fast for the gains."""
    return write_vehicle(tmp_path_factory.mktemp("asym"), plant={"rear": {"l0": 0.15}})


def test_asymmetric_config_is_stable_at_plus_one_only(asym_path):
    c = config.load(asym_path)
    plus = coupled.at_speed(c, 1.0)
    minus = coupled.at_speed(c, -1.0)
    assert plus.sampled_stable and not minus.sampled_stable
    bad = analysis.sampled_instability(c)
    assert bad is not None and bad.v < 0


@pytest.mark.parametrize("cmd", ["check", "dry-run"])
def test_check_and_dry_run_refuse_unstable_at_minus_one(asym_path, tmp_path, cmd):
    log = tmp_path / "never.h5"
    r = _rig(cmd, "--config", str(asym_path), "--log", str(log))
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.count("\n") == 1 and "coupled loop at v = -" in r.stderr and "unstable" not in r.stdout
    assert r.stdout == "" and not log.exists()          # nothing started


def test_check_accepts_the_vehicle_and_names_what_it_covered(veh_path, tmp_path):
    r = _rig("check", "--config", str(veh_path), "--log", str(tmp_path / "x.h5"))
    assert r.returncode == 0, r.stderr
    assert "coupled" in r.stdout and "both directions" in r.stdout and "held for |v| < 0.2" in r.stdout


def test_ctl_set_is_judged_over_the_range(tmp_path):
    """Rear l0 0.2 m: the configured gains are stable over ±1.5 m/s; K_P_y 3 (within the
    shipped bounds) is stable at +1 but not at some negative speed: refused, naming it."""
    c = config.load(write_vehicle(tmp_path, plant={"rear": {"l0": 0.2}}))
    assert analysis.sampled_instability(c) is None
    assert tuning.check(c, "K_P_y", 6.0).new == 6.0
    low = tuning.with_gains(c, {"K_P_y": 3.0})
    assert coupled.at_speed(low, 1.0).sampled_stable and coupled.instability(low).v < 0
    with pytest.raises(TuningError, match=r"K_P_y = 3 would make the sampled closed loop unstable \(coupled loop at "
                                          r"v = -[0-9.]+ m/s \(D_front = .*D_rear = "):
        tuning.check(c, "K_P_y", 3.0)


def test_the_gates_damping_cases(cfg, veh):
    """The paper's set-up: D_max gated where the lateral dynamics are stable open loop (v > 0:
    unchanged). A vehicle config: every D_min/D_max combination is gated (none left ungated)."""
    P = cfg.plant
    assert coupled.damping_cases(cfg, 1.0, coupled.layout(cfg)) == [{"rear": P.D_min}, {"rear": P.D_max}]
    assert coupled.damping_cases(cfg, -1.0, coupled.layout(cfg)) == [{"rear": P.D_min}]
    for v in (1.0, -1.0):
        cases = coupled.damping_cases(veh, v, coupled.layout(veh))
        assert cases == coupled.all_damping_cases(veh, ("front", "rear")) and len(cases) == 4
    p = coupled.at_speed(veh, 1.0)
    assert p.ungated_radius is None and p.sampled_stable


def test_without_the_damping_schedule_the_vehicle_is_refused(veh):
    """The test vehicle's PI-PD without D_sched: unstable with a leading carrier at D_max (the
    combination the gate now judges); with it (D_sched 2) stable at every combination."""
    from rig_runtime import gains
    plain = gains.with_gains(veh, {})
    plain = dataclasses.replace(plain, controller=dataclasses.replace(
        plain.controller, pipd=dataclasses.replace(plain.controller.pipd, D_sched=0.0)))
    bad = coupled.instability(plain)
    assert bad is not None and sorted(bad.D.values())[-1] == veh.plant.D_max
    assert coupled.instability(veh) is None


# ------------------------------------------------------------------ the scenario against the config
def _scenario(tmp_path, text):
    p = tmp_path / "s.yaml"
    p.write_text("name: s\nduration_s: 2\n" + text)
    return p


@pytest.mark.parametrize("text, key", [
    ("speed: [{t: 0, v: 1.0}, {t: 1, v: -1.8}]\n", "speed[1].v"),          # outside v_range
    ("speed: [{t: 0, v: 2.5}]\n", "speed[0].v"),                             # beyond v_max
])
def test_speed_profile_outside_the_range_is_refused(veh_path, tmp_path, text, key):
    r = _rig("check", "--config", str(veh_path), "--scenario", str(_scenario(tmp_path, text)))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and key in r.stderr, r.stderr


def test_open_loop_experiment_may_run_at_any_speed_within_v_max(tmp_path):
    """An identification experiment (open loop) at v = −1 on the paper's config: its input does
    not depend on the gains, only the hardware's v_max applies."""
    ol = "open_loop: {carrier: rear, steps: [[0, 0.0], [1, 0.5]]}\n"
    r = _rig("check", "--scenario", str(_scenario(tmp_path, ol + "speed: [{t: 0, v: -1.0}]\n")))
    assert r.returncode == 0, r.stderr
    r = _rig("check", "--scenario", str(_scenario(tmp_path, ol + "speed: [{t: 0, v: -2.5}]\n")))
    assert r.returncode == 2 and "speed[0].v" in r.stderr and "v_max" in r.stderr, r.stderr


def test_speed_profile_needs_a_schedule_and_references_controlled_carriers(tmp_path):
    r = _rig("check", "--scenario", str(_scenario(tmp_path, "speed: [{t: 0, v: 1.0}, {t: 1, v: 0.5}]\n")))
    assert r.returncode == 2 and "speed[1].v" in r.stderr and "plant.v" in r.stderr, r.stderr
    r = _rig("check", "--scenario", str(_scenario(tmp_path, "reference: {front: [{t: 0, y_mm: 1}]}\n")))
    assert r.returncode == 2 and "reference.front" in r.stderr and "controlled" in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1


# ------------------------------------------------------------------ rig tune on the vehicle
def test_tune_json_on_the_vehicle(veh_path):
    r = _rig("tune", "--json", "--config", str(veh_path))
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    vs = [p["v"] for p in d["coupled"]]
    assert vs == [p["v"] for p in d["coupled_sampled"]] and -1.0 in vs and 1.0 in vs
    for p, q in zip(d["coupled"], d["coupled_sampled"]):
        assert p["stable"] and q["stable"] and len(p["eigenvalues"]) == 10
        assert all(len(e) == 2 for e in p["eigenvalues"]) and 0 <= q["spectral_radius"] < 1
    assert d["coupled_setup"]["held_band"] == [-0.2, 0.2]
    text = _rig("tune", "--config", str(veh_path)).stdout
    assert "coupled loop of the vehicle" in text and "least-damped pole" in text and "held" in text


def test_step_response_of_the_decoupled_law_holds_the_other_carrier():
    """The linear sampled loop of configs/vehicle.yaml (law decoupled) from its description: a
    unit step on the front reaches 1 and the held rear stays within 10 % of it; the per-carrier
    PI-PD with the same cascade gains (law pipd) lets the rear move by a third of it or more."""
    vcfg = config.load(config.CONFIG_DIR / "vehicle.yaml")
    D = coupled.d_min(vcfg, ("front", "rear"))
    r = coupled.step_response(vcfg, 1.0, D, ("front",), 15.0)
    assert abs(r.y["front"][-1] - 1.0) < 0.02
    assert np.max(np.abs(r.y["rear"])) < 0.1
    assert np.max(np.abs(r.u["front"])) * 3e-3 < 3.0            # a 3 mm step under 3 A
    pipd = dataclasses.replace(vcfg, controller=dataclasses.replace(vcfg.controller, law="pipd"))
    assert np.max(np.abs(coupled.step_response(pipd, 1.0, D, ("front",), 15.0).y["rear"])) > 0.3


def test_every_damping_combination_is_reported_and_the_trailing_term_makes_it_stable():
    """rig tune's every-D report (coupled.SpeedResult.rightmost / every_damping_radius): the shipped
    vehicle set, its yaw loop scheduled on D̂ (D_sched), is stable at every combination over the
    range; without the schedule it is unstable with the leading carrier at D_max (docs/vehicle.md
    §3). Unscheduled gains with the trailing carrier following (K_t_y, found by
    benchmarks/vehicle_law_reach.py decoupled-t --radius-only) are stable at every combination, the
    same gains without it are not."""
    vcfg = config.load(config.CONFIG_DIR / "vehicle.yaml")
    assert vcfg.controller.decoupled.D_sched > 0
    assert all(q.every_damping_radius < 1.0 and q.rightmost.real < 0 for q in coupled.analyse(vcfg).points)
    plain = dataclasses.replace(vcfg, controller=dataclasses.replace(
        vcfg.controller, decoupled=dataclasses.replace(vcfg.controller.decoupled, D_sched=0.0)))
    p = coupled.at_speed(plain, 1.5)
    assert p.every_damping_radius > 1.0 and p.rightmost.real > 0
    assert p.rightmost_D == {"front": vcfg.plant.carrier("front").D_max, "rear": vcfg.plant.carrier("rear").D_min}
    g = dataclasses.replace(vcfg.controller.decoupled, K_P_y=0.405, K_I_y=0.00798, K_P_psi=29.05, K_D_psi=1.697,
                            b_y=0.169, K_x_y=2.3985, T_x_y=0.6777, K_I_psi=0.0, K_t_y=12.5886, D_sched=0.0)
    following = dataclasses.replace(vcfg, controller=dataclasses.replace(vcfg.controller, decoupled=g))
    res = coupled.analyse(following)
    assert all(q.every_damping_radius < 1.0 and q.rightmost.real < 0 for q in res.points)
    alone = dataclasses.replace(following, controller=dataclasses.replace(
        following.controller, decoupled=dataclasses.replace(g, K_t_y=0.0)))
    assert max(q.every_damping_radius for q in coupled.analyse(alone).points) > 1.0


def test_ctl_set_of_the_damping_schedule_is_judged_by_the_same_gate():
    """D_sched is a live gain of law decoupled like the others (rig ctl set, tuning.check): too
    little of the schedule leaves a leading carrier at D_max unstable — refused, naming it."""
    v = config.load(config.CONFIG_DIR / "vehicle.yaml")
    c = dataclasses.replace(v, controller=dataclasses.replace(v.controller, tuning={"D_sched": (0.01, 3.0)}))
    assert tuning.check(c, "D_sched", 2.5).new == 2.5
    with pytest.raises(TuningError, match=r"D_sched = 0.01 would make the sampled closed loop unstable .*D_front = "):
        tuning.check(c, "D_sched", 0.01)
