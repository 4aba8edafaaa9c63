"""Drive outages without dry runs: the outage table (the coupled analysis per case, at
configure time) and the supervisor's reconfiguration (isolate the lost drive, its carrier
RECONFIGURED under tighter limits, or the fault naming the analysis' answer)."""

import dataclasses
import math
from types import SimpleNamespace

import pytest

from rig_runtime import config
from rig_runtime.allocation import wheel_currents
from rig_runtime.hardware import Freshness, Health
from rig_runtime.reconfig_analysis import table
from rig_runtime.safety import Channel, Converters, Sample, State, Supervisor

from .test_safety import FakeHardware

H = 0.005
FRESH = Health(Freshness.FRESH, "")
WHEELS = ("fl", "fr", "rl", "rr")
HB = "drive {w} (node {n}): heartbeat missing for 130 ms"
NODE = {"fl": 1, "fr": 2, "rl": 3, "rr": 4}


@pytest.fixture(scope="module")
def vcfg():
    cfg = config.load(config.resolve_config_path("vehicle.yaml"))
    return dataclasses.replace(cfg, degraded=dataclasses.replace(cfg.degraded, on_drive_loss="reallocate"))


@pytest.fixture(scope="module")
def vtable(vcfg):
    return table(vcfg)


def conv(lost=(), off=()):
    drives = tuple((w, HB.format(w=w, n=NODE[w])) for w in lost)
    return Converters(not drives, drives[0][1] if drives else "", not off and not drives, drives=drives,
                      not_enabled=tuple(off) or tuple(lost))


class Vehicle:
    """A supervisor of both carriers with the four wheel channels, taken to RUNNING."""

    def __init__(self, cfg, tb, v=1.0):
        self.cfg = cfg
        self.events = []
        chans = [Channel(w, "wheel", -100, 100, cfg.limits.stale_periods * H) for w in WHEELS]
        self.hw = FakeHardware()
        self.s = Supervisor(cfg.limits, H, chans, ("front", "rear"), self.hw,
                            on_event=lambda *a: self.events.append(a), degraded=cfg.degraded, outages=tb)
        self.v = v
        self.k = 0
        self.s.request_arm(1.0)
        self.step(Converters(True, "", False))
        self.step()
        assert self.s.state is State.RUNNING

    def step(self, c=None, y=(0.0, 0.0), unanswered=None):
        t = self.k * H
        sm = {w: Sample(10.0 + 1e-3 * self.k, t, FRESH, (unanswered or {}).get(w, 0)) for w in WHEELS}
        speed = SimpleNamespace(v=[self.v, self.v], v_hat=self.v, carriers=("front", "rear"))
        self.s.cycle(t, sm, c if c is not None else conv(), [("front", y[0], 0.0), ("rear", y[1], 0.0)],
                     0, True, "", speed=speed)
        self.k += 1
        return t

    def texts(self, kind):
        return [e[3] for e in self.events if e[1] == kind]


def test_the_table_decides_by_carrier_direction_and_speed(vtable):
    """One wheel lost: the nominal loop (the remaining wheel carries the whole command) —
    stable both ways. Both wheels of the leading carrier lost: not stable; of the trailing
    carrier: stable (the numbers are docs/safety.md's table)."""
    for w in WHEELS:
        for v in (1.0, -1.0):
            assert vtable.decide({w}, v).stable
    assert not vtable.decide({"fl", "fr"}, 1.0).stable and vtable.decide({"fl", "fr"}, -1.0).stable
    assert vtable.decide({"rl", "rr"}, 1.0).stable and not vtable.decide({"rl", "rr"}, -1.0).stable
    assert not vtable.decide({"fl", "fr", "rl"}, 1.0).stable          # nothing left to control with
    d = vtable.decide({"fl", "fr"}, 1.0)
    assert d.uncontrolled == ("front",) and d.radius > 1.0 and "not stable" in d.why


def test_the_paper_setup_reconfigures_a_rear_wheel_not_the_whole_rear(cfg):
    tb = table(cfg)
    assert tb.controlled == ("rear",)
    assert tb.decide({"rl"}, cfg.plant.v).stable and tb.decide({"rr"}, cfg.plant.v).stable
    assert not tb.decide({"rl", "rr"}, cfg.plant.v).stable


