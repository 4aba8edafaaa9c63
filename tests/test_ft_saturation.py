"""The F/T sensors in a lockstep dry run (configs/sim.yaml): the simulated sensors are zeroed
at rest, so the rear wheels' static load (480 N, more than the register format holds) is
tared out and every reading stays inside the int16 range; a reading pinned at a limit is a
saturated sensor, INVALID — and, the F/T sensors being supervisor channels, that stops the
run, or keeps the rig from arming, like any INVALID channel (docs/protocols.md §3, "A
saturated sensor and the run")."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.ft_codec import AXES, FORCE_COUNTS_PER_N, INT16_MAX, INT16_MIN, TORQUE_COUNTS_PER_NM
from rig_runtime.errors import DeviceInitError
from rig_runtime.scenario import load_scenario

from .e2e import run

SENSORS = ("ft_fl", "ft_fr", "ft_rl", "ft_rr")
# a step on the rear carrier (wheel torque: Fx) and a side force on it (Fy), from the start
SCENARIO = """\
name: ft-tare
duration_s: 2.5
reference: [{t: 0, y_mm: 0}, {t: 0.5, y_mm: 1.0}]
disturbances: [{kind: constant, carrier: rear, t: 0.5, duration_s: 1.5, F_y: 150}]
"""


def _scenario(tmp_path, text: str):
    path = tmp_path / "scenario.yaml"
    path.write_text(text)
    return load_scenario(path)


def _ft(r) -> dict[str, np.ndarray]:
    return {f"{n}_{a.lower()}": r.col(f"{n}_{a.lower()}") for n in SENSORS for a in AXES}


def test_tared_simulated_fz_is_inside_the_range_and_deterministic(tmp_path, cfg):
    sc = _scenario(tmp_path, SCENARIO)
    a = run(tmp_path / "a", sc, cfg, seed=5)
    assert a.code == 0 and a.summary["final_state"] == "IDLE" and a.summary["faults"] == []
    ft = _ft(a)
    for name, v in ft.items():
        scale = FORCE_COUNTS_PER_N if name[-2] == "f" else TORQUE_COUNTS_PER_NM
        assert np.all(np.isfinite(v)), name
        assert np.all((v > INT16_MIN / scale) & (v < INT16_MAX / scale)), name     # never at a limit
    for n in ("ft_rl", "ft_rr"):                 # the rear carrier is on the rollers (480 N each)
        assert np.max(np.abs(ft[f"{n}_fz"])) < 2.0, n          # tared: noise only (σ 0.2 N)
        assert abs(np.mean(ft[f"{n}_fz"])) < 0.1, n
    t = a.col("t")
    wind = (t > 1.0) & (t < 1.9)
    for n in ("ft_rl", "ft_rr"):                 # what the sensors are for still comes through
        assert abs(np.median(ft[f"{n}_fy"][wind]) - 75.0) < 1.0, n
    assert np.max(np.abs(ft["ft_rl_fx"])) > 1.0               # the step's wheel torque
    b = run(tmp_path / "b", sc, cfg, seed=5)
    for name, v in ft.items():
        assert np.array_equal(v, _ft(b)[name]), name


def test_a_saturated_sensor_is_invalid_and_stops_the_run_with_axis_and_value(tmp_path, cfg):
    # an offset of 400 N on ft_rr's Fy from 1 s pins its register at +32767
    sc = _scenario(tmp_path, SCENARIO.replace("name: ft-tare", "name: ft-saturated") +
                   "faults: [{kind: offset, t: 1.0, device: ft_rr, amount: 400}]\n")
    r = run(tmp_path, sc, cfg, seed=5)
    assert r.summary["final_state"] == "FAULT" and r.code == 3
    f = r.fault
    assert (f["device"], f["check"]) == ("ft_rr", "invalid"), f
    assert f["message"] == "Fy saturated at +327.67 N (int16 limit)"
    assert 1.0 < f["t"] < 1.5
    k = r.fault_row()
    assert r.col("ft_rr_fy")[k] == 327.67                     # the value recorded, flagged by the fault
    assert np.all(r.col("ft_rr_fy")[: k - 30] < 100.0)


def test_a_sensor_saturated_before_the_run_keeps_the_rig_from_arming_naming_it(tmp_path, cfg):
    def untared(sim, devices, clock):      # as an un-zeroed sensor under 480 N would read
        sim.ft.inject("ft_rr", "offset", fz=480.0)

    with pytest.raises(DeviceInitError, match=r"arming: .*ft_rr: Fz saturated at \+327\.67 N \(int16 limit\)"):
        run(tmp_path, _scenario(tmp_path, SCENARIO), cfg, prepare=untared)
