"""``rig commission`` against the simulated rig in lockstep (the simulated operator moves the
vehicle and lifts the carriers): the shipped wiring passes; each miswiring of issue 21 (and
encoder cables crossed) fails exactly the checks that can see it, and the report names it;
a CAN tap sees the power stages enabled only during the bumps and no current beyond the
bump's amplitude; the report is a normal log ``rig log info`` shows. Plus the command's bad
input and the commissioning record."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest

from drivers import cia402 as co
from rig_runtime import config
from rig_runtime.app import runlog
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
    for check in ("lifted-rear", "lifted-front", "bump-rear", "bump-front"):    # each bump is a normal log
        log = read_log(tmp_path / f"c-{check}.h5")
        wheel = "i_rl" if check.endswith("rear") else "i_fl"
        assert State.RUNNING in log["columns"]["state"] and log["columns"][wheel].max() > 0.25
    items = {i.name: i.measured for i in rep.items}
    assert items["bump-rear"]["dpsi_mrad"] > 0.5 and 0.5 <= items["bump-rear"]["relation4_ratio"] <= 1.5
    # lifted: each wheel of the pulsed pair spins freely its own way, k_tau i t / J_x = 3 rad/s
    assert items["lifted-rear"]["dw_rl_rad_s"] > 2 and items["lifted-rear"]["dw_rr_rad_s"] < -2
    assert abs(items["lifted-rear"]["dw_fl_rad_s"]) < 0.3
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
    # enable operation in exactly four blocks of SYNCs (the two lifted bumps, the two on the rollers),
    # none during the passive windows (the lasers' 2.2 s of 5 ms cycles come first), and never more
    # than the bump's current (to the wire's resolution)
    ks = sorted(set(enabled_syncs))
    blocks = 1 + sum(1 for a, b in zip(ks, ks[1:]) if b > a + 1)
    assert blocks == 4 and ks[0] > 440, (blocks, ks[:3])
    # the wire carries thousandths of the rated current (8 A): 0.3 A is sent as 38 ‰ = 0.304 A
    assert 0 < max(currents) <= BUMP_WIRE_A + max(rated.values()) / 1000


def test_the_report_is_a_normal_log_rig_log_info_shows(tmp_path):
    rep = run_lockstep(_cfg(current_sign=["rl"]), ("lasers", "lifted-rear", "encoders", "bump-rear"),
                       log_prefix=tmp_path / "c")
    assert rep.log == str(tmp_path / "c.h5")
    run = runlog.load(rep.log)
    cols = run.columns
    # the passive windows' cycles: the lasers' 2.2 s and the encoders' 1 s, power off, every laser read
    assert run.rows == 640 and set(cols["state"]) == {float(State.IDLE)} and cols["i_rl"].max() == 0.0
    assert all(np.isfinite(cols[r][-200:]).all() for r in ("b_f", "s_rl", "omega_rl"))
    d = runlog.info(run)
    got = {(e["check"], e["what"]) for e in d["commission"]}
    assert got == {("lasers", "pass"), ("lifted-rear", "fail"), ("lifted-rear", "likely fault"), ("lifted-rear", "log"),
                   ("encoders", "pass"), ("encoders", "note"), ("bump-rear", "fail"), ("bump-rear", "likely fault"),
                   ("bump-rear", "log"), ("commissioning", "fail")}, got
    text = "\n".join(runlog.format_info(d))
    assert "lifted-rear FAIL: u_A=+0.600" in text and "dw_rl_rad_s=-3." in text
    assert "likely fault: drive rl current polarity appears inverted" in text
    assert f"bump-rear log: {tmp_path / 'c-bump-rear.h5'}" in text


@pytest.mark.parametrize("mw, failed, fault", [
    ({"laser_sign": ["b_r"]}, {"lasers"}, "b_r reads with the wrong sign"),
    ({"laser_swap": [["s_fl", "s_fr"]]}, {"lasers", "bump-front"}, "s_fl and s_fr appear swapped"),
    ({"laser_swap": [["s_fl", "s_rr"]]}, {"lasers", "bump-rear"},
     "s_fl and s_rr appear swapped (s_fl moves with the rear carrier"),
    ({"laser_swap": [["b_f", "b_r"]]}, {"lasers"}, "b_f and b_r appear swapped (b_f moves most when the rear end"),
    ({"encoder_sign": ["rl"]}, {"encoders", "bump-rear"}, "encoder rl reads with the wrong sign"),
    ({"current_sign": ["rl"]}, {"lifted-rear", "bump-rear"}, "drive rl current polarity appears inverted (node 3"),
    ({"current_sign": ["rl"], "encoder_sign": ["rl"]}, {"lifted-rear", "encoders", "bump-rear"},
     "drive rl current polarity appears inverted (node 3: wheel rl turned -3.0"),
    ({"current_sign": ["fl"]}, {"lifted-front", "bump-front"},
     "drive fl current polarity appears inverted (node 1: wheel fl turned -3.0"),
    ({"node_swap": [["rl", "rr"]]}, {"bump-rear"}, "drives rl and rr appear swapped: drive node 3 moves wheel rr"),
    ({"node_swap": [["rl", "fl"]]}, {"encoders", "bump-rear"}, "drives rl and fl appear swapped: drive node 3 (rl)"),
    ({"encoder_swap": [["rl", "fl"]]}, {"lifted-rear", "lifted-front", "encoders"},
     "the rear pulse (drive nodes 3, 4) is answered at drive node 1 (fl"),
    ({"encoder_swap": [["rl", "rr"]]}, {"lifted-rear", "bump-rear"}, "wheels rl and rr both turned backwards"),
])
def test_each_miswiring_fails_naming_the_fault(mw, failed, fault):
    rep = run_lockstep(_cfg(**mw))
    assert {i.name for i in rep.items if not i.passed} == failed, rep.text()
    assert any(fault in f for f in _faults(rep)), rep.text()
    assert not any("rl or rr" in f for f in _faults(rep)), rep.text()      # the lifted bump names the wheel


def test_a_lifted_bump_on_the_rollers_fails_asking_whether_it_is_lifted():
    rep = run_lockstep(_cfg(), checks=("lifted-rear",), lifted_sessions=0)      # the operator did not lift it
    assert not rep.passed
    assert any("wheel rl does not answer" in f and "is the rear carrier lifted?" in f for f in _faults(rep)), rep.text()


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
