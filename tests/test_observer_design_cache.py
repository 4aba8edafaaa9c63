"""The observer design is memoised on its inputs (rig_runtime.app.observer_design): the same
inputs give the same (frozen) design without designing again, and every input is in the key —
changing any one of them gives another design."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from rig_runtime import config
from rig_runtime.app import observer_design as od


@pytest.fixture(scope="module")
def cfg():
    c = config.load("configs/sim.yaml")
    return c if c.observer is not None else dataclasses.replace(c, observer=config.Observer())


def test_same_inputs_same_design_without_designing_again(cfg):
    a = od.design(cfg, "rear")
    hits = od._design.cache_info().hits
    b = od.design(dataclasses.replace(cfg), "rear")       # an equal config, another object
    assert b is a
    assert od._design.cache_info().hits == hits + 1
    assert od._design.__wrapped__(*od.design_inputs(cfg, "rear")) == a       # what designing gives


def test_the_design_sees_only_its_key():
    """_design takes exactly the DesignInputs (no config object to read anything else from)."""
    params = inspect.signature(od._design.__wrapped__).parameters
    assert len(params) == len(od.DesignInputs._fields)
    assert all("RigConfig" not in str(p.annotation) for p in params.values())


def test_every_input_changes_the_design(cfg):
    base = od.design(cfg, "rear")
    variants = {
        "carrier": lambda c: (c, "front", None),
        "plant": lambda c: (dataclasses.replace(c, plant=dataclasses.replace(c.plant, omega0=c.plant.omega0 * 1.1)),
                            "rear", None),
        "geometry": lambda c: (dataclasses.replace(c, geometry=dataclasses.replace(c.geometry, d0=c.geometry.d0 * 1.2)),
                               "rear", None),
        "observer": lambda c: (c, "rear", dataclasses.replace(c.observer, q_y=c.observer.q_y * 3)),
        "h": lambda c: (dataclasses.replace(c, controller=dataclasses.replace(c.controller, h=c.controller.h / 2)),
                        "rear", None),
        "outage_max_s": lambda c: (dataclasses.replace(c, degraded=dataclasses.replace(c.degraded,
                                                                                     max_s=c.degraded.max_s / 10)),
                                   "rear", None),
        "window": lambda c: (dataclasses.replace(c, limits=dataclasses.replace(
            c.limits, innovation_window=c.limits.innovation_window + 1)), "rear", None),
        "ft_sensors": lambda c: (dataclasses.replace(c, devices=dataclasses.replace(
            c.devices, ft=dataclasses.replace(c.devices.ft, sensors=()))), "rear", None),
        "v": lambda c: (c, "rear", None, c.plant.v * 1.5),
    }
    assert set(variants) == set(od.DesignInputs._fields)
    for name, make in variants.items():
        c, carrier, ocfg, *v = make(cfg)
        inputs = od.design_inputs(c, carrier, ocfg, *v)
        assert getattr(inputs, name) != getattr(od.design_inputs(cfg, "rear"), name), name
        d = od.design(c, carrier, ocfg, *v)
        assert d != base, name
        assert d == od._design.__wrapped__(*inputs), name


def test_a_speed_table_is_made_of_memoised_designs():
    vcfg = config.load("configs/vehicle.yaml")
    assert vcfg.observer is not None and vcfg.controller.schedule is not None
    a = od.speed_table(vcfg, "rear")
    b = od.speed_table(vcfg, "rear")
    assert all(x is y for x, y in zip(a.table.forward + a.table.backward, b.table.forward + b.table.backward))
    assert a == b
