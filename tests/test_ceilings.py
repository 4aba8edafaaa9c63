"""Hard ceilings (issue 11, item 3): every limit of a run config may only tighten the
hardware description's ceilings; a loosened one is refused at load naming the key, the
value and the ceiling, and no config object that loosens one can be made."""

import dataclasses
import shutil

import pytest
import yaml

from rig_runtime import ceilings, config
from rig_runtime.errors import ConfigError
from rig_runtime.safety import Supervisor

from .conftest import ROOT


def _variant(tmp_path, file, mutate):
    d = tmp_path / "configs"
    shutil.copytree(ROOT / "configs", d)
    p = d / file
    data = yaml.safe_load(p.read_text())
    mutate(data)
    p.write_text(yaml.safe_dump(data))
    return d / "sim.yaml", p


def _set(section, key, value, sub=None):
    def m(d):
        target = d[section] if sub is None else d[section][sub]
        target[key] = value
    return m


def _drive(i, key, value):
    def m(d):
        d["devices"]["can"]["drives"][i][key] = value
    return m


# the cases: u_max 1000 A, 20 A with drives rated 8 A, y_max 1 m, psi_max 3 rad,
# du_max 1e9, a 60 s drive watchdog, stale_periods 10^6; and the rest of the ceilings
LOOSENED = [
    ("controller.yaml", _set("limits", "u_max", 1000.0), "limits.u_max", 1000.0, "16"),
    ("controller.yaml", _set("limits", "u_max", 20.0), "limits.u_max", 20.0, "16"),
    ("controller.yaml", _set("limits", "y_max", 1.0), "limits.y_max", 1.0, "0.012"),
    ("controller.yaml", _set("limits", "psi_max", 3.0), "limits.psi_max", 3.0, "0.08"),
    ("controller.yaml", _set("limits", "du_max", 1e9), "limits.du_max", 1e9, "1000"),
    ("controller.yaml", _set("limits", "psi_rate_max", None), "limits.psi_rate_max", None, "2"),
    ("controller.yaml", _set("limits", "stale_periods", 10 ** 6), "limits.stale_periods", 10 ** 6, "10"),
    ("controller.yaml", _set("limits", "overrun_burst", 11), "limits.overrun_burst", 11, "10"),
    ("controller.yaml", _set("limits", "stop_ramp_s", 60.0), "limits.stop_ramp_s", 60.0, "1"),
    ("sim.yaml", _set("devices", "watchdog_ms", 60000, sub="can"), "devices.can.watchdog_ms", 60000, "100"),
    ("sim.yaml", _set("devices", "heartbeat_timeout_factor", 1000.0, sub="can"),
     "devices.can.heartbeat_ms x heartbeat_timeout_factor", 100000.0, "500"),
    ("sim.yaml", _drive(2, "heartbeat_ms", 1000),
     "devices.can.drives[2].heartbeat_ms x heartbeat_timeout_factor", 2500.0, "500"),
    ("sim.yaml", _drive(1, "rated_current_A", 20.0), "devices.can.drives[1].rated_current_A", 20.0, "8"),
]


@pytest.mark.parametrize("file, mutate, key, value, ceiling", LOOSENED, ids=[c[2] + "=" + str(c[3]) for c in LOOSENED])
def test_a_loosened_limit_is_refused_naming_key_value_and_ceiling(tmp_path, file, mutate, key, value, ceiling):
    main, changed = _variant(tmp_path, file, mutate)
    with pytest.raises(ConfigError) as ei:
        config.load(main)
    e = ei.value
    assert e.key_path == key
    assert e.file == str(changed.resolve())           # the file that holds the loosened key
    assert e.got == value
    msg = str(e)
    assert f"at most {ceiling} " in msg or f"ceiling {ceiling} " in msg, msg
    assert "hardware" in msg and "hardware.yaml" in msg


def test_u_max_ceiling_follows_the_lowest_configured_rated_current(tmp_path):
    def m(d):
        for dr in d["devices"]["can"]["drives"]:
            dr["rated_current_A"] = 1.5
    main, _ = _variant(tmp_path, "sim.yaml", m)
    with pytest.raises(ConfigError) as ei:
        config.load(main)          # u_max 4 A, but each wheel may carry 1.5 A only
    assert ei.value.key_path == "limits.u_max" and "at most 3 A" in str(ei.value)


