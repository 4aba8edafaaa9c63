"""Drive outages end to end (lockstep, the simulated rig): an announced motor outage of one
wheel of the leading carrier, in both directions, runs on RECONFIGURED to the end
(configs/vehicle.yaml, the 2 mm steps of vehicle-steps); the failed drive carries 0 A from
that cycle, in the log and on the wire; the paper's set-up reconfigures onto the remaining
rear wheel. The measured numbers are docs/safety.md's ("Drive outages")."""

import dataclasses

import numpy as np
import pytest

from drivers import cia402 as co
from rig_runtime import config
from rig_runtime.app import runlog
from rig_runtime.scenario import FaultInjection, SpeedPoint, load_scenario

from .e2e import run

T_OUT = 6.0         # scenario time of the outage (after the front's step at 1 s, before the rear's at 11 s)


def _outage_run(tmp_path, cfg, scenario, wheel, v=None, mode="announced", taps=None):
    sc = load_scenario(scenario)
    kw = {} if v is None else {"speed": (SpeedPoint(t=0, v=v),)}
    sc = dataclasses.replace(sc, faults=(FaultInjection(kind="motor_outage", t=T_OUT, device=wheel, mode=mode),), **kw)
    prepare = None if taps is None else (lambda sim, devices, clock: taps.append(sim.runtime_bus()))
    return run(tmp_path, sc, cfg=cfg, prepare=prepare)


def _controlwords(tap, node: int) -> list[tuple[int, int]]:
    """(SYNC index, controlword) of every RPDO1 to ``node`` a CAN tap saw."""
    out, syncs = [], 0
    while (m := tap.recv(0)) is not None:
        if m.arbitration_id == co.COB_SYNC:
            syncs += 1
        elif m.arbitration_id == co.COB_RPDO1 + node and len(m.data) == co.RPDO1.size:
            out.append((syncs, co.decode_rpdo1(m.data)[0]))
    tap.shutdown()
    return out


def _check_reconfigured(r, cfg, wheel, carrier, within_s=2 * 0.005):
    s = r.summary
    assert s["final_state"] == "IDLE" and s["faults"] == [] and r.code == 0, s["faults"]
    (e,) = s["reconfigured"]
    assert (e["device"], e["carrier"], e["end"]) == (wheel, carrier, "IDLE") and e["t_end"] is not None
    t, t_run = r.col("t"), r.col("t_run")
    k = int(np.argmin(np.abs(t - e["t_start"])))
    # announced: RECONFIGURED in the cycle whose poll brings the drive's EMCY, within 2 cycles
    # of the outage; silent: the torque response rule after degraded.torque_hold_s
    assert 0 <= t_run[k] - T_OUT <= within_s + 1e-9, t_run[k]
    # 0 A for the failed drive from that cycle, in the log and on the wire (the RPDOs after SYNC k+1)
    assert np.all(r.col(f"i_{wheel}")[k:] == 0.0) and np.any(r.col(f"i_{wheel}")[:k] != 0.0)
    assert all(i == 0.0 for n, w, i in r.wire if w == wheel and n >= k + 1)
    assert all(abs(i) <= cfg.limits.u_max for _, _, i in r.wire)
    # the summary's largest wheel current covers the lone wheel's (one per mille of rated on the wire)
    assert s["max_abs_wire_current_A"] >= max(abs(i) for _, _, i in r.wire) - 0.01
    return k


@pytest.mark.parametrize("v, wheel, carrier", [(1.0, "fl", "front"), (-1.0, "rl", "rear")],
                         ids=["forward-fl", "reverse-rl"])
def test_an_announced_outage_of_the_leading_carrier_runs_on_reconfigured(tmp_path, v, wheel, carrier):
    cfg = config.load(config.resolve_config_path("vehicle.yaml"))
    assert cfg.degraded.on_drive_loss == "reallocate"
    r = _outage_run(tmp_path, cfg, "vehicle-steps", wheel, v)
    k = _check_reconfigured(r, cfg, wheel, carrier)
    d = runlog.info(runlog.load(r.log_path))                # rig log info names it from the log
    (g,) = d["reconfigured"]
    assert g["why"].startswith(f"RECONFIGURED: drive {wheel} lost") and abs(g["t_start"] - (T_OUT + 0.05)) < 0.06
    assert any(line.startswith("RECONFIGURED (run time") for line in runlog.format_info(d))
    for c in ("f", "r"):                                 # |y| below y_max/2 after the outage, both carriers
        y = np.abs(r.col(f"y_{c}")[k:])
        print(f"v {v:+g}, {wheel} lost: max |y_{c}| after the outage {y.max() * 1e3:.3f} mm")
        assert y.max() < cfg.limits.y_max / 2
    steps = [st for st in r.summary["steps"] if st["t0"] > T_OUT]
    assert len(steps) == 3
    for st in steps:                                     # every step after the outage still tracked
        print(f"  step {st['carrier']} at {st['t0']:g} s: steady-state error {st['steady_state_error_mm'] * 1e3:.1f} um")
        assert abs(st["steady_state_error_mm"]) <= 0.02 * abs(st["to_mm"] - st["from_mm"]), st


def test_the_paper_setup_reconfigures_onto_the_remaining_rear_wheel(tmp_path):
    cfg = config.load()
    assert cfg.degraded.on_drive_loss == "reallocate"          # as shipped (configs/sim.yaml)
    r = _outage_run(tmp_path, cfg, "single-step", "rl")
    _check_reconfigured(r, cfg, "rl", "rear")
    assert np.abs(r.col("y_r")).max() < cfg.limits.y_max / 2


