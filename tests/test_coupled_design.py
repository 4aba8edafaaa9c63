"""`rig tune --design` on a vehicle config: scheduled gains for every controlled carrier (the
leading one included), designed on the coupled loop at v_design and checked over the range."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import yaml

from rig_runtime import analysis, config, coupled
from rig_runtime.app import design
from rig_runtime.app.cli import main
from tests.vehicle_configs import write_vehicle


def test_equal_carriers_get_equal_gains_stable_over_the_range(tmp_path):
    cfg = config.load(write_vehicle(tmp_path))
    d = design.design_vehicle(cfg)
    assert set(d.gains) == {"front", "rear"} and d.gains["front"] == d.gains["rear"]
    assert all(c["ok"] for c in d.checks.values()), d.checks
    prop = design.with_vehicle_gains(cfg, d.gains)
    assert coupled.instability(prop) is None
    assert all(p.stable and p.sampled_stable for p in d.result.points)
    # the paper's outer gains, stable on the vehicle but with a poorly damped pair (the lateral
    # pair has lost the rear's stabilising pole): the design is not a no-op
    paper = design.with_vehicle_gains(cfg, {c: replace(d.gains[c], K_P_y=3.0, K_I_y=9.0) for c in ("front", "rear")})
    assert coupled.instability(paper) is None
    assert coupled.at_speed(paper, 1.0).zeta_min < 0.3 < design.ZETA_MIN <= coupled.at_speed(prop, 1.0).zeta_min


def test_differing_carriers_each_get_their_own(tmp_path):
    """Front 30 % off the rear (K, ω0, l0, conicity): each carrier's T_f from its own yaw
    parameters, outer gains scaled so that c̄_y,c K_c is the same; the coupled loop is stable
    over ±1.5 m/s in both directions."""
    cfg = config.load(write_vehicle(tmp_path, plant={"front": {"omega0": 18.774 * 1.3, "delta0": 0.0626982 * 0.7,
                                                               "K": 6.2937e-3 * 0.7, "l0": 0.27625 * 1.3}}))
    d = design.design_vehicle(cfg)
    f, r = d.gains["front"], d.gains["rear"]
    assert f.T_f_psi != r.T_f_psi
    cf, cr = cfg.plant.carrier("front").c_y, cfg.plant.carrier("rear").c_y
    assert cf * f.K_P_y == pytest.approx(cr * r.K_P_y) and cf * f.K_I_y == pytest.approx(cr * r.K_I_y)
    assert all(c["ok"] for c in d.checks.values()), d.checks


def test_write_and_json(tmp_path, capsys):
    src = write_vehicle(tmp_path, plant={"front": {"delta0": 0.0626982 * 1.2}})
    out = tmp_path / "ctl.yaml"
    assert main(["tune", "--design", "--json", "--write", str(out), "--config", str(src)]) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r["gains"]) == {"front", "rear"} and r["ok"]
    assert {"coupled", "coupled_sampled", "configured"} <= set(r)
    ctl = yaml.safe_load(out.read_text())["controller"]
    assert ctl["front"] == pytest.approx(r["gains"]["front"], rel=1e-5)
    assert ctl["rear"] == pytest.approx(r["gains"]["rear"], rel=1e-5)
    assert ctl["pipd"] == ctl["rear"] and ctl["front"] != ctl["rear"]
    assert ctl["schedule"]["v_range"] == [-1.5, 1.5]
    # the fragment in place of the config's controller: loads, and passes the gate over the range
    data = yaml.safe_load(src.read_text())
    data["controller"] = ctl
    again = tmp_path / "again.yaml"
    again.write_text(yaml.safe_dump(data))
    c2 = config.load(again)
    assert analysis.sampled_instability(c2) is None
    assert np.all([p.stable for p in coupled.analyse(c2).points])


def test_default_config_design_unchanged(capsys):
    """The paper's set-up keeps the single-carrier design (Sec. 5.2.3)."""
    assert main(["tune", "--design", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r["gains"]) == {"K_P_y", "K_I_y", "K_P_psi", "K_D_psi", "T_f_psi"} and "coupled" not in r
