"""Supervisor unit tests without dry runs: the channel rules judged afresh after an
isolation (the second breach of one rule in one cycle is caught in that cycle), the stale
boundary in whole periods for every kind, and degraded mode (isolate, absorb, the degraded
limits, max_s, the covariance stop, readmission) driven by Samples and poses."""

import dataclasses
import math
from types import SimpleNamespace

import pytest

from rig_runtime import config
from rig_runtime.hardware import Freshness, Health
from rig_runtime.safety import Channel, Converters, Finding, Sample, State, Supervisor

from .test_safety import FakeHardware

H = 0.005
FRESH = Health(Freshness.FRESH, "")
OK = Converters(True, "", True)
NOT_ENABLED = Converters(True, "", False)
NOMINAL = {"b_f": 0.07, "b_r": 0.07, "rl": 13.0}


class FakeObserver:
    """What the supervisor reads of a carrier's observer: its design (carrier, sensors), ŷ,
    the estimate's σ_y after an outage, and the innovation window (not full: the observer
    rules hold)."""

    def __init__(self, carrier="rear", lateral=("b_r", "b_f")):
        self.d = SimpleNamespace(carrier=carrier, lateral_lasers=lateral, yaw_lasers=("s_rl", "s_rr"),
                                 channels=lateral, encoders=("rl", "rr"), lateral_weights=(0.5, 0.5),
                                 dw_row=(1.0,))
        self.y = 0.0
        self.sigma_y = 0.0
        self.outage = 0
        self.window_full = False


def observe_cfg(cfg, **deg):
    return dataclasses.replace(cfg, degraded=dataclasses.replace(cfg.degraded, on_lateral_loss="observe", **deg))


def chans():
    return [Channel("b_f", "laser", 0.045, 0.095, 4 * H), Channel("b_r", "laser", 0.045, 0.095, 4 * H),
            Channel("rl", "wheel", -100, 100, 4 * H)]


class Rig:
    """A supervisor taken to RUNNING by its cycles, and a per-cycle ``step`` at t = k·h
    where every channel's value arrived in that cycle unless ``over`` says otherwise."""

    def __init__(self, cfg, observe=True, **deg):
        self.cfg = observe_cfg(cfg, **deg) if observe else dataclasses.replace(
            cfg, degraded=dataclasses.replace(cfg.degraded, on_lateral_loss="stop"))
        self.events = []
        self.hw = FakeHardware()
        self.obs = FakeObserver()
        self.s = Supervisor(self.cfg.limits, H, chans(), ("rear",), self.hw, on_event=lambda *a: self.events.append(a),
                            observers=(self.obs,), degraded=self.cfg.degraded)
        self.k = 0
        self.last = {}                      # channel -> the arrival time it reports
        self.s.request_arm(1.0)
        self.step(conv=NOT_ENABLED)
        self.step()
        assert self.s.state is State.RUNNING

    def step(self, conv=OK, y=0.0, silent=(), **over):
        t = self.k * H
        out = {}
        for c in self.s.channels:
            if c.name not in silent:
                self.last[c.name] = t
            sm = Sample(NOMINAL[c.name], self.last.get(c.name, math.nan), FRESH)
            out[c.name] = sm._replace(**over.get(c.name, {}))
        self.s.cycle(t, out, conv, [("rear", y, 0.0)], 0, True, "")
        self.k += 1
        return t

    def texts(self, kind):
        return [e[3] for e in self.events if e[1] == kind]


# ---------------------------------------------------------------------- judged afresh
def test_a_second_laser_breaching_the_same_rule_is_isolated_in_the_same_cycle(cfg):
    """Both lateral lasers of the rear carrier go silent at once: after the first is isolated
    the channel rules start again on the rest, so the second is isolated in that cycle too
    (on the code before the split the loop went on with the next rule: one cycle late)."""
    r = Rig(cfg)
    n = r.cfg.limits.stale_periods
    for _ in range(n):
        r.step(silent=("b_f", "b_r"))
    assert r.s.state is State.RUNNING and set(r.s.isolated) == {"b_f", "b_r"}
    assert len(r.texts("degraded")) == 2


def test_a_second_channel_breaching_the_same_rule_trips_in_the_same_cycle(cfg):
    """A lateral laser (isolated) and an encoder (nothing absorbs it) stale in one cycle: the
    encoder's fault is latched in that cycle, not the next."""
    r = Rig(cfg)
    n = r.cfg.limits.stale_periods
    for _ in range(n - 1):
        r.step(silent=("b_f", "rl"))
    assert r.s.state is State.RUNNING
    t = r.step(silent=("b_f", "rl"))
    f = r.s.fault
    assert r.s.state is State.FAULT and (f.device, f.check, f.t) == ("rl", "stale", t)
    (e,) = r.s.degraded_log                # b_f was isolated first; the run ends in the fault
    assert (e["laser"], e["t_end"], e["end"]) == ("b_f", t, "FAULT")


