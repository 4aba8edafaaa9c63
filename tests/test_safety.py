"""Supervisor unit tests: transitions, latched faults, each check, the output limit."""

import dataclasses
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rig_runtime.hardware import Freshness
from rig_runtime.safety import Channel, State, Supervisor

H = 0.005


def chans(t=0.0):
    cs = [Channel("b_f", "laser", 0.045, 0.095, 0.02), Channel("rl", "wheel", -100, 100, 0.02)]
    for c in cs:
        c.value, c.t, c.state, c.cause = 0.07 if c.kind == "laser" else 13.0, t, Freshness.FRESH, ""
    return cs


def running(cfg, t=0.0):
    events = []
    s = Supervisor(cfg.limits, H, on_event=lambda *a: events.append(a))
    assert s.arm(chans(t), True, t) == []
    s.start(t)
    assert s.state is State.RUNNING
    return s, events


def ok_check(s, t, cs=None, **kw):
    args = dict(converters_ok=True, converter_cause="", y=0.0, psi=0.0, consecutive_misses=0,
                recorder_ok=True, recorder_cause="")
    args.update(kw)
    s.check(t, cs if cs is not None else chans(t), **args)


def test_arming_requires_fresh_in_range_and_ready(cfg):
    s = Supervisor(cfg.limits, H)
    cs = chans(0.0)
    cs[0].state, cs[0].cause = Freshness.STALE, "no data for 30 ms"
    assert s.arm(cs, True, 0.0) == ["b_f: no data for 30 ms"]
    cs = chans(0.0)
    cs[0].value = 0.2
    assert "outside" in s.arm(cs, True, 0.0)[0]
    assert s.arm(chans(0.0), False, 0.0) == ["converters not ready"]
    assert s.state is State.IDLE
    assert s.arm(chans(0.0), True, 0.0) == [] and s.state is State.ARMED


@pytest.mark.parametrize("mutate, check", [
    (lambda cs: setattr(cs[0], "state", Freshness.INVALID), "invalid"),
    (lambda cs: setattr(cs[0], "t", -1.0), "stale"),
    (lambda cs: setattr(cs[0], "value", math.nan), "nan"),
    (lambda cs: setattr(cs[0], "value", 0.2), "range"),
])
def test_channel_checks_latch(cfg, mutate, check):
    s, events = running(cfg)
    cs = chans(0.1)
    mutate(cs)
    ok_check(s, 0.1, cs)
    assert s.state is State.FAULT and s.fault.check == check and s.fault.device == "b_f"
    assert s.limit(3.0, 0.1) == 0.0                # zero in the detecting cycle
    ok_check(s, 0.2)                                # healthy again: still latched
    assert s.state is State.FAULT
    assert any(e[1] == "fault" for e in events)
    s.reset(0.3)
    assert s.state is State.IDLE


@pytest.mark.parametrize("kw, check", [
    (dict(psi=0.06), "psi_limit"), (dict(y=-0.009), "y_limit"),
    (dict(converters_ok=False, converter_cause="rl: EMCY 0x2310"), "converter"),
    (dict(recorder_ok=False, recorder_cause="disk full"), "recorder"),
    (dict(consecutive_misses=5), "overrun"),
])
def test_state_and_system_checks(cfg, kw, check):
    s, _ = running(cfg)
    ok_check(s, 0.005, **kw)
    assert s.state is State.FAULT and s.fault.check == check


def test_yaw_rate_limit(cfg):
    s, _ = running(cfg)
    ok_check(s, 0.005, psi=0.0)
    ok_check(s, 0.010, psi=0.01)     # 2 rad/s > 1 rad/s
    assert s.state is State.FAULT and s.fault.check == "psi_rate_limit"


def test_output_saturation_and_rate_limit(cfg):
    s, _ = running(cfg)
    lim = cfg.limits
    step = lim.du_max * H
    seq = [s.limit(100.0, 0.0) for _ in range(200)]
    assert max(seq) == lim.u_max
    assert all(abs(b - a) <= step + 1e-12 for a, b in zip([0.0] + seq, seq))
    assert s.limit(math.nan, 1.0) == 0.0 and s.state is State.FAULT


