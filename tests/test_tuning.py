"""The one check of a live gain change: whitelist, bounds from config, stability gate."""

import dataclasses
import json

import pytest

from rig_runtime import analysis, config, schema, tuning
from rig_runtime.errors import ConfigError
from rig_runtime.gains import GainChange, TuningError


def with_bounds(cfg, **bounds):
    c = cfg.controller
    return dataclasses.replace(cfg, controller=dataclasses.replace(c, tuning={**c.tuning, **bounds}))


def test_within_bounds_is_accepted(cfg):
    ch = tuning.check(cfg, "K_P_y", 4.5)
    assert ch == GainChange("K_P_y", cfg.controller.pipd.K_P_y, 4.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        ch.new = 5.0
    # the old value is the gain in force, not the configured one
    assert tuning.check(cfg, "K_P_y", 2.0, {"K_P_y": 4.5}).old == 4.5


@pytest.mark.parametrize("value", [0.5, 6.01, 100.0])
def test_outside_bounds_is_refused(cfg, value):
    with pytest.raises(TuningError, match=r"K_P_y = .* is outside its bounds \[1, 6\] \(controller.tuning\)"):
        tuning.check(cfg, "K_P_y", value)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), "abc"])
def test_not_a_finite_number_is_refused(cfg, value):
    with pytest.raises(TuningError, match="K_I_y: value .* not a"):
        tuning.check(cfg, "K_I_y", value)


def test_a_destabilising_value_is_refused(cfg):
    # K_I_y = 40 alone, with wide bounds: the gate finds the sampled loop unstable
    wide = with_bounds(cfg, K_I_y=(1.0, 100.0))
    bad = tuning.with_gains(wide, {"K_I_y": 40.0})
    assert analysis.sampled_instability(bad) is not None
    with pytest.raises(TuningError, match=r"K_I_y = 40 would make the sampled closed loop unstable "
                                          r"\(plant \(10\) with D = .* has an eigenvalue at \+"):
        tuning.check(wide, "K_I_y", 40.0)


def test_a_destabilising_combination_within_the_shipped_bounds_is_refused(cfg):
    # each step within bounds; the last one with the gains then in force is unstable
    inforce = {}
    for name, v in (("K_P_y", 1.0), ("K_P_psi", 80.0)):
        inforce[name] = tuning.check(cfg, name, v, inforce).new
    assert analysis.sampled_instability(tuning.with_gains(cfg, {**inforce, "K_I_y": 18.0})) is not None
    with pytest.raises(TuningError, match="K_I_y = 18 would make the sampled closed loop unstable.*K_P_y 1, "
                                          "K_I_y 18, K_P_psi 80"):
        tuning.check(cfg, "K_I_y", 18.0, inforce)
    tuning.check(cfg, "K_I_y", 18.0)            # with the configured gains it is fine


@pytest.mark.parametrize("name", ["u_max", "y_max", "psi_max", "du_max", "psi_rate_max", "stop_ramp_s",
                                  "overrun_burst", "stale_periods", "psi_ref_max"])
def test_a_limit_is_refused(cfg, name):
    with pytest.raises(TuningError, match=f"^{name} is a limit: limits cannot be changed while running"):
        tuning.check(cfg, name, 1.0)


@pytest.mark.parametrize("name", ["K_p_y", "h", "", "law"])
def test_an_unknown_name_is_refused(cfg, name):
    with pytest.raises(TuningError, match=f"^unknown name {name!r}: tunable gains of law pipd are K_P_y, K_I_y"):
        tuning.check(cfg, name, 1.0)


def test_gain_of_the_other_law_and_gain_without_bounds(cfg):
    with pytest.raises(TuningError, match=r"K_P is not a gain of the control law in use \(pipd"):
        tuning.check(cfg, "K_P", 600.0)
    c = cfg.controller
    nob = dataclasses.replace(cfg, controller=dataclasses.replace(
        c, tuning={k: v for k, v in c.tuning.items() if k != "K_D_psi"}))
    with pytest.raises(TuningError, match="K_D_psi has no bounds in the config .*not tunable"):
        tuning.check(nob, "K_D_psi", 5.0)


def test_p_law(cfg):
    p = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, law="p"))
    assert tuning.check(p, "K_P", 1500.0) == GainChange("K_P", 500.0, 1500.0)
    with pytest.raises(TuningError, match="K_P_y is not a gain of the control law in use"):
        tuning.check(p, "K_P_y", 4.0)
    wide = with_bounds(p, K_P=(100.0, 1e5))
    with pytest.raises(TuningError, match="K_P = 30000 would make the sampled closed loop unstable"):
        tuning.check(wide, "K_P", 3e4)


def test_shipped_bounds_are_stable_one_gain_at_a_time(cfg):
    for name in config.PIPD_GAINS:
        lo, hi = cfg.controller.tuning[name]
        for v in (lo, hi):
            assert tuning.check(cfg, name, v).new == v


def _controller_yaml(tmp_path, tuning_text):
    src = (config.CONFIG_DIR / "controller.yaml").read_text()
    head, _, _ = src.partition("  tuning:\n")
    ctl = tmp_path / "controller.yaml"
    ctl.write_text(head + tuning_text + "limits:" + src.split("\nlimits:", 1)[1])
    for f in ("hardware.yaml", "plant.yaml", "geometry.yaml"):
        (tmp_path / f).write_text((config.CONFIG_DIR / f).read_text())
    top = tmp_path / "top.yaml"
    top.write_text("include: [hardware.yaml, plant.yaml, controller.yaml, geometry.yaml]\n")
    return top


@pytest.mark.parametrize("text, key, expected", [
    ("  tuning:\n    K_P_y: [6.0, 1.0]\n", "controller.tuning.K_P_y", "bounds [lo, hi] with 0 < lo <= hi"),
    ("  tuning:\n    K_P_y: [0.0, 4.0]\n", "controller.tuning.K_P_y", "bounds [lo, hi] with 0 < lo <= hi"),
    ("  tuning:\n    u_max: [1.0, 6.0]\n", "controller.tuning.u_max", "a tunable gain (one of K_P_y"),
    ("  tuning:\n    K_P_y: [1.0]\n", "controller.tuning.K_P_y", "a list of 2 items"),
    ("  tuning:\n    K_P_y: [1.0, a]\n", "controller.tuning.K_P_y[1]", "a number"),
])
def test_bad_bounds_are_refused_at_load(tmp_path, text, key, expected):
    with pytest.raises(ConfigError) as e:
        config.load(_controller_yaml(tmp_path, text))
    msg = str(e.value)
    assert "\n" not in msg and key in msg and expected in msg and "controller.yaml" in msg


def test_config_round_trips_through_its_json(cfg):
    assert tuning.config_from_json(json.dumps(schema.to_dict(cfg))) == cfg
    with pytest.raises(ConfigError, match="JSON text"):
        tuning.config_from_json("{not json")
