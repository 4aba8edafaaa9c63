"""The observer design is memoised on its inputs (rig_runtime.app.observer_design): the same
inputs give the same (frozen) design without designing again, and every input is in the key —
changing any one of them gives another design."""

from __future__ import annotations

import dataclasses
import inspect
import os

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


# ---------------------------------------------------------------------- the design cache across processes
@pytest.fixture
def disk(tmp_path, monkeypatch):
    """The design cache in a directory of the test's own, nothing of this process's memory."""
    monkeypatch.setenv(od.CACHE_ENV, str(tmp_path / "designs"))
    monkeypatch.setattr(od, "_grids", {})
    return tmp_path / "designs"


def _forbid_designing(monkeypatch):
    """Designing raises from here on (a grid must come from the cache's file)."""
    import functools

    def forbidden(*a):
        raise AssertionError("designed again")
    monkeypatch.setattr(od, "_design", functools.wraps(od._design)(forbidden))


def test_a_speed_table_designed_once_is_read_back_by_another_process(disk, monkeypatch):
    vcfg = config.load("configs/vehicle.yaml")
    a = od.speed_table(vcfg, "rear")
    files = list(disk.glob("*.pickle"))
    assert len(files) == 1
    monkeypatch.setattr(od, "_grids", {})              # another process: nothing in memory
    _forbid_designing(monkeypatch)
    b = od.speed_table(vcfg, "rear")
    assert b == a and b.table.forward == a.table.forward and b.table.backward == a.table.backward


class _Foreign:
    def __reduce__(self):
        return (os.getcwd, ())                          # a pickle that would call something


@pytest.mark.parametrize("garble", [b"", b"not a pickle", "shape", "foreign"])
def test_a_corrupt_cache_file_is_designed_again(disk, monkeypatch, garble):
    import pickle
    vcfg = config.load("configs/vehicle.yaml")
    a = od.speed_table(vcfg, "rear")
    (f,) = disk.glob("*.pickle")
    if garble == "shape":                               # a valid pickle of the wrong shape
        f.write_bytes(pickle.dumps(("x",)))
    elif garble == "foreign":                           # a pickle naming a class that is not a design's
        f.write_bytes(pickle.dumps((_Foreign(),) * len(a.table.forward) * 2))
        with open(f, "rb") as fh, pytest.raises(pickle.UnpicklingError):
            od._DesignUnpickler(fh).load()
    else:
        f.write_bytes(garble)
    monkeypatch.setattr(od, "_grids", {})
    assert od.speed_table(vcfg, "rear") == a
    assert od._read(f, len(a.table.forward) * 2) is not None     # written again, whole


def test_an_unwritable_or_switched_off_cache_is_ignored(tmp_path, monkeypatch):
    vcfg = config.load("configs/vehicle.yaml")
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setattr(od, "_grids", {})
    monkeypatch.setenv(od.CACHE_ENV, str(blocker / "designs"))     # cannot be a directory
    a = od.speed_table(vcfg, "rear")
    monkeypatch.setattr(od, "_grids", {})
    monkeypatch.setenv(od.CACHE_ENV, "off")
    assert od.cache_dir() is None
    assert od.speed_table(vcfg, "rear") == a
    assert list(tmp_path.iterdir()) == [blocker]


def test_the_cache_key_is_every_input_and_the_code_version(cfg, monkeypatch):
    """Another value of any design input, another speed or another code version: another key."""
    inputs = od.design_inputs(cfg, "rear")[:-1]
    speeds = [0.5, 1.0]
    base = od.cache_key(od._design, inputs, speeds)
    assert od.cache_key(od._design, inputs, list(speeds)) == base          # the same values: the same key
    other = {
        "plant": dataclasses.replace(inputs[1], omega0=inputs[1].omega0 * (1 + 1e-15)),
        "geometry": dataclasses.replace(inputs[2], d0=inputs[2].d0 * 1.2),
        "observer": dataclasses.replace(inputs[3], yaw_model=not inputs[3].yaw_model),
        "h": inputs[4] / 2, "outage_max_s": inputs[5] + 1, "window": inputs[6] + 1, "ft_sensors": (),
    }
    keys = {base}
    for name, value in other.items():
        i = od.DesignInputs._fields.index(name)
        k = od.cache_key(od._design, inputs[:i] + (value,) + inputs[i + 1:], speeds)
        assert k not in keys, name
        keys.add(k)
    assert od.cache_key(od._design, ("front",) + inputs[1:], speeds) not in keys
    assert od.cache_key(od._design, inputs, [0.5, 1.0 + 1e-16 * 2]) != base
    assert od.cache_key(od._joint, inputs, speeds) != base
    monkeypatch.setattr(od, "code_version", lambda: "another version")
    assert od.cache_key(od._design, inputs, speeds) != base


def test_the_cache_keeps_the_most_recently_used_files(disk, monkeypatch):
    vcfg = config.load("configs/vehicle.yaml")
    monkeypatch.setattr(od, "CACHE_FILES_KEPT", 2)
    disk.mkdir(parents=True)
    for k, name in enumerate(("old", "older")):
        (disk / f"{name}.pickle").write_bytes(b"")
        os.utime(disk / f"{name}.pickle", (1000.0 - k, 1000.0 - k))
    od.speed_table(vcfg, "rear")
    names = {f.name for f in disk.glob("*.pickle")}
    assert len(names) == 2 and "old.pickle" in names          # the new one and the newer of the other two