@pytest.mark.parametrize("key, value", [("u_max", 16.0), ("u_max", 1.0), ("y_max", 0.012), ("psi_max", 0.045),
                                        ("du_max", 100.0), ("stale_periods", 10), ("stop_ramp_s", 0.0)])
def test_a_tightened_or_equal_limit_is_accepted(tmp_path, key, value):
    main, _ = _variant(tmp_path, "controller.yaml", _set("limits", key, value))
    assert getattr(config.load(main).limits, key) == value


def test_psi_ref_max_may_not_exceed_psi_max(tmp_path):
    """The outer loop's yaw reference stays inside the yaw limit: a psi_max tightened below the
    configured psi_ref_max is refused, naming psi_ref_max."""
    main, _ = _variant(tmp_path, "controller.yaml", _set("limits", "psi_max", 0.01))
    with pytest.raises(ConfigError) as ei:
        config.load(main)
    assert ei.value.key_path == "limits.psi_ref_max" and "at most psi_max (0.01 rad)" in str(ei.value)


def test_ceiling_in_seconds_follows_the_sample_time(tmp_path):
    """stale_periods is bounded in time: 4 periods are fine at 5 ms, not at h = 20 ms (80 ms > 50 ms)."""
    main, p = _variant(tmp_path, "controller.yaml", _set("controller", "h", 0.02))
    with pytest.raises(ConfigError) as ei:
        config.load(main)
    assert ei.value.key_path == "limits.stale_periods" and "at most 2 periods" in str(ei.value)


def test_no_config_object_loosens_a_ceiling(cfg):
    """Not even one made by dataclasses.replace (RigConfig checks in __post_init__)."""
    with pytest.raises(ConfigError, match="limits.u_max"):
        dataclasses.replace(cfg, limits=dataclasses.replace(cfg.limits, u_max=100.0))
    tighter = dataclasses.replace(cfg, limits=dataclasses.replace(cfg.limits, u_max=2.0))
    assert tighter.limits.u_max == 2.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.hardware.ceilings.y_max = 1.0


def test_the_supervisor_limits_cannot_be_replaced(cfg):
    s = Supervisor(cfg.limits, cfg.controller.h, [], ("rear",), hardware=None)
    assert s.limits is cfg.limits
    with pytest.raises(AttributeError):
        s.limits = dataclasses.replace(cfg.limits, u_max=8.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.limits.u_max = 8.0


def test_every_shipped_config_is_inside_its_ceilings():
    for name in ("sim.yaml", "rig.yaml", "sim-process.yaml"):
        c = config.load(ROOT / "configs" / name)
        assert c.hardware.source == str((ROOT / "configs" / "hardware.yaml").resolve())
        assert all(ceilings.violation(b) is None for b in ceilings.bounds(c))


def test_hardware_description_is_required_and_a_file_of_its_own(tmp_path):
    # missing
    main, _ = _variant(tmp_path / "a", "sim.yaml", lambda d: d["include"].remove("hardware.yaml"))
    with pytest.raises(ConfigError) as ei:
        config.load(main)
    assert ei.value.key_path == "hardware" and "missing" in str(ei.value)
    # a run config carrying its own (looser) ceilings next to the limits they bound
    hw = yaml.safe_load((ROOT / "configs" / "hardware.yaml").read_text())["hardware"]
    loose = {**hw, "ceilings": {**hw["ceilings"], "y_max": 1.0}}
    main, p = _variant(tmp_path / "b", "sim.yaml", lambda d: d.__setitem__("hardware", loose))
    with pytest.raises(ConfigError) as ei:
        config.load(main)
    assert ei.value.key_path == "hardware" and "file of its own" in str(ei.value)
    # two hardware descriptions
    other = tmp_path / "c"
    other.mkdir()
    (other / "hw2.yaml").write_text(yaml.safe_dump({"hardware": loose}))
    main, p = _variant(tmp_path / "d", "sim.yaml",
                       lambda d: d.__setitem__("include", d["include"] + [str(other / "hw2.yaml")]))
    with pytest.raises(ConfigError, match="defined once"):
        config.load(main)


def test_a_huge_time_ceiling_is_not_a_crash(tmp_path):
    def m(d):
        d["hardware"]["ceilings"]["stale_s"] = 1e308
    d = tmp_path / "configs"
    shutil.copytree(ROOT / "configs", d)
    p = d / "hardware.yaml"
    data = yaml.safe_load(p.read_text())
    m(data)
    p.write_text(yaml.safe_dump(data))
    assert config.load(d / "sim.yaml").hardware.ceilings.stale_s == 1e308
