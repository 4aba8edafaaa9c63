"""The loop carries out operator commands from a mailbox, in lockstep against the simulated
plant (the loop built as rig_runtime/app/dryrun.py builds it). Commands are submitted by
the test between cycles, from the lockstep clock's advance callback."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig_runtime.clock import LockstepClock
from rig_runtime.config import LASER_ROLES, WHEELS
from rig_runtime.devices import Reading, RigDevices
from rig_runtime.hardware import Freshness, Health
from rig_runtime.loop import ControlLoop
from rig_runtime.mailbox import SIZE, Mailbox
from rig_runtime.safety import Channel, Converters, Sample, State
from rig_runtime.scenario import Reference, load_scenario
from sim_backend.rig import SimulatedRig


class MemRecorder:
    healthy = True
    error = ""

    def __init__(self):
        self.rows, self.events = [], []

    def append(self, row):
        self.rows.append(list(row))
        return True

    def event(self, t, kind, device="", check="", value=math.nan, limit=math.nan, message=""):
        self.events.append((t, kind, device, check, value, limit, message))


def run_loop(cfg, scenario_name, duration_s, script, hold_on_fault=False, **run_kw):
    """Run the loop; ``script(loop, server, t)`` runs before every release ``t`` (between
    two cycles) and may submit commands through ``server``."""
    sc = load_scenario(scenario_name)
    sim = SimulatedRig(cfg, sc, seed=0)
    try:
        buf = bytearray(SIZE)
        server = Mailbox(memoryview(buf))
        holder = {}

        def advance(t):
            script(holder["loop"], server, t)
            return sim.advance(t)

        clock = LockstepClock(advance=advance)
        devices = RigDevices(cfg, laser_ports=sim.laser_ports, can_bus=sim.runtime_bus(),
                             ft_endpoints=sim.ft_endpoints)
        rec = MemRecorder()
        loop = holder["loop"] = ControlLoop(cfg, devices, clock, reference=Reference(sc.reference), recorder=rec,
                                            mailbox=Mailbox(memoryview(buf)))
        try:
            devices.configure()
            result = loop.run(duration_s, hold_on_fault=hold_on_fault, **run_kw)
        finally:
            devices.close()
    finally:
        sim.close()
    cols = {n: np.array([r[i] for r in rec.rows]) for i, n in enumerate(loop.columns)}
    return loop, result, rec, cols


class Script:
    """Submit commands at run times; collect the answers."""

    def __init__(self, plan):
        self.plan = list(plan)          # (t_run, kind, name, value)
        self.pending = []
        self.answers = []

    def __call__(self, loop, server, t):
        for seq, what in list(self.pending):
            r = server.result(seq)
            if r is not None:
                self.answers.append((what, r))
                self.pending.remove((seq, what))
        if self.plan and loop.t_start is not None and t - loop.t_start >= self.plan[0][0]:
            _, kind, name, value = what = self.plan.pop(0)
            self.pending.append((server.submit(kind, name, value), what))


def test_set_gain_is_applied_from_the_next_cycle_and_recorded(cfg):
    s = Script([(1.5, "reset-fault", "", math.nan), (2.0, "set", "K_P_y", 4.5), (3.0, "set", "K_P_psi", 60.0)])
    loop, result, rec, c = run_loop(cfg, "single-step", 4.0, s)
    assert result.final_state == "IDLE" and result.faults == []
    assert [a for _, a in s.answers] == [(False, "no latched fault (state RUNNING)"),
                                         (True, "K_P_y 3 -> 4.5"), (True, "K_P_psi 40 -> 60")]
    ops = [e for e in rec.events if e[1] == "operator" and e[2] == "controller"]
    assert [e[2:] for e in ops] == [("controller", "K_P_y", 4.5, 3.0, "K_P_y 3 -> 4.5"),
                                    ("controller", "K_P_psi", 60.0, 40.0, "K_P_psi 40 -> 60")]
    assert loop.gains() == {**loop.gains(), "K_P_y": 4.5, "K_P_psi": 60.0}
    t = c["t"]
    k1 = int(np.searchsorted(t, ops[0][0]))        # the cycle that took the command (its t is the event's)
    k2 = int(np.searchsorted(t, ops[1][0]))
    assert t[k1] == ops[0][0] and t[k2] == ops[1][0] and 100 < k1 < k2
    run = c["state"] == float(State.RUNNING)
    # outer PI: psi_ref = K_P_y e_y + K_I_y x_I (psi_ref not clipped here) with the old gain before, the new one from k1
    kpy = np.where(np.arange(len(t)) < k1, 3.0, 4.5)
    psi_ref = kpy * c["rear_e_y"] + 9.0 * c["rear_x_I"]
    assert np.allclose(psi_ref[run], c["rear_psi_ref"][run], rtol=0, atol=1e-12)
    # bumpless: at the change psi_ref moves no more than in the cycles around it, far less than 1.5 e_y
    dpsi = np.abs(np.diff(c["rear_psi_ref"]))
    assert dpsi[k1 - 1] < 3 * max(dpsi[k1 - 20:k1 - 1].max(), dpsi[k1:k1 + 20].max())
    assert dpsi[k1 - 1] < 0.2 * 1.5 * abs(c["rear_e_y"][k1])
    # inner PD: u_unsat = K_P_psi e_psi + K_D_psi de_psi with 40 before k2 and 60 from k2
    kpp = np.where(np.arange(len(t)) < k2, 40.0, 60.0)
    u = kpp * c["rear_e_psi"] + 5.0 * c["rear_de_psi"]
    assert np.allclose(u[run], c["rear_u_unsat"][run], rtol=1e-12, atol=1e-12)
    assert not np.allclose((40.0 * c["rear_e_psi"] + 5.0 * c["rear_de_psi"])[k2:][run[k2:]],
                           c["rear_u_unsat"][k2:][run[k2:]], rtol=1e-12, atol=1e-12)


def test_the_loop_refuses_a_set_outside_bounds_whoever_posted_it(cfg):
    """The mailbox is written by the ctl server after tuning.check; a set posted straight
    into it is still held to the gain's bounds and name by the loop (nothing applied)."""
    s = Script([(1.0, "set", "K_P_y", 60.0), (1.1, "set", "u_max", 5.0), (1.2, "set", "K_P_y", math.inf),
                (1.3, "set", "K_P_y", 5.0)])
    loop, result, rec, c = run_loop(cfg, "single-step", 2.0, s)
    got = [a for _, a in s.answers]
    assert got[0] == (False, "K_P_y = 60 is outside its bounds [1, 6] (controller.tuning)")
    assert not got[1][0] and "u_max is a limit" in got[1][1]
    assert not got[2][0] and "not a finite number" in got[2][1]
    assert got[3] == (True, "K_P_y 3 -> 5")
    assert [e[3:5] for e in rec.events if e[1] == "operator" and e[2] == "controller"] == [("K_P_y", 5.0)]


