"""memo.by_config: a result per configuration (every field counts), a raise never kept;
the stability gate (preflight's, passed once per config) still refuses an unstable config
every time."""

import dataclasses

import pytest

from rig_runtime import analysis, config, memo
from rig_runtime.app import preflight


def test_kept_by_every_value_of_the_config_and_a_raise_is_not_kept():
    calls = []

    def f(cfg):
        calls.append(cfg)
        if cfg.plant.delta0 > 0.5:
            raise ValueError("no")
        return object()

    g = memo.by_config(f, maxsize=2)
    cfg = config.load(config.CONFIG_DIR / "sim.yaml")
    same = config.load(config.CONFIG_DIR / "sim.yaml")
    assert g(cfg) is g(same) and len(calls) == 1
    other = dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, delta0=cfg.plant.delta0 * (1 + 1e-15)))
    assert other.plant.delta0 != cfg.plant.delta0
    assert g(other) is not g(cfg) and len(calls) == 2
    bad = dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, delta0=0.6))
    for n in (3, 4):
        with pytest.raises(ValueError):
            g(bad)
        assert len(calls) == n
    g(cfg), g(other)            # both still kept (the raise took no place)
    assert len(calls) == 4


def test_the_gate_refuses_an_unstable_config_every_time_after_passing_a_stable_one():
    cfg = config.load(config.CONFIG_DIR / "sim.yaml")
    preflight.stability_gate(cfg)
    preflight.stability_gate(cfg)
    unstable = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, law="p", K_P=19000.0))
    for _ in range(2):
        with pytest.raises(analysis.UnstableLoopError, match="controller.K_P"):
            preflight.stability_gate(unstable)
