"""Every fault scenario ends in FAULT with the right cause, zero current on the wire from
the detecting cycle on, the cause in the log's event table, and a readable log — with
``degraded.on_lateral_loss: stop`` and ``on_drive_loss: stop`` (sim.yaml observes and
reallocates: a lost lateral laser is DEGRADED then, tests/test_observer_degraded_e2e.py, and a
lost drive RECONFIGURED, the test at the end). Each scenario is run once in the session
(conftest.py ``shared_run``): these tests only read the run, and test_lifecycle_e2e.py's
determinism test compares its own second run with it."""

import pytest

from .e2e import assert_safe_stop


CASES = [
    ("fault-dropout", "b_f", "stale"),
    ("fault-corrupt", "s_rl", "corrupt"),
    ("fault-stuck", "s_rr", "stuck"),
    ("fault-offset", "s_rl", "jump"),
    ("fault-out_of_range", "b_r", "invalid"),
    ("fault-no_heartbeat", "converters", "converter"),
    ("fault-bus_error", "converters", "converter"),
    ("fault-stall", "loop", "overrun"),
    ("fault-two-wheels", "converters", "converter"),
    ("fault-during-step", "s_rl", "stale"),
]


@pytest.mark.parametrize("scenario, device, check", CASES, ids=[c[0] for c in CASES])
def test_fault_scenarios(shared_run, scenario, device, check):
    r = shared_run(scenario, on_lateral_loss="stop", on_drive_loss="stop")
    assert_safe_stop(r, device, check)
    if scenario == "fault-no_heartbeat":
        assert "rl" in r.fault["message"] and "heartbeat" in r.fault["message"].lower()
    if scenario == "fault-bus_error":
        assert "bus error" in r.fault["message"]
    if scenario == "fault-two-wheels":        # rl's short gap ended, rr's heartbeat stayed missing
        assert "drive rr" in r.fault["message"] and "heartbeat" in r.fault["message"].lower()
        assert r.fault["t"] - r.summary["run_started_t"] > 2.51
    if scenario == "fault-during-step":       # the step was being driven when it tripped
        k = r.fault_row()
        assert max(abs(u) for u in r.col("rear_u_lim")[k - 20:k]) > 0.1


def test_dropout_detection_latency(shared_run, cfg):
    r = shared_run("fault-dropout", on_lateral_loss="stop", on_drive_loss="stop")
    t_inject = r.summary["run_started_t"] + 3.0
    bound = cfg.limits.stale_periods * cfg.controller.h
    latency_cycles = (r.fault["t"] - t_inject - bound) / cfg.controller.h
    assert latency_cycles <= 3.0, latency_cycles