def test_stop_command_is_a_clean_stop(cfg):
    s = Script([(1.0, "stop", "", math.nan)])
    loop, result, rec, c = run_loop(cfg, "single-step", 10.0, s)
    assert result.final_state == "IDLE" and result.faults == []
    assert [a for _, a in s.answers] == [(True, "stop requested in RUNNING")]
    msgs = [e[6] for e in rec.events]
    assert "stop requested (rig ctl)" in msgs and "RUNNING -> STOPPING: stop requested (rig ctl)" in msgs
    assert c["t_run"][-1] < 2.0                 # well before the 10 s


class FakeDevices:
    """A device set whose sensors read a centred rig (fresh, in range) and whose power
    stages are enabled while active; ``drop`` silences b_f (a dropout: b_f goes stale)."""

    extra_columns = ()

    def __init__(self, cfg):
        self.geo = cfg.geometry
        self.active = False
        self.drop = False
        self.writes = []
        self._b_f_t = math.nan

    def channels(self):
        chs = [Channel(r, "laser", 0.0, 1.0, 0.02) for r in LASER_ROLES]
        return chs + [Channel(w, "wheel", -100.0, 100.0, 0.02) for w in WHEELS]

    def activate(self, now):
        self.active = True

    def deactivate(self, now):
        self.active = False

    def resume(self, now):
        self.resumed = now

    def poll(self, now):
        ok = Health(Freshness.FRESH)
        if not self.drop:
            self._b_f_t = now
        b0 = self.geo.b0
        samples = {"b_f": Sample(b0, self._b_f_t, ok), "b_r": Sample(b0, now, ok)}
        samples.update((r, Sample(0.0375, now, ok)) for r in ("s_fl", "s_fr", "s_rl", "s_rr"))
        samples.update((w, Sample(0.0, now, ok)) for w in WHEELS)
        return Reading(now, samples, {n: s.value for n, s in samples.items()}, (), Converters(True, "", self.active))

    def write(self, currents, now):
        self.writes.append((now, self.active, tuple(currents[w] for w in WHEELS)))