# ---------------------------------------------------------------------- the stale boundary
@pytest.mark.parametrize("phase", [0.0, 0.25, 0.5, 0.999, 1.0])
def test_an_exact_n_period_silence_is_stale_whatever_the_arrival_phase(cfg, phase):
    """The latest value arrived ``phase`` periods before the cycle that first saw it; it is
    stale in exactly the N-th cycle after that one, for any phase and any cycle index (no
    float comparison of ages: k·h is not exact), like a drive's N unanswered SYNCs."""
    n = cfg.limits.stale_periods
    for j in range(3, 400, 7):
        s = Supervisor(cfg.limits, H, [Channel("b_f", "laser", 0.0, 1.0, n * H)], ("rear",), FakeHardware())
        s.request_arm(1e9)
        first_stale = None
        t_a = j * H - phase * H
        for k in range(j, j + n + 3):
            t = k * H
            s.cycle(t, {"b_f": Sample(0.07, t_a if k >= j else t, FRESH)}, NOT_ENABLED, [], 0, True, "")
            if k == j:
                assert s.state is State.ARMED
            if s.state is State.FAULT:
                first_stale = k
                break
        assert first_stale == j + n, (j, phase)
        assert (s.fault.check, s.fault.limit) == ("stale", n * H)


def test_a_drive_and_a_laser_go_stale_in_the_same_cycle(cfg):
    """A laser silent since cycle j and a drive that has answered no SYNC since cycle j are
    judged in whole periods alike: both stale in cycle j + N."""
    n = cfg.limits.stale_periods
    for name, unanswered in (("laser", False), ("drive", True)):
        ch = Channel("x", "laser" if not unanswered else "wheel", -100, 100, n * H)
        s = Supervisor(cfg.limits, H, [ch], ("rear",), FakeHardware())
        s.request_arm(1e9)
        j = 17
        for k in range(j, j + n + 2):
            t = k * H
            sm = Sample(0.07, j * H, FRESH, (k - j) if unanswered else -1)
            s.cycle(t, {"x": sm}, NOT_ENABLED, [], 0, True, "")
            if s.state is State.FAULT:
                break
        assert k == j + n, name


# ---------------------------------------------------------------------- degraded mode
def test_a_lost_lateral_laser_degrades_the_carrier_under_the_degraded_limits(cfg):
    r = Rig(cfg)
    s, lim, dl = r.s, r.cfg.limits, r.s.degraded_limits
    n = lim.stale_periods
    for _ in range(n):
        r.step(silent=("b_f",))
    assert s.state is State.RUNNING and "rear" in s.degraded_since and s.isolated_any(("b_f",))
    (text,) = r.texts("degraded")
    assert text.startswith("DEGRADED: b_f stale (no valid value for ") and "rear carrier(s)" in text
    assert s.degraded_log == [{"carrier": "rear", "laser": "b_f", "check": "stale",
                               "t_start": s.degraded_since["rear"], "t_end": None, "end": ""}]
    # the output saturates at the degraded u_max (rate limited from 0 first)
    u = 0.0
    for _ in range(1000):
        u = s.limit("rear", 100.0, 0.0)
    assert u == dl.u_max < lim.u_max
    # the pose rules judge ŷ under the degraded y_max: the measured y is not used
    r.obs.y = 0.9 * dl.y_max
    r.step(silent=("b_f",), y=10.0)
    assert s.state is State.RUNNING
    r.obs.y = 1.1 * dl.y_max
    t = r.step(silent=("b_f",))
    f = s.fault
    assert (f.device, f.check, f.limit) == ("geometry", "y_limit", dl.y_max)
    assert s.degraded_log[0]["t_end"] == t and s.degraded_log[0]["end"] == "FAULT"


def test_degraded_only_while_running_and_only_for_a_lost_laser(cfg):
    r = Rig(cfg)                       # a laser that lies (jumps) is not isolated: the fault
    r.s.channels[0].step_max = 0.001
    r.step(b_f={"value": 0.08})
    assert r.s.state is State.FAULT and r.s.fault.check == "jump" and not r.s.degraded_since
    r = Rig(cfg, observe=False)        # on_lateral_loss: stop
    for _ in range(r.cfg.limits.stale_periods):
        r.step(silent=("b_f",))
    assert r.s.state is State.FAULT and (r.s.fault.device, r.s.fault.check) == ("b_f", "stale")


def test_degraded_for_longer_than_max_s_is_a_fault(cfg):
    r = Rig(cfg, max_s=0.05)
    while not r.s.degraded_since:
        r.step(silent=("b_f",))
    t0 = r.s.degraded_since["rear"]
    while r.s.state is State.RUNNING:
        t = r.step(silent=("b_f",))
    f = r.s.fault
    assert (f.device, f.check, f.limit) == ("b_f", "degraded", 0.05) and t - t0 > 0.05 >= t - t0 - H


