"""`rig tune` reproduces the paper's printed eigenvalues and P boundary within 2 %."""

import json
import subprocess
import sys

import numpy as np
import pytest

from rig_runtime import analysis


def _match(computed, printed, rel=0.02):
    computed = sorted(computed, key=lambda e: e.real)
    assert len(computed) == len(printed)
    for c, p in zip(computed, sorted(printed)):
        assert abs(c.imag) < 1e-9, computed
        assert c.real == pytest.approx(p, rel=rel), (computed, printed)


@pytest.fixture(scope="module")
def result(cfg):
    return analysis.tune(cfg)


def test_inner_loops(result):
    _match(result.inner, [-88.9, -5.0])
    _match(result.inner_filtered, [-67.1, -40.7, -4.9])


def test_outer_and_complete_loop(result):
    _match(result.outer, [-4.5, -2.0])
    _match(result.closed_loop, [-66.5, -41.0, -4.4, -3.7, -0.5])


def test_p_control(result):
    assert result.stability_boundary_kp == pytest.approx(18605, rel=0.02)
    poles = sorted(result.open_loop_poles, key=lambda e: e.real)
    assert poles[1].real == pytest.approx(-4.5, rel=0.02)
    assert poles[2].real == pytest.approx(-1.73, rel=0.02)
    assert poles[0].real < -50  # "very far in the left half plane"


def test_boundary_is_where_the_locus_crosses(cfg, result):
    kb = result.stability_boundary_kp
    below, above = analysis.root_locus(cfg, np.array([0.99 * kb, 1.01 * kb]))
    assert below.real.max() < 0 < above.real.max()


def test_textbook_inner_loop(cfg):
    """(15) by hand: s² + (2Dω0 + Kω0²K_D) s + ω0²(1 + K K_P) = 0."""
    p, g = cfg.plant, cfg.controller.pipd
    w2 = p.omega0 ** 2
    b1 = 2 * p.D_min * p.omega0 + p.K * w2 * g.K_D_psi
    b0 = w2 * (1 + p.K * g.K_P_psi)
    roots = np.roots([1, b1, b0])
    assert sorted(roots.real) == pytest.approx(sorted(result_inner := analysis.tune(cfg).inner.real))
    assert result_inner.sum() == pytest.approx(-b1)


def test_filter_limit(cfg):
    """Eigenvalues of (16) tend to those of (15) as T_f → 0 (Sec. 5.2.2)."""
    import dataclasses
    g = dataclasses.replace(cfg.controller.pipd, T_f_psi=1e-5)
    c2 = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, pipd=g))
    ev = sorted(np.linalg.eigvals(analysis.inner_filtered_matrix(c2)), key=lambda e: e.real)
    inner = sorted(analysis.tune(cfg).inner, key=lambda e: e.real)
    assert ev[-1].real == pytest.approx(inner[-1].real, rel=1e-3)
    assert ev[-2].real == pytest.approx(inner[-2].real, rel=1e-3)


def test_design_checks(result):
    c = result.checks
    assert c["worst_case_input_per_term_A"]["terms_A"] == pytest.approx([2.0, 2.0])
    assert c["worst_case_psi_ref_rad"]["value"] == pytest.approx(0.024)
    assert c["slowest_outer_eigenvalue"]["ok"]


def test_eq10_form_is_selectable(cfg):
    import dataclasses
    c2 = dataclasses.replace(cfg, tuning=dataclasses.replace(cfg.tuning, outer_lateral_form="eq10"))
    r = analysis.tune(c2)
    assert np.max(r.outer.real) != pytest.approx(np.max(analysis.tune(cfg).outer.real))


def test_cli_json_shape(tmp_path):
    out = subprocess.run([sys.executable, "-m", "rig_runtime", "tune", "--json", "--plot", str(tmp_path)],
                         capture_output=True, text=True, check=True).stdout
    d = json.loads(out)
    for k in ("inner", "inner_filtered", "outer", "closed_loop"):
        assert all(len(e) == 2 for e in d[k]["eigenvalues"])
    assert d["p_control"]["stability_boundary_kp"] == pytest.approx(18605, rel=0.02)
    assert len(d["p_control"]["open_loop_poles"]) == 3
    for name in ("root_locus.png", "eigenvalues.png", "p_slowest_vs_D.png"):
        assert (tmp_path / name).stat().st_size > 1000


def test_cli_bad_config_one_line(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("controller: {h: 0}\n")
    r = subprocess.run([sys.executable, "-m", "rig_runtime", "tune", "--config", str(p)],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "bad.yaml" in r.stderr
