"""End to end in lockstep: the whole runtime against the simulated plant, over the real
transports (ptys, a python-can bus, Modbus TCP on 127.0.0.1)."""

import numpy as np

from .e2e import run


def test_single_step_tracks(tmp_path, cfg):
    r = run(tmp_path, "single-step")
    s = r.summary
    assert r.code == 0 and s["final_state"] == "IDLE" and s["faults"] == []
    assert s["max_abs_current_A"] <= cfg.limits.u_max
    assert all(abs(i) <= cfg.limits.u_max for _, _, i in r.wire)
    (st,) = s["steps"]
    assert st["to_mm"] == 2.0
    assert abs(st["steady_state_error_mm"]) < 0.02 * 2.0
    assert 0.5 < st["rise_time_s"] < 5.0
    assert st["settling_time_s"] is not None and st["settling_time_s"] < 14.0
    assert r.log["rows"] == s["cycles"] == len(r.col("t"))
    assert r.log["attrs"]["software_version"] and "config" in r.log["attrs"]


def test_deterministic_for_a_seed(tmp_path):
    a = run(tmp_path / "a", "single-step", duration_s=2.0, seed=3)
    b = run(tmp_path / "b", "single-step", duration_s=2.0, seed=3)
    assert np.array_equal(a.col("y_r"), b.col("y_r"))
    assert np.array_equal(a.col("rear_u_lim"), b.col("rear_u_lim"))
