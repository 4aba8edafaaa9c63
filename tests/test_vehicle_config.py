"""The two-carrier configuration: per-carrier plant values and gains, the speed schedule, the
hardware's v_max, and scenarios with per-carrier references and a speed profile."""

import textwrap

import pytest

from rig_runtime import config
from rig_runtime.errors import ConfigError
from rig_runtime.scenario import load_scenario



def _with_sections(tmp_path, plant_extra: str = "", controller_extra: str = ""):
    """sim.yaml with plant/controller sections extended (written out in full)."""
    import yaml
    sections = config.load_sections(config.CONFIG_DIR / "sim.yaml")
    data = {k: v for k, (v, f) in sections.items() if k != "hardware"}
    if plant_extra:
        data["plant"] = {**data["plant"], **yaml.safe_load(plant_extra)}
    if controller_extra:
        data["controller"] = {**data["controller"], **yaml.safe_load(controller_extra)}
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump({"include": [str(config.CONFIG_DIR / "hardware.yaml")], **data}))
    return p


def test_carrier_overrides_replace_only_their_keys(tmp_path):
    cfg = config.load(_with_sections(tmp_path, "front: {K: 0.008, l0: 0.3}"))
    f, r = cfg.plant.carrier("front"), cfg.plant.carrier("rear")
    assert (f.K, f.l0) == (0.008, 0.3)
    assert (r.K, r.l0) == (cfg.plant.K, cfg.plant.l0)
    assert f.omega0 == cfg.plant.omega0 and f.front is None and f.rear is None
    assert cfg.plant.per_carrier and not config.load().plant.per_carrier


def test_a_bad_carrier_override_names_its_key(tmp_path):
    with pytest.raises(ConfigError) as e:
        config.load(_with_sections(tmp_path, "rear: {D_max: 1.0}"))   # below D_min
    assert "plant.rear.D_max" in str(e.value)
    with pytest.raises(ConfigError) as e:
        config.load(_with_sections(tmp_path, "front: {omega00: 1.0}"))
    assert "front.omega00" in str(e.value)


def test_per_carrier_gains_and_schedule(tmp_path):
    cfg = config.load(_with_sections(tmp_path, controller_extra=textwrap.dedent("""
        front: {K_P_y: 4.0, K_I_y: 10.0, K_P_psi: 40.0, K_D_psi: 5.0, T_f_psi: 0.034}
        schedule: {v_range: [-1.5, 1.5], v_min: 0.25}
    """)))
    assert cfg.controller.gains("front").K_P_y == 4.0
    assert cfg.controller.gains("rear") == cfg.controller.pipd
    assert cfg.controller.schedule.v_range == (-1.5, 1.5) and cfg.controller.schedule.v_design is None


@pytest.mark.parametrize("sched, key", [
    ("{v_range: [1.0, -1.0]}", "v_range"),
    ("{v_range: [-1, 1], v_min: 0.5, v_design: 0.2}", "v_design"),
    ("{v_range: [-2.5, 1.0]}", "v_range"),            # beyond the hardware's v_max
])
def test_a_bad_schedule_is_refused(tmp_path, sched, key):
    with pytest.raises(ConfigError) as e:
        config.load(_with_sections(tmp_path, controller_extra=f"schedule: {sched}"))
    assert key in str(e.value)


def test_plant_speed_within_hardware_v_max(tmp_path):
    with pytest.raises(ConfigError) as e:
        config.load(_with_sections(tmp_path, "v: -3.0"))
    assert "v_max" in str(e.value)


def test_scenario_per_carrier_reference_and_speed(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text(textwrap.dedent("""
        name: s
        duration_s: 10
        reference: {front: [{t: 0, y_mm: 0}, {t: 1, y_mm: 2}]}
        speed: [{t: 0, v: 1.0}, {t: 2, v: -1.0, ramp_s: 4}]
    """))
    sc = load_scenario(p)
    assert [q.y_mm for q in sc.reference_for("front")] == [0, 2]
    assert [q.y_mm for q in sc.reference_for("rear")] == [0]          # the common default
    v = sc.speed_profile(1.0)
    assert [v(t) for t in (0.0, 2.0, 4.0, 6.0, 9.0)] == [1.0, 1.0, 0.0, -1.0, -1.0]
    assert load_scenario("single-step").speed_profile(0.7)(5.0) == 0.7


def test_scenario_errors_name_the_carrier(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text("name: s\nduration_s: 5\nreference: {front: [{t: 1, y_mm: 0}, {t: 0.5, y_mm: 1}]}\n")
    with pytest.raises(ConfigError) as e:
        load_scenario(p)
    assert "reference.front[1]" in str(e.value)
    p.write_text("name: s\nduration_s: 5\nreference: {middle: [{t: 0, y_mm: 0}]}\n")
    with pytest.raises(ConfigError) as e:
        load_scenario(p)
    assert "reference" in str(e.value)
    p.write_text("name: s\nduration_s: 5\nspeed: [{t: 1, v: 1}, {t: 1, v: 2}]\n")
    with pytest.raises(ConfigError) as e:
        load_scenario(p)
    assert "speed[1]" in str(e.value)