def test_stopping_ramps_to_zero_then_idle(cfg):
    s, _ = running(cfg)
    for _ in range(100):
        s.limit(2.0, 0.0)
    s.request_stop(0.5)
    assert s.state is State.STOPPING
    n, u = 0, 2.0
    while s.state is State.STOPPING:
        u_new = s.limit(2.0, 0.5 + n * H)
        assert abs(u_new) <= abs(u)
        u = u_new
        s.end_cycle(0.5 + n * H)
        n += 1
    assert s.state is State.IDLE and u == 0.0
    ramp_cycles = cfg.limits.stop_ramp_s / H * 2.0 / cfg.limits.u_max
    assert n == pytest.approx(ramp_cycles, abs=2)


def test_limits_cannot_be_loosened(cfg):
    s, _ = running(cfg)
    with pytest.raises(Exception):
        s.limits.u_max = 100.0


def test_stuck_and_jump(cfg):
    s, _ = running(cfg)
    cs = chans(0.0)
    cs[0].stuck_check = True
    n = cfg.limits.stuck_periods
    for k in range(n + 2):
        for c in cs:
            c.t = k * H
        ok_check(s, k * H, cs)
        if s.state is State.FAULT:
            break
    assert s.fault.check == "stuck" and s.fault.device == "b_f" and k >= n
    s2, _ = running(cfg)
    cs = chans(0.0)
    cs[0].step_max = cfg.limits.laser_step_max
    ok_check(s2, 0.0, cs)
    cs[0].value += 0.001
    ok_check(s2, 0.0, cs)
    assert s2.state is State.RUNNING        # 1 mm in one cycle: plausible
    cs[0].value += 0.005
    ok_check(s2, 0.0, cs)
    assert s2.state is State.FAULT and s2.fault.check == "jump"


# a nominal channel with at most one defect each, so that a whole set is nominal but for one detail
_DEFECTS = {
    None: {},
    "stale_state": {"state": Freshness.STALE},
    "invalid": {"state": Freshness.INVALID},
    "old": {"age": 0.03},
    "nan": {"v": math.nan},
    "inf": {"v": math.inf},
    "range": {"prev": 0.2, "v": 0.2},
    "jump": {"prev": 0.05},
    "corrupt": {"bad_run": 2, "bad_new": 1},             # a third cycle in a row with garbled frames
    "corrupt_almost": {"bad_run": 1, "bad_new": 1},
    "stuck": {"prev": 0.0701, "same": 9},                 # the tenth repetition
    "stuck_almost": {"prev": 0.0701, "same": 8},
    "first_cycle": {"prev": math.nan},
    "inf_in_infinite_bounds": {"v": math.inf, "lo": -math.inf, "hi": math.inf},
    "inf_unbounded": {"v": math.inf, "lo": -math.inf, "hi": math.inf, "step_max": math.inf},
    "big_step_unlimited": {"prev": 0.05, "step_max": math.inf},
}
_SPEC = st.lists(st.sampled_from([None] * 6 + list(_DEFECTS)), min_size=1, max_size=4)


@settings(max_examples=300, deadline=None)
@given(spec=_SPEC, counts_on=st.booleans())
def test_one_pass_check_agrees_with_the_ordered_checks(cfg, spec, counts_on):
    """The nominal fast path of ``check`` decides exactly like the checks one by one."""
    lim = dataclasses.replace(cfg.limits, stuck_periods=10 if counts_on else None,
                              corrupt_cycles=3 if counts_on else None)
    t = 1.0
    cs = []
    for k, defect in enumerate(spec):
        p = {"prev": 0.07, "v": 0.0701, "state": Freshness.FRESH, "age": 0.0, "bad_new": 0, "bad_run": 0,
             "same": 0, "step_max": 0.01, "lo": 0.045, "hi": 0.095, **_DEFECTS[defect]}
        c = Channel(f"c{k}", "laser", p["lo"], p["hi"], 0.02, step_max=p["step_max"], stuck_check=True)
        c.prev, c.value, c.state, c.t, c.cause = p["prev"], p["v"], p["state"], t - p["age"], ""
        c.bad_prev, c.bad, c.bad_run, c.same = 5, 5 + p["bad_new"], p["bad_run"], p["same"]
        cs.append(c)
    s = Supervisor(lim, H)
    s.state = State.RUNNING
    ok_check(s, t, cs)
    ref = Supervisor(lim, H)         # same channel data, checks one by one
    ref.state = State.RUNNING
    tripped = ref._check_channels(t, cs, lim.stuck_periods or 0, lim.corrupt_cycles or 0)
    assert tripped == s.new_fault
    if tripped:
        assert (s.fault.device, s.fault.check) == (ref.fault.device, ref.fault.check)
