"""`rig tune --design` (rig_runtime/app/design.py): Sec. 5.2.3 automated on the analysis'
loop matrices; the shipped plant, plants differing by ±30 %, and closed-loop dry runs."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import yaml

from rig_runtime import config
from rig_runtime.app import design
from rig_runtime.app.cli import main
from rig_runtime.scenario import load_scenario
from tests.identify_plants import plants


def _perturbed():
    """The recovery test's plants and two more corners of ±30 % in the loop's parameters."""
    out = {k: v[0] for k, v in plants().items() if k != "shipped"}
    cfg = config.load()
    P = cfg.plant
    out["slow"] = replace(cfg, plant=replace(P, omega0=P.omega0 * 0.7, K=P.K * 0.7, D_min=P.D_min * 1.3,
                                             delta0=P.delta0 * 0.7, l0=P.l0 * 1.3))
    out["fast"] = replace(cfg, plant=replace(P, omega0=P.omega0 * 1.3, K=P.K * 1.3, D_min=P.D_min * 0.7,
                                             delta0=P.delta0 * 1.3, l0=P.l0 * 0.7))
    return out


def test_shipped_plant_gives_the_papers_inner_gains():
    cfg = config.load()
    d = design.design(cfg)
    g = d.gains
    assert g.K_P_psi == pytest.approx(40.0) and g.K_D_psi == pytest.approx(5.0)
    assert all(c["ok"] for c in d.checks.values()), d.checks
    # T_f: the slowest eigenvalue of (16) within the tolerance of (15)'s, and not more than that
    s15 = np.max(d.result.inner.real)
    s16 = np.max(d.result.inner_filtered.real)
    assert abs(s16 - s15) <= design.TF_SLOW_TOL * abs(s15) * (1 + 1e-9)
    assert 0.02 < g.T_f_psi < 0.06
    # outer: the criteria hold, and a larger integrator would break one of them
    assert g.K_P_y * cfg.tuning.y_design <= cfg.tuning.psi_ref_design_max + 1e-12
    assert np.max(d.result.outer.real) <= cfg.tuning.slowest_eig_min
    bigger = design.with_gains(cfg, replace(g, K_I_y=g.K_I_y + design.KI_Y_GRID))
    ev17 = np.linalg.eigvals(design.analysis.outer_matrix(bigger))
    ev19 = np.linalg.eigvals(design.analysis.closed_loop_matrix(bigger))
    evs = design.analysis.sampled_closed_loop(bigger)
    assert (np.any(np.abs(ev17.imag) > 1e-9) or np.max(ev17.real) > cfg.tuning.slowest_eig_min
            or np.max(ev19.real) > design.SLOW_19 or not design._zeta_ok(ev19) or not design._zeta_ok(evs))


@pytest.mark.parametrize("name", ["A", "B", "slow", "fast"])
def test_perturbed_plants_pass_the_gate_and_the_checks(name):
    d = design.design(_perturbed()[name])
    assert all(c["ok"] for c in d.checks.values()), d.checks
    assert np.max(d.result.closed_loop.real) < 0 and np.max(d.result.closed_loop_sampled.real) < 0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["shipped", "A", "B", "slow", "fast"])
def test_designed_gains_track_a_2mm_step_in_a_lockstep_dry_run(name, tmp_path):
    from rig_runtime.app.dryrun import run_lockstep
    cfg = config.load() if name == "shipped" else _perturbed()[name]
    g = design.design(cfg).gains
    run_cfg = design.with_gains(cfg, g)
    summary, code = run_lockstep(run_cfg, load_scenario("single-step"), tmp_path / "step.h5")
    assert code == 0 and summary["final_state"] == "IDLE"
    (step,) = summary["steps"]
    assert step["to_mm"] == pytest.approx(2.0)
    assert abs(step["steady_state_error_mm"]) < 0.02 * 2.0, step


def test_tune_design_json_and_write(tmp_path, capsys):
    out = tmp_path / "controller-designed.yaml"
    assert main(["tune", "--design", "--json", "--write", str(out)]) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r["gains"]) == {"K_P_y", "K_I_y", "K_P_psi", "K_D_psi", "T_f_psi"}
    assert r["gains"]["K_P_psi"] == pytest.approx(40.0) and r["gains"]["K_D_psi"] == pytest.approx(5.0)
    assert r["ok"] and r["configured"]["gains"]["K_P_y"] == 3.0
    w = yaml.safe_load(out.read_text())["controller"]["pipd"]
    assert w == pytest.approx(r["gains"], rel=1e-5)
    bounds = yaml.safe_load(out.read_text())["controller"]["tuning"]    # live tuning still possible
    assert bounds == {k: list(v) for k, v in config.load().controller.tuning.items()}
    assert "the designed 7.5 lies outside" in out.read_text()          # K_P_y 7.5 vs [1, 6]
    assert main(["tune", "--design", "--write", str(out)]) == 2        # never overwrites
    assert "overwrite" in capsys.readouterr().err
    assert main(["tune", "--write", str(tmp_path / "x.yaml")]) == 2    # --write needs --design