def test_an_announced_outage_reconfigures_its_carrier_in_that_cycle(vcfg, vtable):
    r = Vehicle(vcfg, vtable)
    t = r.step(conv(lost=("fl",)))
    s = r.s
    assert s.state is State.RUNNING and set(s.wheels_lost) == {"fl"} and s.faults == []
    assert r.hw.calls[-1] == ("isolate fl", t)          # that drive quick-stopped and disabled
    (text,) = r.texts("reconfigured")
    assert text.startswith("RECONFIGURED: drive fl lost (drive fl (node 1): heartbeat missing") and "fr alone" in text
    assert s.reconfigured_log == [{"carrier": "front", "device": "fl", "check": "converter", "t_start": t,
                                   "t_end": None, "end": ""}]
    # 0 A for the lost wheel from that cycle: the allocation gives fr the whole command
    u = s.limit("front", 1.0, t)
    out = wheel_currents([SimpleNamespace(wheels=("fl", "fr"), u=u), SimpleNamespace(wheels=("rl", "rr"), u=0.0)],
                         {}, s.wheels_lost, 8.0)
    assert out["fl"] == 0.0 and out["fr"] == -u
    # the tighter limits: u_max and y_max of degraded.limits for the front carrier only
    for _ in range(2000):
        u = s.limit("front", 100.0, t)
    assert u == vcfg.degraded.limits.u_max
    r.step(conv(lost=("fl",)), y=(0.9 * vcfg.degraded.limits.y_max, 0.0))
    r.step(conv(lost=("fl",)), y=(0.0, 1.5 * vcfg.degraded.limits.y_max))     # rear: the normal limits
    assert s.state is State.RUNNING
    r.step(conv(lost=("fl",)), y=(1.1 * vcfg.degraded.limits.y_max, 0.0))
    assert s.state is State.FAULT and (s.fault.check, s.fault.limit) == ("y_limit", vcfg.degraded.limits.y_max)
    assert s.reconfigured_log[0]["end"] == "FAULT"


def test_a_second_wheel_of_the_leading_carrier_is_the_fault_the_analysis_names(vcfg, vtable):
    r = Vehicle(vcfg, vtable, v=1.0)
    r.step(conv(lost=("fl",)))
    t = r.step(conv(lost=("fl", "fr")))
    f = r.s.fault
    assert r.s.state is State.FAULT and (f.device, f.check) == ("converters", "converter")
    assert f.message.startswith("drive fr (node 2): heartbeat missing")
    assert "not reconfigured: front carrier uncontrolled" in f.message
    assert r.s.reconfigured_log[0]["t_end"] == t
    r = Vehicle(vcfg, vtable, v=-1.0)            # trailing in reverse: the rear goes on alone
    r.step(conv(lost=("fl",)))
    r.step(conv(lost=("fl", "fr")))
    assert r.s.state is State.RUNNING and set(r.s.wheels_lost) == {"fl", "fr"}
    assert r.s.limit("front", 3.0, 0.0) == 0.0          # no wheel left: no command
    assert "uncontrolled (both wheels lost)" in r.texts("reconfigured")[-1]


def test_a_silent_drive_reconfigures_like_an_announced_one(vcfg, vtable):
    """A drive that leaves stale_periods SYNCs unanswered (the channel rule's breach) is lost
    the same way; the channel rules then judge the other wheels afresh in that cycle."""
    r = Vehicle(vcfg, vtable)
    n = vcfg.limits.stale_periods
    r.step(unanswered={"rr": n})
    assert r.s.state is State.RUNNING and set(r.s.wheels_lost) == {"rr"}
    assert r.s.reconfigured_log[0]["check"] == "stale"


def test_stop_keeps_the_fault_and_the_reconfiguration_ends_with_the_run(vcfg, vtable):
    stop = dataclasses.replace(vcfg, degraded=dataclasses.replace(vcfg.degraded, on_drive_loss="stop"))
    r = Vehicle(stop, vtable)
    r.step(conv(lost=("fl",)))
    assert r.s.state is State.FAULT and r.s.fault.message == HB.format(w="fl", n=1) and not r.s.wheels_lost
    r = Vehicle(vcfg, vtable)
    r.step(conv(lost=("rl",)))
    r.s.request_stop(0.0, "duration reached")
    r.step(conv(lost=("rl",)))
    assert r.s.state is State.STOPPING
    for _ in range(10000):
        for c in ("front", "rear"):
            r.s.limit(c, 0.0, 0.0)
        r.s.end_cycle(1.0)
        if r.s.state is State.IDLE:
            break
    assert r.s.state is State.IDLE and r.s.faults == [] and r.s.reconfigured_log[0]["end"] == "IDLE"
    assert not r.s.wheels_lost


def test_not_reconfigured_unless_running(vcfg, vtable):
    s = Supervisor(vcfg.limits, H, [Channel(w, "wheel", -100, 100, 0.02) for w in WHEELS], ("front", "rear"),
                   FakeHardware(), degraded=vcfg.degraded, outages=vtable)
    s.request_arm(1.0)
    s.cycle(0.0, {w: Sample(1.0, 0.0, FRESH, 0) for w in WHEELS}, Converters(True, "", False), [], 0, True, "")
    assert s.state is State.ARMED
    s.cycle(H, {w: Sample(1.0, H, FRESH, 0) for w in WHEELS}, conv(lost=("fl",)), [], 0, True, "")
    assert s.state is State.FAULT and s.fault.check == "converter"


