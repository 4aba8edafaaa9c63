"""Config validation: every error names the file, the key path and what was expected."""

import shutil

import pytest
import yaml

from rig_runtime import config
from rig_runtime.errors import ConfigError

from .conftest import ROOT


def test_shipped_configs_load():
    sim = config.load()
    rig = config.load(ROOT / "configs" / "rig.yaml")
    assert sim.controller.h == 0.005
    assert sim.controller.pipd.K_P_y == 3 and sim.controller.pipd.K_I_y == 9
    assert sim.controller.pipd.K_P_psi == 40 and sim.controller.pipd.K_D_psi == 5
    assert sim.controller.K_P == 500
    assert sim.limits.u_max == 4.0 and sim.limits.psi_max == 0.05
    assert rig.devices.can.interface == "socketcan"
    assert len(rig.devices.lasers) == 6 and len(rig.devices.can.drives) == 4
    assert sim.controlled == ("rear",)


def test_config_is_frozen(cfg):
    with pytest.raises(Exception):
        cfg.limits.u_max = 10.0  # limits cannot be loosened at run time


def _write_variant(tmp_path, section_file, mutate):
    """Copy the shipped configs into tmp_path and mutate one file's YAML."""
    d = tmp_path / "configs"
    shutil.copytree(ROOT / "configs", d)
    p = d / section_file
    data = yaml.safe_load(p.read_text())
    mutate(data)
    p.write_text(yaml.safe_dump(data))
    return d / "sim.yaml", p


@pytest.mark.parametrize("section_file, mutate, key, expected", [
    ("controller.yaml", lambda d: d["controller"].__setitem__("h", 0), "controller.h", "positive"),
    ("controller.yaml", lambda d: d["controller"].__setitem__("h", -0.005), "controller.h", "positive"),
    ("controller.yaml", lambda d: d["limits"].__setitem__("u_max", 0), "limits.u_max", "positive"),
    ("controller.yaml", lambda d: d["controller"]["pipd"].__setitem__("K_P_psi", "forty"),
     "controller.pipd.K_P_psi", "a number"),
    ("controller.yaml", lambda d: d["controller"]["pipd"].pop("K_I_y"), "controller.pipd.K_I_y", "missing"),
    ("controller.yaml", lambda d: d["controller"]["pipd"].__setitem__("K_Q", 1.0), "controller.pipd.K_Q", "no such key"),
    ("controller.yaml", lambda d: d["controller"].__setitem__("law", "pid"), "controller.law", "one of"),
    ("controller.yaml", lambda d: d.__setitem__("controlled", ["middle"]), "controlled[0]", "one of"),
    ("plant.yaml", lambda d: d["plant"].__setitem__("J_x", -0.01), "plant.J_x", "positive"),
    ("plant.yaml", lambda d: d["plant"].__setitem__("D_max", 1.0), "plant.D_max", "D_min"),
    ("plant.yaml", lambda d: d["plant"]["bouc_wen"].__setitem__("a", 1.5), "plant.bouc_wen.a", "[0, 1]"),
    ("plant.yaml", lambda d: d["plant"].__setitem__("omega0", True), "plant.omega0", "a number"),
    ("plant.yaml", lambda d: d["plant"].pop("K"), "plant.K", "missing"),
    ("geometry.yaml", lambda d: d["geometry"].__setitem__("d0", 0.0), "geometry.d0", "positive"),
    ("sim.yaml", lambda d: d["devices"]["lasers"][0].__setitem__("role", "b_x"), "devices.lasers[0].role", "one of"),
    ("sim.yaml", lambda d: d["devices"]["can"]["drives"][1].__setitem__("node_id", 200),
     "devices.can.drives[1].node_id", "node id"),
    ("sim.yaml", lambda d: d["devices"]["lasers"][1].__setitem__("role", "b_f"), "devices.lasers", "duplicate"),
    # a removed key is named as removed, with what judges it now
    ("sim.yaml", lambda d: d["devices"]["can"].__setitem__("tpdo_timeout_periods", 4),
     "devices.can.tpdo_timeout_periods", "removed: a drive's TPDO is judged now by limits.stale_periods"),
])
def test_bad_values_name_file_and_key(tmp_path, section_file, mutate, key, expected):
    main, changed = _write_variant(tmp_path, section_file, mutate)
    with pytest.raises(ConfigError) as ei:
        config.load(main)
    e = ei.value
    assert e.key_path == key
    assert expected in e.expected
    assert e.file == str(changed.resolve())
    assert str(changed.resolve()) in str(e) and key in str(e)


def test_unknown_section(tmp_path):
    main, p = _write_variant(tmp_path, "sim.yaml", lambda d: d.__setitem__("controler", {}))
    with pytest.raises(ConfigError, match="controler: expected no such section"):
        config.load(main)


def test_missing_section(tmp_path):
    main, p = _write_variant(tmp_path, "sim.yaml", lambda d: d.__setitem__("include", ["plant.yaml", "geometry.yaml"]))
    with pytest.raises(ConfigError) as ei:
        config.load(main)
    assert ei.value.key_path == "controller"


def test_yaml_syntax_error_names_line(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("controller:\n  h: [0.005\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: expected valid YAML \(syntax error at line"):
        config.load(p)


def test_missing_file_and_non_mapping(tmp_path):
    with pytest.raises(ConfigError, match="existing config file"):
        config.load(tmp_path / "nope.yaml")
    p = tmp_path / "list.yaml"
    p.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping of sections"):
        config.load(p)


def test_duplicate_section_across_includes(tmp_path):
    d = tmp_path
    (d / "a.yaml").write_text("limits: {u_max: 4, psi_max: 0.05, y_max: 0.008}\n")
    (d / "b.yaml").write_text("limits: {u_max: 4, psi_max: 0.05, y_max: 0.008}\n")
    (d / "main.yaml").write_text("include: [a.yaml, b.yaml]\n")
    with pytest.raises(ConfigError, match="defined once"):
        config.load(d / "main.yaml")


def test_exponent_without_sign_is_a_number(tmp_path):
    # PyYAML alone reads "1.0e5" as a string; engineers write it, so it is a float here
    (tmp_path / "g.yaml").write_text("geometry: {b0: 7.0e-2, l_L: 8e-1, l0: 0.27625, d0: 2.5E-1}\n")
    sections = config.load_sections(tmp_path / "g.yaml")
    assert sections["geometry"][0] == {"b0": 0.07, "l_L": 0.8, "l0": 0.27625, "d0": 0.25}


def test_derived_plant_quantities(cfg):
    import math
    p = cfg.plant
    d = p.delta0
    # c̄_y = cos²δ − (2 r0/b) cosδ sinδ  (algebraically equal to Sec. 4.1.1's expression)
    assert p.c_y == pytest.approx(math.cos(d) ** 2 - 2 * p.r0 / p.b * math.cos(d) * math.sin(d), rel=1e-12)
    assert p.Gamma == pytest.approx(math.tan(d) / (p.b / 2 - p.r0 * math.tan(d)))
    assert p.a_lat == pytest.approx(p.c_y * p.v / (2 * p.l0))