def test_hold_on_fault_until_reset_then_a_new_run(cfg):
    dev = FakeDevices(cfg)
    clock_t = {"fault": math.nan}
    pending, answers = [], []
    buf = bytearray(SIZE)
    server = Mailbox(memoryview(buf))
    holder = {}

    def advance(t):
        loop = holder["loop"]
        for seq, what in list(pending):
            r = server.result(seq)
            if r is not None:
                answers.append((what, r))
                pending.remove((seq, what))
        sup, tr = loop.supervisor, (t - loop.t_start if loop.t_start is not None else math.nan)
        if sup.state is State.RUNNING and math.isnan(clock_t["fault"]) and tr >= 1.5:
            dev.drop = True                     # b_f falls silent: stale after 20 ms -> FAULT
        if sup.state is State.FAULT and math.isnan(clock_t["fault"]):
            clock_t["fault"] = t
            dev.drop = False                    # back at once; the fault stays latched
        if t - clock_t["fault"] >= 1.0 and sup.state is State.FAULT and not pending and not answers:
            pending.append((server.submit("reset-fault"), "reset"))
        if sup.state is State.RUNNING and answers and tr >= 1.0 and len(answers) == 1 and not pending:
            pending.append((server.submit("stop"), "stop"))

    clock = LockstepClock(advance=advance)
    rec = MemRecorder()
    loop = holder["loop"] = ControlLoop(cfg, dev, clock, reference=lambda tr: 0.001 if tr >= 0.2 else 0.0,
                                        recorder=rec, mailbox=Mailbox(memoryview(buf)))
    result = loop.run(2.0, hold_on_fault=True)     # the reset comes after the first run's 2 s were over
    c = {n: np.array([r[i] for r in rec.rows]) for i, n in enumerate(loop.columns)}

    assert [(f["device"], f["check"]) for f in result.faults] == [("b_f", "stale")]
    assert result.final_state == "IDLE"
    assert answers == [("reset", (True, "fault reset: arming again, the scenario restarts when RUNNING")),
                       ("stop", (True, "stop requested in RUNNING"))]
    states = [e[6] for e in rec.events if e[1] == "state"]
    assert states == ["IDLE -> ARMED", "ARMED -> RUNNING", "RUNNING -> FAULT: b_f stale",
                      "FAULT -> IDLE", "IDLE -> ARMED", "ARMED -> RUNNING",
                      "RUNNING -> STOPPING: stop requested (rig ctl)", "STOPPING -> IDLE: stopped"]
    assert [e[6] for e in rec.events if e[1] == "operator"] == ["fault reset", "stop requested (rig ctl)"]
    # held in FAULT 1 s (a run that does not hold ends 0.1 s after the fault): zero current,
    # power stages off, every cycle recorded and written
    held = c["state"] == float(State.FAULT)
    assert held.sum() * cfg.controller.h >= 1.0
    for col in ("rear_u_lim", "i_fl", "i_fr", "i_rl", "i_rr"):
        assert np.all(c[col][held] == 0.0)
    t_held = c["t"][held]
    assert all(not active and cur == (0.0,) * 4 for t, active, cur in dev.writes if t_held[0] <= t <= t_held[-1])
    # the second RUNNING restarted the scenario's time and the controller (bumpless start)
    k = int(np.argmax(held)) + int(held.sum())
    again = k + np.flatnonzero(c["state"][k:] == float(State.RUNNING))
    assert again.size and c["t_run"][again[0]] == 0.0 and c["y_ref"][again[0]] == 0.0
    assert c["y_ref"][again][-1] == 0.001 and np.any(c["rear_u_lim"][again] != 0.0)
    assert result.t_start == c["t"][again[0]]


