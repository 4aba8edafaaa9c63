"""Campaigns on the vehicle (configs/vehicle.yaml, both carriers controlled): metrics per
carrier on its own columns and reference and the worst over both, step figures judged per
carrier with the held carrier's excursion, and parameter paths that name a carrier
(``plant.front.delta0``) or every carrier (``plant.delta0``) — read back from the configs the
campaign writes. Short runs (a front step, then a rear step 3.5 s later — long enough for the shipped
law's 10–90 % rise, ~1.4 s after a first lag — 7.5 s in all) for the 2-core machine."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from rig_runtime import config as rig_config
from rig_runtime.app.campaign import outcome, prepare
from rig_runtime.app.campaign.spec import load_spec
from rig_runtime.app.cli import main

from .test_campaign import ENV, HANG_S, table

ROOT = Path(__file__).resolve().parent.parent
SCENARIO = {
    "name": "vehicle-steps-short",
    "duration_s": 7.5,
    "speed": [{"t": 0, "v": 1.0}],
    "reference": {"front": [{"t": 0, "y_mm": 0}, {"t": 0.5, "y_mm": 1.0}],
                  "rear": [{"t": 0, "y_mm": 0}, {"t": 4.0, "y_mm": 1.0}]},
}


def vehicle_spec(tmp: Path, **changes) -> Path:
    (tmp / "short.yaml").write_text(yaml.safe_dump(SCENARIO))
    spec = {"name": "vehicle", "base": {"config": "vehicle.yaml", "scenario": "short.yaml"},
            "parameters": {"plant.delta0": {"pct": 20}, "plant.front.K": {"pct": 10},
                           "plant.rear.omega0": {"uniform": [17.0, 19.0]}},
            "design": {"method": "lhs", "n": 4, "seed": 1},
            "pass": {"no_fault": True, "overshoot_pct": 1000.0, "front_held_excursion_pct": 1000.0}}
    spec.update(changes)
    (tmp / "v.yaml").write_text(yaml.safe_dump(spec))
    return tmp / "v.yaml"


def test_the_generated_configs_vary_each_carrier_as_the_spec_says(tmp_path):
    spec = load_spec(vehicle_spec(tmp_path))
    base = rig_config.load(ROOT / "configs/vehicle.yaml").plant
    f0, r0 = base.carrier("front"), base.carrier("rear")
    assert f0.delta0 != r0.delta0               # the front has its own delta0: the case that was wrong
    store = prepare.create(spec, tmp_path / "out")
    try:
        for i in store.sample_ids():
            s = store.sample(i)
            plant = rig_config.load(s["config"]).plant
            front, rear = plant.carrier("front"), plant.carrier("rear")
            x = s["p:plant.delta0"]
            # plant.delta0 varies both carriers by the same factor, each from its own value
            assert rear.delta0 == pytest.approx(x)
            assert front.delta0 == pytest.approx(f0.delta0 * x / r0.delta0)
            assert x != pytest.approx(r0.delta0)
            # a carrier's own parameter varies that carrier only
            assert front.K == pytest.approx(s["p:plant.front.K"]) and rear.K == r0.K
            assert rear.omega0 == pytest.approx(s["p:plant.rear.omega0"]) and front.omega0 == f0.omega0
    finally:
        store.close()


def test_a_carrier_parameter_has_that_carriers_nominal(tmp_path):
    spec = load_spec(vehicle_spec(tmp_path, parameters={"plant.front.K": {"pct": 10}, "plant.rear.K": {"pct": 10}}))
    base = rig_config.load(ROOT / "configs/vehicle.yaml").plant
    nominal = {p.name: p.nominal for p in spec.parameters}
    assert nominal == {"plant.front.K": base.carrier("front").K, "plant.rear.K": base.carrier("rear").K}


@pytest.mark.parametrize("change, key", [
    ({"pass": {"rear_held_excursion_pct": 10.0}, "base": {"config": "sim.yaml", "scenario": "single-step"}},
     "pass.rear_held_excursion_pct"),                  # the paper's set-up controls one carrier
    ({"pass": {"front_overshoot_pct": 10.0}, "base": {"config": "sim.yaml", "scenario": "single-step"}},
     "pass.front_overshoot_pct"),
    ({"parameters": {"plant.front.no_such": {"pct": 10}}}, "parameters.plant.front.no_such"),
])
def test_a_carrier_metric_or_parameter_that_does_not_apply_is_refused(tmp_path, capsys, change, key):
    spec = vehicle_spec(tmp_path, **change)
    assert main(["campaign", "run", str(spec), "--out", str(tmp_path / "out"), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and key in err
    assert not (tmp_path / "out").exists()


def test_a_vehicle_campaign_reports_each_carrier_and_the_worst(tmp_path):
    spec = vehicle_spec(tmp_path)
    p = subprocess.run([sys.executable, "-m", "rig_runtime", "campaign", "run", str(spec), "--out",
                        str(tmp_path / "out"), "--workers", "2"], cwd=tmp_path, env=ENV, capture_output=True,
                       text=True, timeout=HANG_S)
    assert p.returncode == 0, p.stderr
    rows = table(tmp_path / "out")
    assert len(rows) == 4
    for r in rows:
        assert r["status"] == "pass", r["why"]                  # every step judged: no metric undefined
        for m in ("max_abs_e_y_mm", "overshoot_pct", "rise_time_s", "max_abs_u_A", "rms_u_A"):
            per = [r[f"front_{m}"], r[f"rear_{m}"]]
            assert None not in per and r[m] == max(per), (m, r[m], per)
        # the front step is judged on the front's reference (1 mm), the rear's on the rear's
        assert r["front_overshoot_pct"] != r["rear_overshoot_pct"]
        assert r["front_max_abs_e_y_mm"] < 1.5 and r["rear_max_abs_e_y_mm"] < 1.5
        # the rear held 0 while the front stepped, the front held 1 mm while the rear stepped
        assert r["rear_held_excursion_mm"] > 0 and r["front_held_excursion_mm"] > 0
        assert r["held_excursion_pct"] == max(r["rear_held_excursion_pct"], r["front_held_excursion_pct"])
    # a row's command reproduces its per-carrier metrics
    import json
    import shlex
    r = rows[0]
    log = tmp_path / "again.h5"
    cmd = shlex.split(r["command"])
    q = subprocess.run([sys.executable, "-m", "rig_runtime", *cmd[1:], "--log", str(log), "--json"], cwd=tmp_path,
                       env=ENV, capture_output=True, text=True, timeout=HANG_S)
    assert q.returncode == 0, q.stderr
    assert outcome.metrics(json.loads(q.stdout), log) == {m: r[m] for m in outcome.METRICS}


def test_gain_paths_name_a_carrier_or_every_carrier():
    from rig_runtime.app.campaign import paths
    base = {"controller": {"pipd": {"K_P_y": 3.0, "K_I_y": 9.0, "K_P_psi": 40.0, "K_D_psi": 5.0, "T_f_psi": 0.03}},
            "plant": {"delta0": 0.06, "y_off": 0.0, "front": {"delta0": 0.066, "y_off": 0.001}}}
    s = yaml.safe_load(yaml.safe_dump(base))
    values = {"controller.front.K_P_y": 4.0, "controller.pipd.K_I_y": 18.0}
    for name in paths.order(values):        # every carrier's K_I_y, then the front's own gains from those
        paths.apply(s, name, values[name], base)
    assert s["controller"]["front"] == dict(base["controller"]["pipd"], K_P_y=4.0, K_I_y=18.0)
    assert s["controller"]["pipd"] == dict(base["controller"]["pipd"], K_I_y=18.0)
    s = yaml.safe_load(yaml.safe_dump(base))
    paths.apply(s, "plant.y_off", 0.002, base)                  # a common value of 0: the same offset
    assert s["plant"]["y_off"] == 0.002 and s["plant"]["front"]["y_off"] == pytest.approx(0.003)
    assert paths.nominal(base, "plant.front.delta0") == 0.066 and paths.nominal(base, "plant.rear.delta0") == 0.06
    assert paths.nominal(base, "controller.rear.K_D_psi") == 5.0
    assert paths.order(["plant.front.delta0", "plant.delta0"]) == ["plant.delta0", "plant.front.delta0"]


def test_the_shipped_vehicle_spec_loads_and_plant_v_under_a_speed_profile_is_refused(tmp_path, capsys):
    spec = load_spec(ROOT / "configs/campaigns/vehicle-steps.yaml")
    assert {p.name for p in spec.parameters} >= {"plant.front.K", "plant.rear.K", "plant.delta0"}
    bad = vehicle_spec(tmp_path, parameters={"plant.v": {"uniform": [0.5, 1.5]}})
    assert main(["campaign", "run", str(bad), "--out", str(tmp_path / "out"), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "parameters.plant.v" in err and "speed" in err
