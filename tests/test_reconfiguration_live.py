"""A silent motor outage against a real `rig sim` (its own process, real time): the drive
answers every SYNC and stays enabled, its wheel gets no torque; `rig run` finds it by the
torque response rule and runs on RECONFIGURED to the end, as in lockstep
(tests/test_reconfiguration_e2e.py). Then a SIGINT during RECONFIGURED ends it clean."""

from __future__ import annotations

import json
import signal
import subprocess
import time

import pytest

from rig_runtime.config import Degraded
from sim_backend.launcher import start_sim_process

from .e2e import REALTIME_CEILINGS, REALTIME_TOLERANCE, config_with, realtime_sim_config
from .test_sim_process import SIM_RT_ARGS, rig_run_cmd

T_OUT = 3.0
TORQUE_HOLD_S = Degraded().torque_hold_s


def _sim_and_config(tmp_path):
    scen = tmp_path / "silent-rl.yaml"
    scen.write_text("name: silent-rl\nduration_s: 60\nreference: [{t: 0, y_mm: 0}, {t: 1, y_mm: 2.0}]\n"
                    f"faults: [{{kind: motor_outage, t: {T_OUT}, device: rl, mode: silent}}]\n")
    sp = start_sim_process(config=realtime_sim_config(tmp_path), scenario=scen, extra_args=SIM_RT_ARGS,
                           workdir=tmp_path / "sim")
    run_cfg = config_with(sp.config_path, tmp_path / "run.yaml",
                          {**REALTIME_TOLERANCE, "degraded.on_drive_loss": "reallocate",
                           # the detection this test times: the shipped hold, not the stall allowance
                           "degraded.torque_hold_s": TORQUE_HOLD_S}, ceilings=REALTIME_CEILINGS)
    return sp, run_cfg


def _summary(out: str, err: str) -> dict:
    try:
        return json.loads(out.strip().splitlines()[-1])
    except (IndexError, ValueError):
        pytest.fail(f"no JSON summary\nstdout: {out[-2000:]}\nstderr: {err[-3000:]}")


@pytest.mark.slow
def test_a_silent_outage_against_rig_sim_is_detected_and_reconfigured(tmp_path):
    sp, run_cfg = _sim_and_config(tmp_path)
    try:
        log = tmp_path / "run.h5"
        p = subprocess.run(rig_run_cmd("--config", str(run_cfg), "--scenario", "single-step", "--duration", "6",
                                       "--json", "--log", str(log), "--ctl-socket", str(log.with_suffix(".sock"))),
                           capture_output=True, text=True, timeout=90, stdin=subprocess.DEVNULL)
        s = _summary(p.stdout, p.stderr)
        assert p.returncode == 0 and s["final_state"] == "IDLE" and s["faults"] == [], (s["faults"], p.stderr[-2000:])
        (e,) = s["reconfigured"]
        assert (e["device"], e["carrier"], e["check"], e["end"]) == ("rl", "rear", "torque", "IDLE")
        # the simulator's scenario time starts with its session (the drives enabled: ARM), the
        # run's with RUNNING a few cycles later: detected within 0.3 s of the outage
        delay = e["t_start"] - s["run_started_t"] - T_OUT
        print(f"rig sim: silent rl outage detected {delay:.3f} s after it (run time)")
        assert -0.1 < delay <= 0.3
    finally:
        assert sp.stop(signal.SIGINT) == 0, sp.stderr()


@pytest.mark.slow
def test_a_sigint_during_reconfigured_ends_clean(tmp_path):
    sp, run_cfg = _sim_and_config(tmp_path)
    try:
        log = tmp_path / "run.h5"
        proc = subprocess.Popen(rig_run_cmd("--config", str(run_cfg), "--scenario", "single-step", "--json",
                                            "--log", str(log), "--ctl-socket", str(log.with_suffix(".sock"))),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
        deadline = time.monotonic() + 30.0           # into the session, past the outage and its detection
        while time.monotonic() < deadline:
            ses = sp.status()["session"]
            if ses["active"] and ses["t0"] is not None and sp.status()["t"] - ses["t0"] > T_OUT + 1.0:
                break
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
        s = _summary(out, err)
        assert s["final_state"] == "IDLE" and s["faults"] == [], s["faults"]
        (e,) = s["reconfigured"]
        assert e["device"] == "rl" and e["end"] == "IDLE"
        time.sleep(0.4)
        st = sp.status()
        assert all(d["current_A"] == 0.0 for d in st["drives"].values()), st["drives"]
    finally:
        assert sp.stop(signal.SIGINT) == 0, sp.stderr()