def test_the_covariance_rule_ends_the_degraded_run_in_a_clean_stop(cfg):
    r = Rig(cfg)
    while not r.s.degraded_since:
        r.step(silent=("b_f",))
    r.obs.sigma_y, r.obs.outage = 2 * r.cfg.degraded.sigma_y_max, 5
    r.step(silent=("b_f",))
    assert any(x.startswith("DEGRADED ends:") for x in r.texts("degraded"))
    r.step(silent=("b_f",))
    assert r.s.state is State.STOPPING
    for _ in range(10000):
        r.s.limit("rear", 0.0, 0.0)
        r.s.end_cycle(0.0)
        if r.s.state is State.IDLE:
            break
    e = r.s.degraded_log[0]
    assert r.s.state is State.IDLE and e["end"].startswith("IDLE (sigma_y ") and r.s.faults == []


def test_a_lost_laser_is_readmitted_once_fit_and_agreeing_for_readmit_s(cfg):
    r = Rig(cfg, readmit_s=0.02, readmit_tol_m=1e-4)
    while not r.s.degraded_since:
        r.step(silent=("b_f",))
    need = round(0.02 / H)
    r.obs.y = 5e-4                      # fit again, but ŷ disagrees with the measured y
    for _ in range(2 * need):
        r.step(y=0.0)
    assert "b_f" in r.s.isolated
    r.obs.y = 0.5e-4                    # agrees now: readmitted after readmit_s
    for k in range(need + 1):
        t = r.step(y=0.0)
        if not r.s.isolated:
            break
    assert k == need - 1 and not r.s.degraded_since and r.s.state is State.RUNNING
    assert r.s.degraded_log[0]["end"] == "b_f readmitted" and r.s.degraded_log[0]["t_end"] == t
    assert r.texts("degraded")[-1] == "rear carrier: DEGRADED ended"


def test_findings_are_read_by_name():
    f = Finding("b_f", "stale", 0.03, 0.02, "no valid value for 30 ms")
    with pytest.raises(TypeError):
        f[0]                                        # noqa: B018 - not a tuple: no positional reads
    assert dataclasses.is_dataclass(f)


# ---------------------------------------------------------------------- the cycle's slots
def test_the_observer_rules_wait_while_a_channel_rule_gathers_evidence(cfg):
    """An innovation finding on a carrier one of whose sensors brings garbled data (the
    corrupt-link rule gathering evidence) waits; once the channel is clean again it trips in
    that cycle. The evidence is asked only of a finding: the outcome is the rules' order."""
    r = Rig(cfg)
    o = r.obs
    thr = r.cfg.limits.innovation_chi2
    o.window_full, o.lat_used, o.T_psi, o.T_lat, o.T_dw = True, 0.0, 2 * thr, 0.0, 0.0
    for k in (1, 2, 3):                 # b_r discards data three cycles in a row
        r.step(b_r={"health": Health(Freshness.FRESH, "", bad_frames=k)})
        assert r.s.state is State.RUNNING
    t = r.step(b_r={"health": Health(Freshness.FRESH, "", bad_frames=3)})      # nothing newly discarded
    f = r.s.fault
    assert r.s.state is State.FAULT and (f.check, f.t, f.value) == ("innovation", t, 2 * thr)


def test_fit_judges_every_named_channel_by_the_arm_rules(cfg):
    """``fit`` is False if any named channel breaks an arm rule, whichever order the names
    come in and whether they come as a tuple or a list."""
    r = Rig(cfg)
    t = r.step(b_r={"value": 1.0})           # out of its range (isolated: fit judges the channel itself)
    s = r.s
    assert s.fit(("b_f",), t) and s.fit(("b_f", "rl"), t)
    assert not s.fit(("b_f", "b_r"), t) and not s.fit(("b_r", "b_f"), t) and not s.fit(["b_f", "b_r"], t)
    t = r.step()
    assert s.fit(("b_f", "b_r"), t)


def test_the_largest_torque_residual_counts_residuals_within_the_threshold():
    """A drive answering a little off its commands (within degraded.torque_residual_A) starts
    no run of the torque rule, and the largest residual is still recorded (the margin a
    healthy run reports)."""
    from .test_reconfiguration import Vehicle, _torque_cycle
    cfg = config.load(config.resolve_config_path("vehicle.yaml"))
    cfg = dataclasses.replace(cfg, degraded=dataclasses.replace(cfg.degraded, on_drive_loss="reallocate"))
    from rig_runtime.reconfig_analysis import table
    r = Vehicle(cfg, table(cfg))
    off = 0.5 * cfg.degraded.torque_residual_A
    for _ in range(100):                    # -1 A ramps in at du_max, then holds
        _torque_cycle(r, -1.0, {"fl": r.s._cmds["fl"][0] + off})
    assert r.s.state is State.RUNNING and not r.s.wheels_lost
    assert r.s.torque_residual_max["fl"] == pytest.approx(off, rel=1e-9)
    assert r.s._torque_run["fl"] == 0 and max(r.s.torque_residual_max[w] for w in ("fr", "rl", "rr")) <= 1e-12
