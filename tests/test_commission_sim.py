"""The simulator's side of ``rig commission``: the free-spinning wheels of a lifted carrier
(sim_backend/lifted_wheels.py) where the simulated rig forms the wheel speeds, the simulated
operator's set-ups and hands (sim_backend/hands.py), and the crossed-encoder miswiring."""

from __future__ import annotations

import dataclasses
import math

import pytest

from rig_runtime import config
from rig_runtime.geometry import ideal_readings, pose_from_carriers
from sim_backend import hands, miswire
from sim_backend.lifted_wheels import FRICTION_TIME_S, LiftedWheels
from sim_backend.rig import SimulatedRig


def _cfg(**sim):
    cfg = config.load(None)
    return dataclasses.replace(cfg, sim={**(cfg.sim or {}), "laser_noise_m": 0.0, "encoder_noise_rad_s": 0.0, **sim})


def _speeds(sim):
    sim.set_wheel_speeds()
    return {w: d.omega for w, d in sim.drives.drives.items()}


def test_a_lifted_wheel_spins_up_as_j_x_domega_dt_equals_k_tau_i():
    lw = LiftedWheels(J_x=0.01, k_tau=0.5)
    lw.lift("rl")
    for _ in range(40):                          # 0.2 s of 5 ms steps at 0.3 A
        lw.step(0.005, {"rl": 0.3})
    tau = FRICTION_TIME_S
    exact = 0.5 * 0.3 / 0.01 * tau * (1 - math.exp(-0.2 / tau))
    assert lw.omega["rl"] == pytest.approx(exact, rel=1e-12)
    assert lw.omega["rl"] == pytest.approx(3.0, rel=0.02)        # friction costs 1 % over the pulse
    lw.step(tau, {})                             # coasting: the viscous drag's time constant
    assert lw.omega["rl"] == pytest.approx(exact / math.e, rel=1e-12)
    lw.lower("rl")
    assert lw.omega == {}


def test_the_shipped_front_carrier_is_lifted_its_wheels_spin_freely_the_rear_rolls():
    with SimulatedRig(_cfg()) as sim:
        om = _speeds(sim)
        assert om["fl"] == om["fr"] == 0.0 and om["rl"] == pytest.approx(sim.cfg.plant.v / sim.cfg.plant.r0, rel=1e-3)
        for _ in range(40):
            sim.step(sim.h, [0.3, -0.3, 0.0, 0.0])
        om2 = _speeds(sim)
    assert om2["fl"] == pytest.approx(3.0, rel=0.02) and om2["fr"] == pytest.approx(-3.0, rel=0.02)
    assert om2["rl"] == pytest.approx(om["rl"], abs=1e-3)


def test_a_lifted_wheel_turns_with_its_motors_current_as_miswired():
    with SimulatedRig(_cfg(miswire={"current_sign": ["fl"]})) as sim:
        for _ in range(40):
            sim.step(sim.h, [0.3, -0.3, 0.0, 0.0])
        om = _speeds(sim)
    assert om["fl"] == pytest.approx(-3.0, rel=0.02) and om["fr"] == pytest.approx(-3.0, rel=0.02)


def test_the_simulated_operator_holds_the_carriers_lifted_for_the_lifted_sessions_only():
    with SimulatedRig(_cfg(operator="commission", operator_lifted_sessions=2)) as sim:
        rolling = sim.cfg.plant.v / sim.cfg.plant.r0
        assert _speeds(sim)["rl"] == 0.0                         # lifted from the start, at rest
        for n in range(2):
            sim.power_observed(True)
            assert _speeds(sim)["rl"] == 0.0, n
            sim.power_observed(False)
        om = _speeds(sim)                                        # two sessions ended: on the rollers
        assert om["rl"] == pytest.approx(rolling, rel=1e-3) and om["fl"] == 0.0      # the front stays lifted (set-up)
        assert sim.power_sessions == [2, 2]
    with SimulatedRig(_cfg(operator="commission", operator_lifted_sessions=0)) as sim:
        assert _speeds(sim)["rl"] == pytest.approx(rolling, rel=1e-3)
    with SimulatedRig(_cfg()) as sim:                            # no simulated operator: nothing lifted by hand
        assert _speeds(sim)["rl"] == pytest.approx(rolling, rel=1e-3)


def test_the_hands_push_the_rear_end_alone_once_a_round():
    geo = config.load(None).geometry
    pushes = [hands.offset(k * 0.005) for k in range(int(hands.PERIOD_S / 0.005))]
    alone = [o for o in pushes if o.dy_r > 1e-4 and o.dy_f == 0.0]
    together = [o for o in pushes if o.dy_f > 1e-4]
    assert alone and together and all(o.dy_r == o.dy_f for o in together)
    peak = max(alone, key=lambda o: o.dy_r)
    r = ideal_readings(pose_from_carriers(0.0, peak.dy_r, 0.0, 0.0, geo), geo, s0=0.0)
    r0 = ideal_readings(pose_from_carriers(0.0, 0.0, 0.0, 0.0, geo), geo, s0=0.0)
    assert r.b_r - r0.b_r > 1e-3 > abs(r.b_f - r0.b_f)            # b_r moves by far the most


def test_encoder_swap_exchanges_the_reported_speeds_only():
    mw = miswire.Miswire(encoder_swap=(("rl", "fl"),), encoder_sign=("rr",))
    assert miswire.wheel_speeds(mw, [1.0, 2.0, 3.0, 4.0]) == [3.0, 2.0, 1.0, -4.0]
    assert miswire.motor_currents(mw, [1.0, 2.0, 3.0, 4.0]) == [1.0, 2.0, 3.0, 4.0]
    with pytest.raises(Exception, match="encoder_swap"):
        miswire.Miswire(encoder_swap=(("rl", "rl"),))
