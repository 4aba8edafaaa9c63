"""``rig commission`` against the simulated rig in lockstep (the simulated operator moves the
vehicle): the shipped wiring passes; each miswiring of issue 21 fails and the report names
it; a CAN tap sees the power stages enabled only during the bumps and no current beyond
the bump's amplitude. Plus the command's bad input and the commissioning record."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import pytest

from drivers import cia402 as co
from rig_runtime import config
from rig_runtime.app.export import read_log
from rig_runtime.safety import State
from rig_runtime.app.commission import CHECKS, record
from rig_runtime.app.commission.procedure import BUMP_WIRE_A, run_lockstep


def _cfg(**mw):
    cfg = config.load(None)
    return dataclasses.replace(cfg, sim={**(cfg.sim or {}), **({"miswire": mw} if mw else {})})


def _faults(rep):
    return [f for i in rep.items for f in i.faults]


def test_the_shipped_wiring_passes_and_the_tap_sees_power_only_in_the_bumps(tmp_path):
    cfg = _cfg()
    taps = []
    rep = run_lockstep(cfg, prepare=lambda sim: taps.append(sim.runtime_bus()), log_prefix=tmp_path / "c")
    assert rep.passed, rep.text()
    assert [i.name for i in rep.items] == list(CHECKS)
    for c in ("rear", "front"):                     # each bump is a normal log
        log = read_log(tmp_path / f"c-bump-{c}.h5")
        wheel = "i_rl" if c == "rear" else "i_fl"
        assert State.RUNNING in log["columns"]["state"] and log["columns"][wheel].max() > 0.25
    rear = next(i for i in rep.items if i.name == "bump-rear").measured
    assert rear["dpsi_mrad"] > 0.5 and 0.5 <= rear["relation4_ratio"] <= 1.5
    rated = {d.node_id: d.rated_current_A for d in cfg.devices.can.drives}
    syncs, enabled_syncs, currents = 0, [], []
    while (m := taps[0].recv(0)) is not None:
        cid = m.arbitration_id
        if cid == co.COB_SYNC:
            syncs += 1
        elif co.COB_RPDO1 < cid <= co.COB_RPDO1 + 127 and len(m.data) == co.RPDO1.size:
            cw, tq = co.decode_rpdo1(m.data)
            i = co.permille_to_amps(tq, rated[cid - co.COB_RPDO1])
            if cw == co.CW_ENABLE_OPERATION:
                enabled_syncs.append(syncs)
            else:
                assert i == 0.0, (syncs, cw, i)         # current only with the power stage commanded on
            currents.append(abs(i))
    # enable operation in exactly two blocks of SYNCs (the rear bump, then the front bump), none
    # during the passive windows (2.2 s + 1 s of 5 ms cycles), and never more than the bump's current
    # (to the wire's resolution)
    ks = sorted(set(enabled_syncs))
    blocks = 1 + sum(1 for a, b in zip(ks, ks[1:]) if b > a + 1)
    assert blocks == 2 and ks[0] > 640, (blocks, ks[:3])
    # the wire carries thousandths of the rated current (8 A): 0.3 A is sent as 38 ‰ = 0.304 A
    assert 0 < max(currents) <= BUMP_WIRE_A + max(rated.values()) / 1000


@pytest.mark.parametrize("mw, fault", [
    ({"laser_sign": ["b_r"]}, "b_r reads with the wrong sign"),
    ({"laser_swap": [["s_fl", "s_fr"]]}, "s_fl and s_fr appear swapped"),
    ({"laser_swap": [["s_fl", "s_rr"]]}, "s_fl and s_rr appear swapped (s_fl moves with the rear carrier"),
    ({"encoder_sign": ["rl"]}, "encoder rl reads with the wrong sign"),
    ({"current_sign": ["rl"]}, "drive rl or rr current polarity appears inverted"),
    ({"node_swap": [["rl", "rr"]]}, "drives rl and rr appear swapped: drive node 3 moves wheel rr"),
])
def test_each_miswiring_fails_naming_the_fault(mw, fault):
    rep = run_lockstep(_cfg(**mw))
    assert not rep.passed
    assert any(fault in f for f in _faults(rep)), rep.text()


def _rig(*argv, **kw):
    env = {**os.environ, **kw.pop("env", {})}
    return subprocess.run([sys.executable, "-m", "rig_runtime", *argv], capture_output=True, text=True,
                          timeout=60, env=env, **kw)


def test_an_unknown_check_is_one_line_and_exit_2():
    r = _rig("commission", "--only", "lasers,wiring", "--yes")
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "unknown check 'wiring'" in r.stderr and "bump-rear" in r.stderr


def test_no_terminal_without_yes_is_one_line_and_exit_2():
    r = _rig("commission", stdin=subprocess.DEVNULL)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "stdin is not a terminal" in r.stderr and "--yes" in r.stderr


def test_the_record_knows_a_passed_commissioning_of_this_config_only(tmp_path):
    p = tmp_path / "rec.jsonl"
    cfg = config.load(None)
    assert not record.passed_on_record(cfg, p)
    record.append(cfg, False, CHECKS, p)
    assert not record.passed_on_record(cfg, p)
    record.append(cfg, True, ("lasers",), p)        # a partial run is not a commissioning
    assert not record.passed_on_record(cfg, p)
    record.append(cfg, True, CHECKS, p)
    assert record.passed_on_record(cfg, p)
    other = dataclasses.replace(cfg, devices=dataclasses.replace(
        cfg.devices, can=dataclasses.replace(cfg.devices.can, drives=tuple(
            dataclasses.replace(d, node_id=d.node_id + 10) for d in cfg.devices.can.drives))))
    assert not record.passed_on_record(other, p)


def test_rig_run_warns_without_a_passed_commissioning(tmp_path):
    r = _rig("run", "--config", str(config.CONFIG_DIR / "rig.yaml"), "--duration", "1", "--no-panel", "--no-ctl",
             "--log", str(tmp_path / "r.h5"), env={"RIG_COMMISSION_RECORD": str(tmp_path / "none.jsonl")},
             stdin=subprocess.DEVNULL)
    assert "warning: no passed commissioning on record for this config" in r.stderr, r.stderr