def _torque_cycle(r, u, actual):
    """One cycle where the lanes command ``u`` per carrier and each drive reports ``actual``
    (wheel -> A; missing: the command it was given, as a healthy drive does)."""
    c = conv()
    cmds = {w: r.s._cmds.get(w, [0.0])[0] for w in WHEELS}
    c = c._replace(torque=tuple((w, actual.get(w, cmds[w])) for w in WHEELS))
    t = r.step(c)
    for car in ("front", "rear"):
        r.s.limit(car, u, t)
    r.s.end_cycle(t)
    return t


def test_a_drive_without_torque_response_is_lost_after_the_hold_time(vcfg, vtable):
    """Silent outage: the drive answers every SYNC and stays enabled, but reports no current
    against its commands (either sign) for degraded.torque_hold_s: lost, RECONFIGURED."""
    r = Vehicle(vcfg, vtable)
    need = round(vcfg.degraded.torque_hold_s / H)
    for k in range(200):                    # healthy: the commands answered, nothing happens
        _torque_cycle(r, 1.0 if k % 40 < 20 else -1.0, {})
    assert not r.s.wheels_lost and max(r.s.torque_residual_max.values()) <= 1e-12
    for k in range(need + 3):               # below the residual threshold: no evidence either way
        _torque_cycle(r, 0.5 * vcfg.degraded.torque_residual_A, {"fl": 0.0})
    assert not r.s.wheels_lost
    ts = [_torque_cycle(r, -1.0, {"fl": 0.0}) for _ in range(need + 5)]
    (e,) = r.s.reconfigured_log
    assert (e["device"], e["check"]) == ("fl", "torque") and set(r.s.wheels_lost) == {"fl"}
    # the three latest commands must all be large before the count starts (-1 A ramps in at du_max)
    assert ts.index(e["t_start"]) <= need + 3
    assert "no torque response" in r.texts("reconfigured")[0]


def test_the_torque_response_is_judged_only_when_reallocating(vcfg, vtable):
    """With on_drive_loss: stop the rule is off (its threshold is measured on the simulated
    drives only; docs/safety.md): a drive that does not answer its commands is what it was."""
    stop = dataclasses.replace(vcfg, degraded=dataclasses.replace(vcfg.degraded, on_drive_loss="stop"))
    r = Vehicle(stop, vtable)
    for _ in range(50):
        _torque_cycle(r, -1.0, {"fl": 0.0})
    assert r.s.state is State.RUNNING and not r.s.wheels_lost


def test_the_summary_printout_lists_each_reconfiguration(capsys):
    from rig_runtime.app.commands import _print_summary
    summary = {"final_state": "IDLE", "cycles": 10, "log": "x.h5", "max_abs_current_A": 1.0,
               "max_abs_wire_current_A": 0.5, "faults": [], "run_started_t": 1.0, "clock": "lockstep",
               "wall_time_s": 0.1, "sim_time_s": 0.05, "timing": {},
               "reconfigured": [{"carrier": "front", "device": "fl", "check": "torque", "t_start": 7.05,
                                 "t_end": 32.0, "end": "IDLE"}]}
    _print_summary(summary, False)
    out = capsys.readouterr().out
    assert ("RECONFIGURED at t=+6.050 s: drive fl lost (torque), front carrier on its remaining wheels until "
            "t=+31.000 s: IDLE") in out


def test_the_panel_shows_the_reconfiguration_while_running():
    from rig_runtime.app.panel import render
    from tests.test_panel import text_of
    msg = "RECONFIGURED: drive fl lost (drive fl (node 1): EMCY 0x5000 device hardware); front carrier on fr alone"
    events = [(6.05, "reconfigured", "", "", 0.0, 0.0, msg)]
    out = text_of(render({"state": float(State.RUNNING)}, {}, events), width=200)
    assert "RECONFIGURED: drive fl lost" in out
    out = text_of(render({"state": float(State.IDLE)}, {}, events), width=200)
    assert "RECONFIGURED" not in out


def test_a_wheel_speed_out_of_range_is_a_fault_not_a_lost_drive(vcfg, vtable):
    r = Vehicle(vcfg, vtable)
    t = r.k * H
    sm = {w: Sample(10.0, t, FRESH, 0) for w in WHEELS}
    sm["fl"] = Sample(1000.0, t, FRESH, 0)
    r.s.cycle(t, sm, conv(), [("front", 0.0, 0.0), ("rear", 0.0, 0.0)], 0, True, "")
    assert r.s.state is State.FAULT and (r.s.fault.device, r.s.fault.check) == ("fl", "range")
    assert not r.s.wheels_lost


def test_telemetry_status_names_the_lost_drives():
    from rig_runtime.app.telemetry import status_parts
    assert status_parts({"wheels_lost": ["fl"], "timing": {"deadline_misses": 0}})["reconfigured"] == {"fl": 1}
    assert "reconfigured" not in status_parts({"wheels_lost": []})