@pytest.mark.parametrize("v", [1.0, -1.0], ids=["forward", "reverse"])
@pytest.mark.parametrize("wheel", ["fl", "fr", "rl", "rr"])
def test_a_silent_outage_is_detected_within_0_3_s_and_reconfigured(tmp_path, wheel, v):
    """The drive stays OPERATION ENABLED and answers every SYNC, but its wheel gets no torque
    (its torque actual: 0 A): the torque response rule finds it, the run goes on RECONFIGURED."""
    cfg = config.load(config.resolve_config_path("vehicle.yaml"))
    taps = []
    r = _outage_run(tmp_path, cfg, "vehicle-steps", wheel, v, mode="silent", taps=taps)
    k = _check_reconfigured(r, cfg, wheel, "front" if wheel[0] == "f" else "rear", within_s=0.3)
    # a CAN tap: the failed drive quick-stopped, then disabled, from the next cycle to the end
    node = next(d.node_id for d in cfg.devices.can.drives if d.wheel == wheel)
    cws = [cw for n, cw in _controlwords(taps[0], node) if n >= k + 2]
    assert cws and cws[0] == co.CW_QUICK_STOP and set(cws) <= {co.CW_QUICK_STOP, co.CW_DISABLE_VOLTAGE}
    assert co.CW_DISABLE_VOLTAGE in cws
    (e,) = r.summary["reconfigured"]
    assert e["check"] == "torque"
    print(f"silent {wheel} v {v:+g}: detected {r.col('t_run')[k] - T_OUT:.3f} s after the outage")
    for c in ("f", "r"):
        assert np.abs(r.col(f"y_{c}")[k:]).max() < cfg.limits.y_max / 2
    for st in (st for st in r.summary["steps"] if st["t0"] > T_OUT):
        assert abs(st["steady_state_error_mm"]) <= 0.02 * abs(st["to_mm"] - st["from_mm"]), st


@pytest.mark.parametrize("carrier, v, goes_on", [("front", 1.0, False), ("front", -1.0, True),
                                                 ("rear", 1.0, True), ("rear", -1.0, False)],
                         ids=["front-forward", "front-reverse", "rear-forward", "rear-reverse"])
def test_both_motors_of_a_carrier_lost_is_what_the_analysis_decides(tmp_path, carrier, v, goes_on):
    """The trailing carrier uncontrolled: the other carrier holds both (RECONFIGURED to the
    end); the leading one: the fault, naming the analysis' answer (docs/safety.md's table)."""
    cfg = config.load(config.resolve_config_path("vehicle.yaml"))
    sc = load_scenario("vehicle-steps")
    wheels = ("fl", "fr") if carrier == "front" else ("rl", "rr")
    sc = dataclasses.replace(sc, speed=(SpeedPoint(t=0, v=v),),
                             faults=tuple(FaultInjection(kind="motor_outage", t=T_OUT, device=w) for w in wheels))
    r = run(tmp_path, sc, cfg=cfg)
    s = r.summary
    if not goes_on:
        assert s["final_state"] == "FAULT" and s["faults"][0]["check"] == "converter"
        msg = s["faults"][0]["message"]
        assert f"not reconfigured: {carrier} carrier uncontrolled: sampled loop spectral radius" in msg, msg
        assert msg.endswith("(not stable)")
        return
    assert s["final_state"] == "IDLE" and s["faults"] == []
    (e,) = s["reconfigured"]
    assert e["device"] == "/".join(wheels) and e["end"] == "IDLE"
    k = int(np.argmin(np.abs(r.col("t") - e["t_start"])))
    for w in wheels:
        assert np.all(r.col(f"i_{w}")[k:] == 0.0)
    for c in ("f", "r"):
        y = np.abs(r.col(f"y_{c}")[k:]).max()
        print(f"{carrier} lost, v {v:+g}: max |y_{c}| after the outage {y * 1e3:.3f} mm")
        assert y < cfg.degraded.limits.y_max          # within the RECONFIGURED limit (the run went on)


@pytest.mark.parametrize("scenario, wheel, t_lost", [("fault-no_heartbeat", "rl", 3.0), ("fault-two-wheels", "rr", 2.51)])
def test_the_shipped_drive_fault_scenarios_reconfigure_on_the_shipped_sim_config(tmp_path, scenario, wheel, t_lost):
    """configs/sim.yaml reallocates: a drive whose heartbeat stops is isolated once its
    heartbeat is missing for the consumer's timeout, the rear carrier runs on its other wheel to
    the end of the scenario, and the lost drive carries 0 A from that cycle (with
    ``on_drive_loss: stop`` the same scenarios are the converter fault, tests/test_faults_e2e.py)."""
    cfg = config.load()
    r = run(tmp_path, scenario, cfg=cfg)
    s = r.summary
    assert s["final_state"] == "IDLE" and s["faults"] == [] and r.code == 0, s["faults"]
    (e,) = s["reconfigured"]
    assert (e["device"], e["carrier"], e["end"]) == (wheel, "rear", "IDLE") and e["check"] == "converter"
    t, t_run = r.col("t"), r.col("t_run")
    k = int(np.argmin(np.abs(t - e["t_start"])))
    # the consumer's timeout after the drive's last heartbeat (at most one producer period before t_lost)
    period = next(d.heartbeat_ms for d in cfg.devices.can.drives if d.wheel == wheel) / 1000
    timeout = period * cfg.devices.can.heartbeat_timeout_factor
    assert t_lost + timeout - period <= t_run[k] + 1e-9 <= t_lost + timeout + 2 * cfg.controller.h, t_run[k]
    assert np.all(r.col(f"i_{wheel}")[k:] == 0.0) and np.any(r.col(f"i_{wheel}")[:k] != 0.0)
    assert all(i == 0.0 for n, w, i in r.wire if w == wheel and n >= k + 1)
    assert np.abs(r.col("y_r")).max() < cfg.limits.y_max / 2
