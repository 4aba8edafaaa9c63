"""Simulated miswiring (sim_backend/miswire.py): each option changes exactly the wire values
a rig wired that way would send, where the simulated rig makes them."""

from __future__ import annotations

import dataclasses

import pytest

from rig_runtime import config
from rig_runtime.errors import ConfigError
from sim_backend import miswire
from sim_backend.rig import SimulatedRig
from sim_backend.simconfig import sim_config


def _cfg(**mw):
    cfg = config.load(None)
    return dataclasses.replace(cfg, sim={**(cfg.sim or {}), "laser_noise_m": 0.0, "encoder_noise_rad_s": 0.0,
                                         **({"miswire": mw} if mw else {})})


@pytest.fixture(scope="module")
def shipped():
    with SimulatedRig(_cfg()) as sim:
        yield ({r: v.distance_m for r, v in sim.lasers.items()},
               {w: d.omega for w, d in sim.drives.drives.items()},
               {w: d.node_id for w, d in sim.drives.drives.items()})


def test_pure_laser_values():
    mw = miswire.Miswire(laser_sign=("b_r",), laser_swap=(("s_fl", "s_fr"),))
    out = miswire.laser_values(mw, {"b_r": 0.072, "s_fl": 0.031, "s_fr": 0.034}, {"b_r": 0.070, "s_fl": 0.0375, "s_fr": 0.0375})
    assert out == pytest.approx({"b_r": 0.068, "s_fl": 0.034, "s_fr": 0.031})


def test_laser_sign_mirrors_b_r_about_its_mid_range(shipped):
    lasers, _, _ = shipped
    with SimulatedRig(_cfg(laser_sign=["b_r"])) as sim:
        got = {r: v.distance_m for r, v in sim.lasers.items()}
        mid = sim.s0["b_r"]
    assert got["b_r"] == pytest.approx(2 * mid - lasers["b_r"])
    assert got["b_r"] != pytest.approx(lasers["b_r"])
    assert {r: v for r, v in got.items() if r != "b_r"} == {r: v for r, v in lasers.items() if r != "b_r"}


def test_laser_swap_exchanges_the_ports(shipped):
    lasers, _, _ = shipped
    with SimulatedRig(_cfg(laser_swap=[["s_fl", "s_fr"]])) as sim:
        got = {r: v.distance_m for r, v in sim.lasers.items()}
    assert lasers["s_fl"] != lasers["s_fr"]
    assert (got["s_fl"], got["s_fr"]) == (lasers["s_fr"], lasers["s_fl"])
    assert {r: got[r] for r in ("b_f", "b_r", "s_rl", "s_rr")} == {r: lasers[r] for r in ("b_f", "b_r", "s_rl", "s_rr")}


def test_encoder_sign_inverts_one_drives_speed(shipped):
    _, omegas, _ = shipped
    with SimulatedRig(_cfg(encoder_sign=["rl"])) as sim:
        got = {w: d.omega for w, d in sim.drives.drives.items()}
    assert omegas["rl"] > 0 and got["rl"] == -omegas["rl"]
    assert {w: got[w] for w in ("fl", "fr", "rr")} == {w: omegas[w] for w in ("fl", "fr", "rr")}


def test_current_sign_inverts_what_the_motor_sees():
    seen = []
    with SimulatedRig(_cfg(current_sign=["rl"])) as sim:
        sim.plant.step = lambda dt, du_f, du_r, *f: seen.append((du_f, du_r))
        sim.step(sim.h, [0.1, -0.1, 0.3, -0.3])
    assert seen == [(pytest.approx(0.2), pytest.approx(0.0))]      # rl pushed as -0.3, like rr


def test_node_swap_exchanges_the_drives_node_ids(shipped):
    _, _, nodes = shipped
    with SimulatedRig(_cfg(node_swap=[["rl", "rr"]])) as sim:
        got = {w: d.node_id for w, d in sim.drives.drives.items()}
        wired = {d.wheel: d.node_id for d in sim.wired_can().drives}
    assert (got["rl"], got["rr"]) == (nodes["rr"], nodes["rl"]) == (wired["rl"], wired["rr"])
    assert (got["fl"], got["fr"]) == (nodes["fl"], nodes["fr"])


@pytest.mark.parametrize("mw, key", [({"laser_sign": ["b_x"]}, "laser_sign"), ({"node_swap": [["rl", "rl"]]}, "node_swap"),
                                     ({"encoder_sign": ["front"]}, "encoder_sign")])
def test_a_bad_miswire_option_names_the_key(mw, key):
    with pytest.raises(ConfigError, match=key):
        sim_config(_cfg(**mw))