def test_reset_fault_against_the_simulated_drives_arms_again(cfg):
    """With the simulated CiA 402 drives: the FAULT's deactivate leaves them PRE-OPERATIONAL;
    the reset brings communication back (NMT start, power stages off: ``resume``), the arm
    rules pass on fresh TPDOs, and ARM walks the drives to OPERATION ENABLED again."""
    phase = {"fault_t": math.nan}
    pending, answers = [], []

    def script(loop, server, t):
        for seq, what in list(pending):
            r = server.result(seq)
            if r is not None:
                answers.append((what, r))
                pending.remove((seq, what))
        sup = loop.supervisor
        if sup.state is State.FAULT and math.isnan(phase["fault_t"]):
            phase["fault_t"] = t
        if t - phase["fault_t"] >= 0.5 and sup.state is State.FAULT and not pending and not answers:
            pending.append((server.submit("reset-fault"), "reset"))

    loop, result, rec, c = run_loop(cfg, "fault-during-step", 5.0, script, hold_on_fault=True)
    assert [(f["device"], f["check"]) for f in result.faults][0] == ("s_rl", "stale")
    assert answers == [("reset", (True, "fault reset: arming again, the scenario restarts when RUNNING"))]
    held = c["state"] == float(State.FAULT)
    assert held.sum() * cfg.controller.h >= 0.5
    for col in ("rear_u_lim", "i_fl", "i_fr", "i_rl", "i_rr"):
        assert np.all(c[col][held] == 0.0)
    states = [e[6] for e in rec.events if e[1] == "state"]
    k = states.index(next(x for x in states if x.startswith("FAULT -> IDLE")))
    assert states[k + 1].startswith("IDLE -> ARMED") and states[k + 2].startswith("ARMED -> RUNNING"), states
    after = np.flatnonzero(c["state"] == float(State.RUNNING))
    assert after[-1] > np.flatnonzero(held)[-1]          # running again after the reset


def test_a_failed_rearm_after_reset_ends_the_run_with_its_blockers(cfg):
    """Reset while the cause persists (s_rl silent for 2 s): arming again times out, the loop
    ends in IDLE with power off, and the result names what blocked the arm (the runner makes
    that exit 3, not a quiet 0)."""
    sent = []

    def script(loop, server, t):
        if loop.supervisor.state is State.FAULT and not sent:
            sent.append(server.submit("reset-fault"))

    loop, result, rec, c = run_loop(cfg, "fault-during-step", 5.0, script, hold_on_fault=True, arm_timeout_s=0.5)
    assert result.final_state == "IDLE" and loop.supervisor.arm_failed
    assert any(b.startswith("s_rl:") for b in result.arm_blockers), result.arm_blockers
    assert c["state"][-1] == float(State.IDLE) and np.all(c["rear_u_lim"][c["state"] != float(State.RUNNING)] == 0.0)
    assert rec.rows and c["t"][-1] < 1.4 + 0.1 + 0.5 + 0.2      # ended at the arm deadline, not at 5 s


def test_reset_fault_without_hold_is_refused(cfg):
    got = []

    def script(loop, server, t):
        if loop.supervisor.state is State.FAULT and not got:
            got.append(server.submit("reset-fault"))
        elif got and len(got) == 1:
            r = server.result(got[0])
            if r is not None:
                got.append(r)

    loop, result, rec, c = run_loop(cfg, "fault-stall", 6.0, script)
    assert result.final_state == "FAULT"
    assert got[1] == (False, "no latched fault to reset: this run ends on a fault (it does not hold)")
