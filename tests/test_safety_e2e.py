"""Each supervisor check provoked end to end (lockstep): FAULT, zero current on the wire
from the detecting cycle, the cause in the event table, the log complete and readable.
(stale, corrupt, stuck, jump, invalid, converter and overrun are provoked by the fault
scenarios in test_faults_e2e.py.) And: no frame on the wire ever exceeds the limit."""

import dataclasses
import math
import random

import numpy as np
import pytest

from rig_runtime.hardware import Freshness, Health
from rig_runtime.safety import Sample
from rig_runtime import config
from rig_runtime.recorder import Recorder
from rig_runtime.scenario import Disturbance, FaultInjection, RefPoint, Scenario, load_scenario

from .e2e import assert_safe_stop, run


def with_limits(**kw):
    cfg = config.load()
    return dataclasses.replace(cfg, limits=dataclasses.replace(cfg.limits, **kw))


STEP = load_scenario("single-step")


@pytest.mark.parametrize("limits, check", [
    (dict(y_max=0.001), "y_limit"),
    (dict(psi_rate_max=0.005), "psi_rate_limit"),
])
def test_state_limits(tmp_path, limits, check):
    r = run(tmp_path, STEP, cfg=with_limits(**limits), duration_s=6.0)
    assert_safe_stop(r, "geometry", check)


def test_yaw_limit(tmp_path):
    """The PI-PD law keeps ψ_ref within limits.psi_ref_max, so the yaw limit is provoked open loop."""
    sc = load_scenario("open-loop-steps")
    sc = dataclasses.replace(sc, duration_s=6.0, open_loop=dataclasses.replace(sc.open_loop, steps=((0.0, 0.0), (1.0, 1.0))))
    r = run(tmp_path, sc, cfg=with_limits(psi_max=0.003, psi_ref_max=0.0024))
    assert_safe_stop(r, "geometry", "psi_limit")


def test_raw_range(tmp_path):
    """s_rl pushed to 100.4 % of its range (a valid reading, but outside [SMR, SMR+MR])."""
    sc = dataclasses.replace(STEP, duration_s=5.0, faults=(
        FaultInjection(kind="offset", t=2.0, device="s_rl", amount=0.0122),))
    r = run(tmp_path, sc, cfg=with_limits(laser_step_max=None))
    assert_safe_stop(r, "s_rl", "range")


def test_nan_sample(tmp_path):
    """A driver that returns a fresh NaN (a broken conversion) must not reach the controller."""
    def prepare(sim, devices, clock):
        poll = devices.poll

        def bad_poll(now):
            inp = poll(now)
            if now > 2.0:
                bad = Sample(math.nan, now, Health(Freshness.FRESH))
                inp = inp._replace(samples={**inp.samples, "s_fr": bad}, values={**inp.values, "s_fr": math.nan})
            return inp
        devices.poll = bad_poll
    r = run(tmp_path, STEP, duration_s=4.0, prepare=prepare)
    assert_safe_stop(r, "s_fr", "nan")


def test_recorder_failure(tmp_path, monkeypatch):
    """The recorder reports a disk failure: safe stop, and what was recorded stays readable."""
    orig = Recorder.append

    def failing(self, row):
        if row[1] > 2.0 and self.healthy:
            self._fail("simulated disk failure")
        return orig(self, row)
    monkeypatch.setattr(Recorder, "append", failing)
    r = run(tmp_path, STEP, duration_s=4.0)
    s = r.summary
    assert s["final_state"] == "FAULT"
    assert (r.fault["device"], r.fault["check"]) == ("recorder", "recorder")
    assert "disk failure" in r.fault["message"]
    k = int(np.argmin(np.abs(r.col("t") - r.fault["t"])))
    assert all(i == 0.0 for n, _, i in r.wire if n >= k + 1)
    assert r.log["rows"] > 300          # everything up to the failure is readable


def _random_scenario(rng: random.Random, i: int) -> Scenario:
    t, pts = 0.0, [RefPoint(t=0.0, y_mm=0.0)]
    for _ in range(4):
        t += rng.uniform(0.5, 1.5)
        pts.append(RefPoint(t=t, y_mm=rng.uniform(-6.0, 6.0), ramp_s=rng.choice([0.0, 0.0, 0.3])))
    dist = tuple(Disturbance(kind="pulse", carrier="rear", t=rng.uniform(0.5, t), duration_s=0.2,
                             F_y=rng.uniform(-500, 500)) for _ in range(2))
    return Scenario(name=f"random-{i}", duration_s=t + 1.0, reference=tuple(pts), disturbances=dist)


@pytest.mark.parametrize("seed", range(4))
def test_no_frame_exceeds_the_limit(tmp_path, seed):
    rng = random.Random(seed)
    cfg = config.load()
    if seed % 2:   # a stiff P law saturates most of the time
        cfg = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, law="p", K_P=5000.0))
    r = run(tmp_path, _random_scenario(rng, seed), cfg=cfg, seed=seed)
    lim = cfg.limits
    wire = np.array([i for _, _, i in r.wire])
    assert len(wire) > 1000
    assert np.all(np.abs(wire) <= lim.u_max / 2 + 1e-3)        # each wheel gets ±u/2
    u = r.col("rear_u_lim")
    assert np.all(np.abs(u) <= lim.u_max)
    assert np.all(np.abs(np.diff(u)) <= lim.du_max * cfg.controller.h + 1e-9)
    if seed % 2:
        assert np.max(np.abs(r.col("rear_u_cmd"))) > lim.u_max * 0.99   # the limit was actually exercised
