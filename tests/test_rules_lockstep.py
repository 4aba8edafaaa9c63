"""Rules judged once, by the supervisor, on what the drivers observed (lockstep, simulated
time): a link that delivers only garbled frames is named as corrupted, not as silent."""

import dataclasses

from rig_runtime import config
from rig_runtime.scenario import FaultInjection, load_scenario

from .e2e import assert_safe_stop, run


def test_a_laser_link_delivering_only_garbled_frames_is_named_corrupted(tmp_path, cfg):
    base = load_scenario("fault-corrupt")
    sc = dataclasses.replace(base, faults=(FaultInjection(kind="corrupt", t=3.0, device="s_rl", fraction=1.0,
                                                          duration_s=2.0),))
    r = run(tmp_path, sc)
    assert_safe_stop(r, "s_rl", "corrupt")
    msg = r.fault["message"]
    assert msg.startswith("no valid value for ") and "bytes of unparseable data in that time" in msg, msg
    # judged when the latest valid value is stale_periods periods old (whole periods), not later
    bound = cfg.limits.stale_periods * cfg.controller.h
    assert r.fault["value"] >= bound - 1e-9 and r.fault["limit"] == bound
    t_inject = r.summary["run_started_t"] + 3.0
    assert r.fault["t"] - t_inject <= bound + 3 * cfg.controller.h
    n = int(msg.split(": ")[1].split()[0])
    assert n >= 1


def test_a_silent_laser_is_named_stale_without_corruption(tmp_path, cfg):
    # a lost lateral laser with degraded.on_lateral_loss: stop (sim.yaml observes: DEGRADED,
    # tests/test_observer_degraded_e2e.py)
    r = run(tmp_path, "fault-dropout", cfg=dataclasses.replace(cfg, degraded=config.Degraded()))
    assert_safe_stop(r, "b_f", "stale")
    assert "garbled" not in r.fault["message"] and r.fault["message"].startswith("no valid value for ")
