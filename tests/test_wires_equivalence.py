"""In-memory wires and kernel wires give the same log (issue 26, item 1).

``sim.wires: memory`` (the default) carries the lasers' frames on in-process serial lines
and the F/T Modbus TCP frames on in-process streams (rig_runtime/wires.py); ``kernel``
carries the same bytes on pty pairs and loopback TCP. The drivers and the codecs are the
same on both. A lockstep run of each scenario over both must give bit-identical cycle
columns (every column but ``work``, the wall-clock compute time of a cycle) and the same
events. Durations are cut short, each past the scenario's step or fault. Besides the
shipped scenarios, ``ft-faults`` takes the F/T wire through its timeouts, garbled replies
and reconnects.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rig_runtime import config
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.app.export import read_log
from rig_runtime.scenario import FaultInjection, RefPoint, Scenario, load_scenario

from .e2e import shipped_config_for

# the F/T wire's own failure paths (no shipped scenario has them): a sensor that stops
# answering (timeouts, reconnects) and one that garbles its replies (bad frames,
# reconnects), each shorter than the supervisor's 0.5 s (limits.ft_stale_s, the corrupt
# window), so the run goes on over the recovery
FT_FAULTS = Scenario(name="ft-faults", duration_s=1.5,
                     reference=(RefPoint(t=0.0, y_mm=0.0), RefPoint(t=0.2, y_mm=1.0)),
                     faults=(FaultInjection(kind="dropout", t=0.3, duration_s=0.3, device="ft_rl"),
                             FaultInjection(kind="corrupt", t=0.3, duration_s=0.3, device="ft_fr")))

WALL_CLOCK_COLUMNS = {"work"}       # the cycle's compute time, measured on the wall clock

# scenario -> RUNNING seconds: past the step (single-step 1 s, vehicle-steps 1 s), the fault
# (fault-corrupt 3 s, degraded-dropout 8 s, ft-faults 0.3 s and their end 0.6 s) or the
# first input step (ident-steps 10 s)
CASES = {
    "single-step": 1.6,
    "fault-corrupt": 3.4,
    "degraded-dropout": 8.5,
    "vehicle-steps": 1.6,
    "ident-steps": 10.5,
    FT_FAULTS.name: 1.5,
}


def _run(tmp_path, name: str, wires: str, duration_s: float, prepare=None) -> tuple[dict, dict]:
    path = shipped_config_for(name)
    cfg = config.load(path) if path else config.load()
    cfg = dataclasses.replace(cfg, sim={**(cfg.sim or {}), "wires": wires})
    log = tmp_path / f"{name}-{wires}.h5"
    scenario = FT_FAULTS if name == FT_FAULTS.name else load_scenario(name)
    summary, _ = run_lockstep(cfg, scenario, log, duration_s=duration_s, prepare=prepare)
    return summary, read_log(log)


@pytest.fixture(scope="module")
def memory_run(tmp_path_factory):
    """``memory_run(name)``: ``_run`` of a case over memory wires for its CASES duration, made
    once per module and shared by the tests that only read it (the equivalence test and the
    check that the cut durations reach the fault)."""
    done: dict = {}

    def get(name: str) -> tuple[dict, dict]:
        if name not in done:
            done[name] = _run(tmp_path_factory.mktemp("memory"), name, "memory", CASES[name])
        return done[name]
    return get


@pytest.mark.parametrize("name", sorted(CASES))
def test_memory_and_kernel_wires_give_the_same_log(tmp_path, name, memory_run):
    s_mem, mem = memory_run(name)
    s_ker, ker = _run(tmp_path, name, "kernel", CASES[name])
    assert mem["rows"] == ker["rows"] > 0
    assert list(mem["columns"]) == list(ker["columns"])
    differ = [c for c in mem["columns"] if c not in WALL_CLOCK_COLUMNS
              and mem["columns"][c].tobytes() != ker["columns"][c].tobytes()]
    assert differ == []
    assert mem["events"].keys() == ker["events"].keys()
    for field in mem["events"]:
        a, b = np.asarray(mem["events"][field]), np.asarray(ker["events"][field])
        if a.dtype == object:
            assert list(a) == list(b), field
        else:                                       # numbers, NaN included: bit for bit
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), field
    assert s_mem["final_state"] == s_ker["final_state"]
    assert s_mem["faults"] == s_ker["faults"]


def test_the_scenarios_reach_their_fault_and_step(memory_run):
    """The cut durations still contain what each scenario is about: fault-corrupt trips the
    corrupt check, degraded-dropout goes DEGRADED (memory wires: the runs the equivalence
    test compared)."""
    _, log = memory_run("fault-corrupt")
    assert "corrupt" in set(log["events"]["check"])
    _, log = memory_run("degraded-dropout")
    kinds = set(log["events"]["kind"]) | set(log["events"]["message"])
    assert any("DEGRADED" in str(k) or "degraded" in str(k) for k in kinds)


def test_the_ft_faults_reach_the_driver(tmp_path):
    """The F/T case is not trivially equal: over memory wires the driver times out on the
    silent sensor and rejects the garbled replies, reconnects to both, and the run goes on."""
    devices, last = [], {}

    def prepare(sim, dev, clock):          # keep the F/T driver's last readings
        poll = dev.ft.poll

        def keep(now):
            readings = poll(now)
            last.update(readings)
            return readings
        dev.ft.poll = keep
        devices.append(dev)

    summary, _ = _run(tmp_path, FT_FAULTS.name, "memory", FT_FAULTS.duration_s, prepare=prepare)
    assert summary["final_state"] == "IDLE" and summary["faults"] == []
    assert last["ft_rl"].health.timeouts >= 1 and last["ft_fr"].health.bad_frames >= 1
    assert last["ft_fl"].health.timeouts == last["ft_fl"].health.bad_frames == 0
    c = devices[0].ft.counters()
    assert c["ft_rl.connects"] >= 2 and c["ft_fr.connects"] >= 2 and c["ft_fl.connects"] == 1


def test_the_wires_are_what_the_setting_says(tmp_path):
    """memory: mem:// URLs for the lasers and the F/T endpoints; kernel: pty paths and
    127.0.0.1 ports."""
    from sim_backend.rig import SimulatedRig
    cfg = config.load()
    for wires, laser_prefix, ft_prefix in (("memory", "mem://", "mem://"), ("kernel", "/dev/", "127.0.0.1")):
        c = dataclasses.replace(cfg, sim={**(cfg.sim or {}), "wires": wires})
        with SimulatedRig(c) as sim:
            assert all(p.startswith(laser_prefix) for p in sim.laser_ports.values())
            assert all(h.startswith(ft_prefix) for h, _ in sim.ft_endpoints.values())
            assert sim.ft_endpoints


def test_sim_wires_is_checked():
    from rig_runtime.errors import ConfigError
    from sim_backend.simconfig import sim_config
    cfg = config.load()
    with pytest.raises(ConfigError):
        sim_config(dataclasses.replace(cfg, sim={**(cfg.sim or {}), "wires": "carrier-pigeon"}))
