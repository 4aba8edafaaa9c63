"""Supervisor unit tests: transitions (the supervisor owns them and switches the power
stages), latched faults, each rule, the order of root causes, the output limit."""

import dataclasses
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rig_runtime.hardware import Freshness, Health
from rig_runtime.safety import (
    ARM_RULES, CHANNEL_RULES, POSE_RULES, Channel, Converters, Sample, State, Supervisor)

H = 0.005
FRESH = Health(Freshness.FRESH, "")
OK = Converters(True, "", True)           # converters fine, every power stage enabled
NOT_ENABLED = Converters(True, "", False)


class FakeHardware:
    """Records what the supervisor switches."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, float]] = []

    def activate(self, now: float) -> None:
        self.calls.append(("activate", now))

    def deactivate(self, now: float) -> None:
        self.calls.append(("deactivate", now))

    def resume(self, now: float) -> None:
        self.calls.append(("resume", now))

    def isolate(self, wheel: str, now: float) -> None:
        self.calls.append(("isolate " + wheel, now))


def chans():
    return [Channel("b_f", "laser", 0.045, 0.095, 0.02), Channel("rl", "wheel", -100, 100, 0.02)]


NOMINAL = {"b_f": 0.07, "rl": 13.0}


def samples(t, cs, **over):
    """A fresh, nominal sample per channel at ``t``; ``over[name]`` replaces fields of one
    (``value``, ``t``, ``health``)."""
    out = {}
    for c in cs:
        s = Sample(NOMINAL.get(c.name, 0.0), t, FRESH)
        if c.name in over:
            s = s._replace(**over[c.name])
        out[c.name] = s
    return out


def step(s, t, conv=OK, poses=None, misses=0, recorder_ok=True, recorder_cause="", **over):
    """One cycle; ``poses``: (y, ψ) per carrier in ``s.carriers`` order. Returns the Step."""
    poses = poses if poses is not None else [(0.0, 0.0)] * len(s.carriers)
    return s.cycle(t, samples(t, s.channels, **over), conv, [(c, y, p) for c, (y, p) in zip(s.carriers, poses)],
                   misses, recorder_ok, recorder_cause)


def supervisor(cfg, carriers=("rear",), limits=None, cs=None):
    events = []
    hw = FakeHardware()
    s = Supervisor(limits or cfg.limits, H, cs if cs is not None else chans(), carriers, hw,
                   on_event=lambda *a: events.append(a))
    return s, events, hw


def running(cfg, t=0.0, carriers=("rear",), limits=None, cs=None):
    """A supervisor taken IDLE -> ARMED -> RUNNING by the cycles themselves."""
    s, events, hw = supervisor(cfg, carriers, limits, cs)
    s.request_arm(t + 1.0)
    step(s, t, conv=NOT_ENABLED)
    assert s.state is State.ARMED and s.arm_blockers == []
    assert step(s, t + H).started
    assert s.state is State.RUNNING
    return s, events, hw


def test_arming_requires_fresh_in_range_and_converters_ok(cfg):
    s, _, hw = supervisor(cfg)
    s.request_arm(1.0)
    step(s, 0.0, b_f={"t": -0.03})
    assert s.state is State.IDLE and s.arm_blockers == ["b_f: no valid value for 30 ms"]
    step(s, 0.005, b_f={"value": 0.2})
    assert s.state is State.IDLE and len(s.arm_blockers) == 1
    assert s.arm_blockers[0].startswith("b_f:") and "outside" in s.arm_blockers[0]
    step(s, 0.010, conv=Converters(False, "drive rl (node 3): EMCY 0x2310", False))
    assert s.state is State.IDLE and s.arm_blockers == ["converters: drive rl (node 3): EMCY 0x2310"]
    step(s, 0.015, misses=2)        # warm-up still missing deadlines
    assert s.state is State.IDLE and s.arm_blockers == ["loop: 2 periods lost to deadline misses"]
    assert hw.calls == []           # no power while any blocker is left
    step(s, 0.020, conv=NOT_ENABLED)   # the power stages need not be enabled to arm
    assert s.arm_blockers == [] and s.state is State.ARMED and s.ever_armed
    assert hw.calls == [("activate", 0.020)]


def test_arm_rules_are_a_prefix_of_the_channel_rules():
    assert CHANNEL_RULES[:len(ARM_RULES)] == ARM_RULES
    assert [r.__name__ for r in CHANNEL_RULES] == [
        "invalid", "stale", "not_finite", "out_of_range", "corrupt_link", "stuck", "jump"]
    assert [r.__name__ for r in POSE_RULES] == ["pose_not_finite", "psi_limit", "y_limit", "psi_rate_limit"]


def test_arm_deadline_passes_and_stop_cancels_arming(cfg):
    s, _, hw = supervisor(cfg)
    s.request_arm(0.010)
    for k in range(4):
        step(s, k * H, b_f={"health": Health(Freshness.INVALID, "no peak (262076)")})
    assert s.state is State.IDLE and s.arm_failed and s.arm_blockers == ["b_f: no peak (262076)"]
    step(s, 0.05)                   # fit now, but the request has expired
    assert s.state is State.IDLE and hw.calls == []
    s2, _, hw2 = supervisor(cfg)
    s2.request_arm(1.0)
    step(s2, 0.0, b_f={"value": 0.2})
    s2.request_stop(0.005, "operator stop")
    step(s2, 0.010)
    assert s2.state is State.IDLE and not s2.ever_armed and hw2.calls == []


@pytest.mark.parametrize("over, check, value, limit", [
    ({"b_f": {"health": Health(Freshness.INVALID, "no peak (262076)")}}, "invalid", 0.07, math.nan),
    ({"b_f": {"t": -1.0}}, "stale", 1.1, 0.02),
    ({"b_f": {"t": math.nan}}, "stale", math.inf, 0.02),
    ({"b_f": {"value": math.nan}}, "nan", math.nan, math.nan),
    ({"b_f": {"value": -math.inf}}, "nan", -math.inf, math.nan),
    ({"b_f": {"value": 0.2}}, "range", 0.2, 0.095),
    ({"b_f": {"value": 0.01}}, "range", 0.01, 0.045),
], ids=["invalid", "stale_age", "stale_never", "nan", "inf", "range_hi", "range_lo"])
def test_channel_checks_latch(cfg, over, check, value, limit):
    s, events, hw = running(cfg)
    step(s, 0.1, **over)
    f = s.fault
    assert s.state is State.FAULT and f.check == check and f.device == "b_f"
    assert f.t == 0.1
    assert f.value == pytest.approx(value, nan_ok=True) and f.limit == pytest.approx(limit, nan_ok=True)
    assert s.limit("rear", 3.0, 0.1) == 0.0                 # zero in the detecting cycle
    assert s.end_cycle(0.1) is f                    # the cycle's outcome names the new fault
    assert hw.calls[-1] == ("deactivate", 0.1)
    step(s, 0.2)                                    # healthy again: still latched
    assert s.state is State.FAULT and s.fault is f
    assert s.limit("rear", 3.0, 0.2) == 0.0
    assert s.end_cycle(0.2) is None                 # latched before: not new in this cycle
    assert [e for e in events if e[1] == "fault"] == [(0.1, "fault", f, f.message)]
    s.reset(0.3)
    assert s.state is State.IDLE and s.fault is None and s.faults == [f]
    # reset enables no power stage: it only brings communication back (resume)
    assert hw.calls.count(("activate", 0.0)) == 1 and hw.calls[-1] == ("resume", 0.3) and len(hw.calls) == 3


@pytest.mark.parametrize("kw, device, check, value, limit, text", [
    (dict(poses=[(0.0, 0.06)]), "geometry", "psi_limit", 0.06, 0.05, "rear carrier"),
    (dict(poses=[(0.0, -0.06)]), "geometry", "psi_limit", -0.06, 0.05, "rear carrier"),
    (dict(poses=[(-0.009, 0.0)]), "geometry", "y_limit", -0.009, 0.008, "rear carrier"),
    (dict(poses=[(math.nan, 0.0)]), "geometry", "nan", math.nan, math.nan, "rear carrier"),
    (dict(conv=Converters(False, "rl: EMCY 0x2310", False)), "converters", "converter", math.nan, math.nan,
     "rl: EMCY 0x2310"),
    (dict(conv=NOT_ENABLED), "converters", "disabled", math.nan, math.nan, "OPERATION ENABLED"),
    (dict(recorder_ok=False, recorder_cause="disk full"), "recorder", "recorder", math.nan, math.nan, "disk full"),
    (dict(misses=5), "loop", "overrun", 5, 5, "5 control periods"),
])
def test_state_and_system_checks(cfg, kw, device, check, value, limit, text):
    s, _, _ = running(cfg)
    step(s, 0.010, **kw)
    f = s.fault
    assert s.state is State.FAULT and (f.device, f.check) == (device, check)
    assert f.value == pytest.approx(value, nan_ok=True) and f.limit == pytest.approx(limit, nan_ok=True)
    assert text in f.message


def test_below_the_limits_nothing_trips(cfg):
    s, _, _ = running(cfg)
    step(s, 0.010, poses=[(0.0079, 0.004)], misses=4)
    step(s, 0.015, poses=[(-0.0079, 0.0)])
    assert s.state is State.RUNNING and s.faults == []


# in order: with this cause and every one below it present, this one is recorded
ROOT_CAUSES = ["overrun", "recorder", "converter", "disabled", "invalid", "stale", "range", "psi_limit", "y_limit"]


def _causes(present):
    kw = {}
    if "overrun" in present:
        kw["misses"] = 5
    if "recorder" in present:
        kw.update(recorder_ok=False, recorder_cause="disk full")
    if "converter" in present:
        kw["conv"] = Converters(False, "rl: EMCY 0x2310", False)
    elif "disabled" in present:
        kw["conv"] = NOT_ENABLED
    if "invalid" in present:
        kw["b_f"] = {"health": Health(Freshness.INVALID, "no peak (262076)")}
    if "stale" in present:
        kw["rl"] = {"t": -1.0}
    if "range" in present:
        kw.setdefault("b_f", {})["value"] = 0.2
    kw["poses"] = [(0.009 if "y_limit" in present else 0.0, 0.06 if "psi_limit" in present else 0.0)]
    return kw


@pytest.mark.parametrize("first", range(len(ROOT_CAUSES)), ids=ROOT_CAUSES)
def test_order_of_root_causes(cfg, first):
    """Overruns before the recorder before the converters before the channels before the
    poses: with every cause from ``first`` on present, ``first`` is the one recorded."""
    s, _, _ = running(cfg)
    step(s, 0.010, **_causes(ROOT_CAUSES[first:]))
    assert s.state is State.FAULT and s.fault.check == ROOT_CAUSES[first]
    assert len(s.faults) == 1                       # one fault per cycle: the first


def test_each_channel_rule_is_applied_to_every_channel_before_the_next(cfg):
    # b_f (first channel) out of range, rl (second) invalid: the invalid rule comes first
    s, _, _ = running(cfg)
    step(s, 0.010, b_f={"value": 0.2}, rl={"health": Health(Freshness.INVALID, "EMCY 0x2310")})
    assert (s.fault.device, s.fault.check) == ("rl", "invalid")
    # both stale: the first channel is named
    s, _, _ = running(cfg)
    step(s, 0.010, b_f={"t": -1.0}, rl={"t": -1.0})
    assert (s.fault.device, s.fault.check) == ("b_f", "stale")


def test_yaw_rate_limit(cfg):
    s, _, _ = running(cfg)
    step(s, 0.010, poses=[(0.0, 0.0)])
    step(s, 0.015, poses=[(0.0, 0.01)])     # 2 rad/s > 1 rad/s
    f = s.fault
    assert s.state is State.FAULT and f.check == "psi_rate_limit" and f.device == "geometry"
    assert f.value == pytest.approx(2.0) and f.limit == cfg.limits.psi_rate_max
    s, _, _ = running(cfg)
    step(s, 0.010, poses=[(0.0, 0.0)])
    step(s, 0.015, poses=[(0.0, 0.004)])    # 0.8 rad/s: fine
    assert s.state is State.RUNNING


def test_output_saturation_and_rate_limit(cfg):
    s, _, _ = running(cfg)
    lim = cfg.limits
    step_a = lim.du_max * H
    seq = [s.limit("rear", 100.0, 0.0) for _ in range(200)]
    assert max(seq) == lim.u_max
    assert all(abs(b - a) <= step_a + 1e-12 for a, b in zip([0.0] + seq, seq))
    seq = [s.limit("rear", -100.0, 0.0) for _ in range(200)]
    assert min(seq) == -lim.u_max
    assert all(abs(b - a) <= step_a + 1e-12 for a, b in zip([lim.u_max] + seq, seq))
    assert s.limit("rear", math.nan, 1.0) == 0.0 and s.state is State.FAULT
    assert (s.fault.device, s.fault.check) == ("controller", "nan")
    assert s.end_cycle(1.0) is s.fault


@pytest.mark.parametrize("u", [math.inf, -math.inf, math.nan])
def test_a_non_finite_output_trips_and_sends_zero(cfg, u):
    s, _, _ = running(cfg)
    assert s.limit("rear", u, 1.0) == 0.0 and s.state is State.FAULT
    assert (s.fault.device, s.fault.check) == ("controller", "nan") and "rear carrier" in s.fault.message


@pytest.mark.parametrize("pose", [(math.inf, 0.0), (0.0, -math.inf), (math.nan, 0.0)])
def test_a_non_finite_pose_trips(cfg, pose):
    s, _, _ = running(cfg)
    step(s, 0.010, poses=[pose])
    assert (s.fault.device, s.fault.check) == ("geometry", "nan") and "rear carrier" in s.fault.message


def test_output_is_zero_unless_running_or_stopping(cfg):
    s, _, _ = supervisor(cfg)
    assert s.limit("rear", 2.0, 0.0) == 0.0 and s.limit("rear", 2.0, 0.0) == 0.0          # IDLE
    s.request_arm(1.0)
    step(s, 0.0, conv=NOT_ENABLED)
    assert s.state is State.ARMED and s.limit("rear", 2.0, 0.0) == 0.0               # ARMED: no torque yet


def test_stopping_ramps_to_zero_then_idle(cfg):
    s, events, hw = running(cfg)
    for _ in range(100):
        s.limit("rear", 2.0, 0.0)
    s.request_stop(0.5)
    step(s, 0.5)                            # the transition is made in the next cycle
    assert s.state is State.STOPPING
    assert any(e[1] == "operator" and e[3] == "stop requested" for e in events)
    n, u = 0, 2.0
    while s.state is State.STOPPING:
        t = 0.5 + n * H
        if n:
            step(s, t)
        u_new = s.limit("rear", 2.0, t)
        assert abs(u_new) <= abs(u)
        u = u_new
        assert hw.calls[-1][0] == "activate"            # still on while ramping
        s.end_cycle(t)
        n += 1
    assert s.state is State.IDLE and u == 0.0
    assert hw.calls[-1] == ("deactivate", 0.5 + (n - 1) * H)
    ramp_cycles = cfg.limits.stop_ramp_s / H * 2.0 / cfg.limits.u_max
    assert n == pytest.approx(ramp_cycles, abs=2)


def test_limits_cannot_be_loosened(cfg):
    s, _, _ = running(cfg)
    with pytest.raises(Exception):
        s.limits.u_max = 100.0


def test_stuck_and_jump(cfg):
    cs = chans()
    cs[0].stuck_check = True
    s, _, _ = running(cfg, cs=cs)
    n = cfg.limits.stuck_periods
    for k in range(2, n + 4):
        step(s, k * H, rl={"value": 13.0 + 1e-3 * k})
        if s.state is State.FAULT:
            break
    f = s.fault
    assert f.check == "stuck" and f.device == "b_f" and k >= n
    assert f.value == n and f.limit == n
    cs = chans()
    cs[0].step_max = cfg.limits.laser_step_max
    s2, _, _ = running(cfg, cs=cs)
    step(s2, 0.010, b_f={"value": 0.071})
    assert s2.state is State.RUNNING        # 1 mm in one cycle: plausible
    step(s2, 0.015, b_f={"value": 0.076})
    f = s2.fault
    assert s2.state is State.FAULT and f.check == "jump" and f.device == "b_f"
    assert f.value == pytest.approx(0.005) and f.limit == cfg.limits.laser_step_max


def test_corrupt_link(cfg):
    n = cfg.limits.corrupt_cycles
    s, _, _ = running(cfg)
    bad = 0
    for k in range(2, 2 + n - 1):           # garbled frames in n - 1 cycles in a row
        bad += 1
        step(s, k * H, rl={"health": Health(Freshness.FRESH, "", bad_frames=bad)})
    step(s, (n + 1) * H, rl={"health": Health(Freshness.FRESH, "", bad_frames=bad)})   # a clean cycle
    assert s.state is State.RUNNING
    for k in range(n + 2, 2 * n + 2):
        bad += 1
        step(s, k * H, rl={"health": Health(Freshness.FRESH, "", bad_frames=bad)})
    f = s.fault
    assert s.state is State.FAULT and (f.device, f.check) == ("rl", "corrupt")
    assert f.value == n and f.limit == n and k == 2 * n + 1


def test_only_the_front_carrier_beyond_psi_max(cfg):
    s, _, _ = running(cfg, carriers=("front", "rear"))
    for _ in range(3):                      # both carriers have current
        u_f, u_r = s.limit("front", 1.5, 0.010), s.limit("rear", -1.5, 0.010)
        s.end_cycle(0.010)
    assert u_f == 1.5 and u_r == -1.5
    t, psi = 0.015, 0.0
    while s.state is State.RUNNING:         # the front carrier yaws at 0.8 rad/s, the rear not
        psi += 0.004
        step(s, t, poses=[(0.0, psi), (0.0, 0.0)])
        u_f, u_r = s.limit("front", 1.5, t), s.limit("rear", -1.5, t)
        s.end_cycle(t)
        t += H
    f = s.fault
    assert (f.device, f.check) == ("geometry", "psi_limit")
    assert f.value == pytest.approx(psi) and psi > cfg.limits.psi_max and f.limit == cfg.limits.psi_max
    assert "front" in f.message and "rear" not in f.message
    assert u_f == 0.0 and u_r == 0.0        # both zero in the detecting cycle
    for k in range(5):                      # and from then on
        step(s, t + k * H, poses=[(0.0, 0.0), (0.0, 0.0)])
        assert s.limit("front", 1.5, t + k * H) == 0.0 and s.limit("rear", -1.5, t + k * H) == 0.0


def test_only_the_rear_carrier_beyond_y_max(cfg):
    s, _, _ = running(cfg, carriers=("front", "rear"))
    step(s, 0.010, poses=[(0.0, 0.0), (0.0085, 0.0)])
    f = s.fault
    assert (f.device, f.check) == ("geometry", "y_limit") and f.value == 0.0085
    assert "rear" in f.message and "front" not in f.message


def test_hardware_is_switched_only_at_arm_fault_and_end_of_stop(cfg):
    s, events, hw = supervisor(cfg)
    s.request_arm(1.0)
    step(s, 0.0, b_f={"t": math.nan})      # no valid value yet
    assert s.state is State.IDLE and hw.calls == []
    step(s, 0.005, conv=NOT_ENABLED)
    assert s.state is State.ARMED and hw.calls == [("activate", 0.005)]
    for k in range(2, 10):                  # the drives take a few periods to enable
        step(s, k * H, conv=NOT_ENABLED)
    step(s, 0.050)
    assert s.state is State.RUNNING and hw.calls == [("activate", 0.005)]
    for k in range(11, 30):
        step(s, k * H)
        s.limit("rear", 1.0, k * H)
        s.end_cycle(k * H)
    assert hw.calls == [("activate", 0.005)]
    s.request_stop(0.150)
    t = 0.150
    while s.state is not State.IDLE:
        step(s, t)
        s.limit("rear", 1.0, t)
        assert len(hw.calls) == 1
        s.end_cycle(t)
        t += H
    assert hw.calls == [("activate", 0.005), ("deactivate", t - H)]
    kinds = [e[3] for e in events if e[1] == "state"]
    assert kinds == ["IDLE -> ARMED", "ARMED -> RUNNING", "RUNNING -> STOPPING: stop requested",
                     "STOPPING -> IDLE: stopped"]
    # a fault: deactivate at the FAULT transition; reset and re-arming after reset
    s, _, hw = running(cfg, t=1.0)
    assert hw.calls == [("activate", 1.0)]
    step(s, 1.010, b_f={"value": 0.2})
    assert s.state is State.FAULT and hw.calls == [("activate", 1.0), ("deactivate", 1.010)]
    step(s, 1.015)
    s.reset(1.020)
    step(s, 1.025)
    assert s.state is State.IDLE and hw.calls[2:] == [("resume", 1.020)]    # communication on, no power
    s.request_arm(2.0)
    step(s, 1.030)
    assert s.state is State.ARMED and hw.calls[-1] == ("activate", 1.030)
    step(s, 1.035)
    assert s.state is State.RUNNING and len(hw.calls) == 4


def test_arm_again_after_a_completed_stop(cfg):
    s, _, hw = running(cfg)
    s.request_stop(0.010)
    t = 0.010
    while s.state is not State.IDLE:
        step(s, t)
        s.limit("rear", 1.0, t)
        s.end_cycle(t)
        t += H
    s.request_arm(t + 1.0)
    step(s, t)
    assert s.state is State.ARMED
    step(s, t + H)
    assert s.state is State.RUNNING


def test_activation_timeout(cfg):
    s, _, hw = supervisor(cfg)
    s.request_arm(1.0)
    step(s, 0.0, conv=NOT_ENABLED)
    assert s.state is State.ARMED
    k = 1
    while s.state is State.ARMED:
        step(s, k * H, conv=Converters(True, "fl: SWITCHED ON", False))
        k += 1
    f = s.fault
    assert s.state is State.FAULT and (f.device, f.check) == ("converters", "activate")
    assert f.value > 0.5 and f.value == pytest.approx(0.5 + H) and f.limit == 0.5
    assert "fl: SWITCHED ON" in f.message
    assert hw.calls == [("activate", 0.0), ("deactivate", (k - 1) * H)]


# a nominal channel with at most one defect each, so that a whole set is nominal but for one detail
_DEFECTS = {
    None: ({}, None),
    "never": ({"age": math.inf}, "stale"),
    "invalid": ({"state": Freshness.INVALID}, "invalid"),
    "old": ({"age": 0.03}, "stale"),
    "nan": ({"v": math.nan}, "nan"),
    "inf": ({"v": math.inf}, "nan"),
    "range": ({"prev": 0.2, "v": 0.2}, "range"),
    "jump": ({"prev": 0.05}, "jump"),
    "corrupt": ({"bad_run": 2, "bad_new": 1}, "corrupt"),      # a third cycle in a row with garbled frames
    "corrupt_almost": ({"bad_run": 1, "bad_new": 1}, None),
    "stuck": ({"prev": 0.0701, "same": 9}, "stuck"),           # the tenth repetition
    "stuck_almost": ({"prev": 0.0701, "same": 8}, None),
    "first_cycle": ({"prev": math.nan}, None),
    "inf_in_infinite_bounds": ({"v": math.inf, "lo": -math.inf, "hi": math.inf}, "nan"),
    "inf_unbounded": ({"v": math.inf, "lo": -math.inf, "hi": math.inf, "step_max": math.inf}, "nan"),
    "big_step_unlimited": ({"prev": 0.05, "step_max": math.inf}, None),
}
_SPEC = st.lists(st.sampled_from([None] * 6 + list(_DEFECTS)), min_size=1, max_size=4)
_ORDER = ["invalid", "stale", "nan", "range", "corrupt", "stuck", "jump"]


@settings(max_examples=300, deadline=None)
@given(spec=_SPEC, counts_on=st.booleans())
def test_the_first_rule_in_order_trips(cfg, spec, counts_on):
    """Whatever the mix of defects, the fault is the earliest rule (in rule order, then
    channel order) that some channel fails; switched-off count rules never trip."""
    lim = dataclasses.replace(cfg.limits, stuck_periods=10 if counts_on else None,
                              corrupt_cycles=3 if counts_on else None)
    t = 1.0
    cs, ss, expected = [], [], []
    for k, defect in enumerate(spec):
        p, check = _DEFECTS[defect]
        p = {"prev": 0.07, "v": 0.0701, "state": Freshness.FRESH, "age": 0.0, "bad_new": 0, "bad_run": 0,
             "same": 0, "step_max": 0.01, "lo": 0.045, "hi": 0.095, **p}
        c = Channel(f"c{k}", "laser", p["lo"], p["hi"], 0.02, step_max=p["step_max"], stuck_check=True)
        c.value, c.bad, c.bad_run, c.same = p["prev"], 5, p["bad_run"], p["same"]     # the history
        c.bad_at_value = 5                  # no garbled frames since the latest valid value
        cs.append(c)
        ss.append(Sample(p["v"], t - p["age"], Health(p["state"], "", bad_frames=5 + p["bad_new"])))
        if check in ("stuck", "corrupt") and not counts_on:
            check = None
        if check is not None:
            expected.append((_ORDER.index(check), k, check))
    s = Supervisor(lim, H, cs, ("rear",), FakeHardware())
    s.state = State.RUNNING
    s.cycle(t, {c.name: x for c, x in zip(cs, ss)}, OK, [("rear", 0.0, 0.0)], 0, True, "")
    assert (s.end_cycle(t) is not None) == bool(expected)
    if expected:
        _, k, check = min(expected)
        assert (s.fault.device, s.fault.check) == (f"c{k}", check)


def test_a_drive_is_judged_by_the_syncs_it_left_unanswered_not_by_the_clock(cfg):
    """The runtime's own lateness is not a drive's fault: a wheel whose latest TPDO is far
    older than stale_periods·h in wall time, but which answered every SYNC the runtime sent
    (the loop lost periods and sent none), is fit; one that left stale_periods SYNCs
    unanswered is stale however recent its last TPDO, and the fault says so."""
    n = cfg.limits.stale_periods
    s, _, _ = running(cfg)
    t = 1.0
    step(s, t, rl={"t": t - 0.5, "unanswered": 1})      # 0.5 s old: a stalled loop, one SYNC out since
    assert s.state is State.RUNNING
    step(s, t + H, rl={"t": t + H, "unanswered": n - 1})
    assert s.state is State.RUNNING
    step(s, t + 2 * H, rl={"t": t + H, "unanswered": n})
    f = s.fault
    assert (f.device, f.check, f.value, f.limit) == ("rl", "stale", n, n)
    assert f.message == f"no valid value for {n} requests sent"
