"""Real-time behaviour under a stall, deterministically: the lockstep ``stall`` fault.

In lockstep the simulated rig decides when the runtime wakes up: a scenario ``stall`` makes
``advance`` return a release time later than the one asked for (sim_backend/rig.py
``_stall_s``) while the plant, the lasers and the drives' timers run on and every device
answers what the runtime sent. So what the real-time tests can only hope for on a loaded
machine is exact here:

- the loop loses 3–4 periods while every device answered in time: the runtime counts its
  own lateness (one deadline miss, the periods it skipped) and blames no device — no stale
  fault on any channel (a drive's TPDO is judged by the SYNCs it left unanswered, not by
  wall-clock periods; docs/sim-process.md, "Runtime-side issues" item 5) — and a burst
  shorter than ``limits.overrun_burst`` is no fault at all;
- a burst of ``overrun_burst`` periods is the loop's ``overrun`` fault, nothing else;
- a drive that stops answering the SYNCs while the loop runs on time is a ``stale`` fault
  naming that drive (with ``on_drive_loss: stop``; as shipped, a controlled one is
  RECONFIGURED at the same instant).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rig_runtime import config
from rig_runtime.config import LASER_ROLES, WHEELS
from rig_runtime.scenario import FaultInjection, load_scenario

from .e2e import assert_safe_stop, run

T_FAULT = 1.0           # s of RUNNING (scenario time) at which the fault acts
DURATION_S = 2.0


def _scenario(name: str, fault: FaultInjection):
    base = load_scenario("fault-stall")      # its reference: hold 0, a 1 mm step at 0.5 s
    return dataclasses.replace(base, name=name, duration_s=DURATION_S, faults=(fault,), expect_fault=None)


def _stalled_cycle(r) -> int:
    """The row of the one cycle released late (the stall), checked to be the only one."""
    late = np.flatnonzero(r.col("lateness") > 0.0)
    assert len(late) == 1, r.col("lateness")[late]
    return int(late[0])


@pytest.mark.parametrize("stall_s, lost", [(0.012, 3), (0.018, 4)], ids=["3-periods", "4-periods"])
def test_a_stall_shorter_than_the_overrun_burst_blames_no_device(tmp_path, stall_s, lost):
    cfg = config.load()
    h, burst = cfg.controller.h, cfg.limits.overrun_burst
    assert lost < burst
    r = run(tmp_path, _scenario(f"stall-{lost}", FaultInjection(kind="stall", t=T_FAULT, duration_s=stall_s)), cfg)
    s = r.summary
    assert r.code == 0 and s["final_state"] == "IDLE", s["faults"]
    assert s["faults"] == [], s["faults"]
    assert "fault" not in list(r.log["events"]["kind"]), r.log["events"]
    # the loop counted its own lateness: one release late by the stall, the periods it
    # covered skipped (not caught up), `lost` periods in all
    timing = s["timing"]
    assert timing["deadline_misses"] == 1 and timing["skipped_periods"] == lost - 1, timing
    k = _stalled_cycle(r)
    t, run_t = r.col("t"), r.col("t_run")
    assert r.col("lateness")[k] == pytest.approx(stall_s, abs=1e-9)
    # at the scenario's time (its clock starts when every drive is enabled, a few cycles before RUNNING)
    assert T_FAULT - 0.1 < run_t[k] - stall_s <= T_FAULT + 1e-9, run_t[k]
    assert t[k + 1] - t[k - 1] == pytest.approx((lost + 1) * h, abs=1e-9)   # the next release on the grid
    assert r.col("state")[k] == r.col("state")[k + 1] == float(config_state("RUNNING"))
    # every input was fresh on waking: its age is that of the latest frame, not of the stall
    for name in LASER_ROLES:
        assert r.col(f"{name}_age")[k] < h, (name, r.col(f"{name}_age")[k])
    for w in WHEELS:
        assert r.col(f"omega_{w}_age")[k] < h, (w, r.col(f"omega_{w}_age")[k])
    # and the loop went on controlling after it: current commanded on the wire after the stall
    assert any(i != 0.0 for n, _, i in r.wire if n > k + 1)


def test_a_stall_of_the_overrun_burst_is_the_loops_overrun_fault(tmp_path):
    cfg = config.load()
    h, burst = cfg.controller.h, cfg.limits.overrun_burst
    stall_s = burst * h + 0.1e-3                # the burst's periods lost on waking
    r = run(tmp_path, _scenario("stall-burst", FaultInjection(kind="stall", t=T_FAULT, duration_s=stall_s)), cfg)
    assert_safe_stop(r, "loop", "overrun")
    assert [(f["device"], f["check"]) for f in r.summary["faults"]] == [("loop", "overrun")]
    assert r.fault["value"] == burst and r.fault_row() == _stalled_cycle(r)


@pytest.mark.parametrize("wheel", ["rl", "fr"])
def test_a_drive_silent_longer_than_its_staleness_limit_is_stale(tmp_path, wheel):
    cfg = config.load()          # the staleness rule's fault: with on_drive_loss stop (sim.yaml reallocates)
    cfg = dataclasses.replace(cfg, degraded=dataclasses.replace(cfg.degraded, on_drive_loss="stop"))
    h, n = cfg.controller.h, cfg.limits.stale_periods
    r = run(tmp_path, _scenario(f"drive-dropout-{wheel}",
                                FaultInjection(kind="dropout", device=wheel, t=T_FAULT, duration_s=0.5)), cfg)
    assert_safe_stop(r, wheel, "stale")
    assert [(f["device"], f["check"]) for f in r.summary["faults"]] == [(wheel, "stale")]
    assert r.summary["timing"]["deadline_misses"] == 0           # the loop ran on time throughout
    assert not np.any(r.col("lateness") > 0.0)
    # detected once `stale_periods` SYNCs went unanswered: within a period or two of n h
    t_fault = r.fault["t"] - r.summary["run_started_t"]
    assert T_FAULT + n * h - 1e-9 <= t_fault <= T_FAULT + (n + 2) * h, (t_fault, n)


def test_a_controlled_drive_silent_past_its_staleness_limit_is_reconfigured_on_sim_yaml(tmp_path):
    """As shipped (on_drive_loss: reallocate) the same silence of rl is judged by the same
    rule at the same instant, and the rear carrier runs on rr to the end."""
    cfg = config.load()
    h, n = cfg.controller.h, cfg.limits.stale_periods
    r = run(tmp_path, _scenario("drive-dropout-rl", FaultInjection(kind="dropout", device="rl", t=T_FAULT,
                                                                   duration_s=0.5)), cfg)
    s = r.summary
    assert s["final_state"] == "IDLE" and s["faults"] == [] and r.code == 0
    (e,) = s["reconfigured"]
    assert (e["device"], e["carrier"], e["check"], e["end"]) == ("rl", "rear", "stale", "IDLE")
    t = e["t_start"] - s["run_started_t"]
    assert T_FAULT + n * h - 1e-9 <= t <= T_FAULT + (n + 2) * h, (t, n)


def config_state(name: str):
    from rig_runtime.safety import State
    return State[name]
