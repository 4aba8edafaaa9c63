"""The hysteresis (9) and damping law (7) in the observer's model (docs/observer.md, "The
hysteresis and the damping in the model"): the estimate's Bouc-Wen map and damping are the
plant's, the step feeds them as a known input, and the design carries them per carrier."""

from __future__ import annotations

import dataclasses
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rig_runtime import config
from rig_runtime.app import observer_design as od
from rig_runtime.observer import JointCarrier, Observer, YawModel, _YawState, zmap
from sim_backend.plant import _Carrier


@pytest.fixture(scope="module")
def cfg():
    return config.load(config.resolve_config_path("sim.yaml"))


@pytest.fixture(scope="module")
def vcfg():
    return config.load(config.resolve_config_path("vehicle.yaml"))


@settings(max_examples=300, deadline=None)
@given(z=st.floats(-6e-3, 6e-3), dpsi=st.floats(-2e-2, 2e-2))
def test_the_estimates_bouc_wen_map_is_the_plants(cfg, z, dpsi):
    car = _Carrier(cfg.plant, None)
    bw = cfg.plant.bouc_wen
    assert zmap(z, dpsi, bw.A, bw.beta, bw.gamma) == pytest.approx(car.zmap(z, dpsi), rel=1e-12, abs=1e-18)


def test_the_estimates_damping_is_the_plants_for_the_same_currents(cfg):
    """D of (7) from the held current's filter residual, as the plant computes it (at the
    period's middle: the plant averages D over the period, the estimate takes its midpoint)."""
    d = od.design(cfg, "rear")
    m = d.yaw
    car = _Carrier(cfg.plant, None)
    ys = _YawState()
    ys.start(0.0, 0.0)
    ef = math.exp(-cfg.controller.h / car.tau)
    half = math.exp(-0.5 * cfg.controller.h / car.tau)
    currents = [0.0, 1.0, 1.0, 1.0] + [1.0] * 100 + [1.0 + 1e-7 * k for k in range(50)]
    decays = []
    for u in currents:
        _, decay = ys.inputs(m, 0.0, u)
        decays.append(decay)
        # the plant's D at mid-period: its residual after the input change, decayed half a period
        r = car.e + (u - car.du)
        car.du, car.e = u, r * ef
        car_e_mid = r * half
        saved = car.e
        car.e = car_e_mid
        D = car.damping()
        car.e = saved
        assert decay == pytest.approx(math.exp(-2.0 * m.w0 * (D - m.D0) * m.h), rel=1e-12)
    assert decays[1] == 1.0                                       # a step in u: D = D_min, the model's
    assert min(decays) < 1e-3                                     # held long enough: D near D_max


def test_the_step_feeds_the_hysteresis_as_an_equivalent_current(cfg):
    """One step with the model against the same step without it and the current
    u + (1 − a)/K (ψ̂ − ẑ): equal (closed-loop damping: D = D_min, no extra decay)."""
    d = od.design(cfg, "rear")
    bw, p = cfg.plant.bouc_wen, cfg.plant
    assert d.yaw.gain == pytest.approx((1 - bw.a) / p.K)
    on, off = Observer(d), Observer(dataclasses.replace(d, yaw=None))
    for o in (on, off):
        o.step(1e-4, 2e-3, 0.0, 0.3, 0.0, True)
    on._ys.z = 1e-3                                               # ψ̂ − ẑ = 1 mrad
    on._ys.e = 1.0                                                # the input is moving: D = D_min
    on.step(1e-4, 2.1e-3, 0.01, 0.3, 0.0, True)
    off.step(1e-4, 2.1e-3, 0.01, 0.3 + d.yaw.gain * 1e-3, 0.0, True)
    # the Δω innovation uses the real current (its input term), the prediction the equivalent one
    gu = d.dw_row[2]
    assert on.nu_psi == pytest.approx(off.nu_psi, rel=1e-12)
    assert on.nu_dw == pytest.approx(off.nu_dw + gu * d.yaw.gain * 1e-3, rel=1e-9)
    # ẑ follows ψ̂ by the map, at the next prediction (over ψ̂'s change in the step before it)
    psi1 = on.psi
    on.step(1e-4, 2.1e-3, 0.01, 0.3, 0.0, True)
    assert on._ys.z == pytest.approx(zmap(1e-3, psi1 - 2e-3, bw.A, bw.beta, bw.gamma), rel=1e-12)


def test_off_or_without_hysteresis_the_model_is_linear(cfg):
    o = dataclasses.replace(cfg.observer, yaw_model=False)
    assert od.design(cfg, "rear", o).yaw is None
    plant = dataclasses.replace(cfg.plant, bouc_wen=None)
    m = od.yaw_model(plant, plant.D_min, cfg.controller.h, True)
    assert isinstance(m, YawModel) and m.gain == 0.0              # the damping law stays


def test_the_joint_filter_carries_each_carriers_own_model(vcfg):
    j = od.designs(vcfg)["front"]
    assert isinstance(j, JointCarrier)
    f, r = j.joint.front.yaw, j.joint.rear.yaw
    pf, pr = vcfg.plant.carrier("front"), vcfg.plant.carrier("rear")
    assert f.gain == pytest.approx((1 - pf.bouc_wen.a) / pf.K)
    assert r.gain == pytest.approx((1 - pr.bouc_wen.a) / pr.K)
    assert (f.w0, f.D0, r.w0, r.D0) == (pf.omega0, pf.D_min, pr.omega0, pr.D_min)


def test_the_measurement_jitter_does_not_move_the_bouc_wen_state(cfg):
    """ψ̂ jittering by less than the dead band leaves ẑ where it is (the unloading branch would
    ratchet it towards 0); a motion beyond it moves ẑ by the map over the whole motion."""
    m = od.design(cfg, "rear").yaw
    assert m.dead > 0.0
    ys = _YawState()
    ys.start(4e-3, 0.0)
    psi = 4e-3
    for k in range(200):                          # each prediction's ψ̂: ẑ follows its change first
        psi += (0.9 if k % 2 == 0 else -0.9) * m.dead
        ys.inputs(m, psi, 0.0)
    assert ys.z == 4e-3
    ys.inputs(m, psi - 0.9 * m.dead, 0.0)         # the accumulated −0.9 dead stays below it (net −0.9: no move)
    ys.inputs(m, psi - 1.1 * m.dead, 0.0)         # past it: the map over the accumulated −1.1 dead
    assert ys.z == pytest.approx(zmap(4e-3, -1.1 * m.dead, m.A, m.beta, m.gamma), rel=1e-9)
    assert ys.acc == 0.0
