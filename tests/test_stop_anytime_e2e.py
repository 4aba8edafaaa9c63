"""Safe at every edge, end to end: `rig run` against `rig sim`, stopped by SIGINT/SIGTERM at
instants spread over start-up, running and shut-down, and killed right after configuring.

After every stop: the process exited with the documented code (0 after RUNNING began,
128 + signal before; killed by the signal only if it came before the interpreter reached
the runtime's first line, when nothing was open yet) and one line saying what happened, no traceback; the log, if one was
written, is readable; every simulated drive is switched off — SWITCH ON DISABLED with zero
current, not FAULT (the runtime switched their heartbeat consumers off before it left).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest

from rig_runtime.config import WHEELS
from rig_runtime.export import read_log
from sim_backend.launcher import start_sim_process

# instants after the start of `rig run` (s): imports, configure, warm-up/arm, running
# (--duration 1.0), the 0.5 s stop ramp, closing
INSTANTS = (0.1, 0.3, 0.5, 0.7, 0.9, 1.1, 1.4, 1.7, 2.0, 2.4, 2.8, 3.3)
CONSUMER_S = 0.25      # the drives' heartbeat consumer time (sim.yaml: 100 ms x 2.5)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    sp = start_sim_process(workdir=tmp_path_factory.mktemp("rig-sim"))
    yield sp
    assert sp.stop(signal.SIGINT) == 0, sp.stderr()


def _run(sim, log, duration="1.0"):
    cmd = [sys.executable, "-m", "rig_runtime", "run", "--config", str(sim.config_path), "--json",
           "--duration", duration, "--log", str(log)]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)


def _drives_off(sim, t_after: float) -> dict:
    """A status written after ``t_after`` (and after the consumer time, so a consumer that was
    not switched off would have fired by then)."""
    time.sleep(CONSUMER_S + 0.15)
    return sim.wait_status(lambda s: s["t"] > t_after + CONSUMER_S, timeout_s=3.0)


@pytest.mark.slow
def test_a_signal_at_any_instant_ends_in_a_clean_stop(sim, tmp_path):
    seen = {"before RUNNING": 0, "after RUNNING": 0}
    for k, delay in enumerate(INSTANTS):
        sig = (signal.SIGINT, signal.SIGTERM)[k % 2]
        log = tmp_path / f"run-{k}.h5"
        events0 = {w: d["heartbeat_events"] for w, d in sim.status()["drives"].items()}
        proc = _run(sim, log)
        time.sleep(delay)
        sent = proc.poll() is None
        if sent:
            proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
        t_exit = time.monotonic()
        what = f"instant {delay} s, {sig.name}: exit {proc.returncode}\nstdout {out[-1500:]}\nstderr {err[-1500:]}"
        assert "Traceback" not in err, what
        if proc.returncode == -sig:
            # the signal came before the interpreter reached the runtime's first line (its start
            # takes ~0.1-0.3 s here): the default action ended it, nothing had been opened
            st = _drives_off(sim, t_exit)
            assert all(d["nmt"] == "PRE-OPERATIONAL" for d in st["drives"].values()), (what, st)
            seen["before Python"] = seen.get("before Python", 0) + 1
        elif proc.returncode == 128 + sig:
            lines = [ln for ln in err.splitlines() if ln.strip()]
            assert lines and lines[-1].startswith(f"rig run: stopped by {sig.name} before RUNNING"), what
            seen["before RUNNING"] += 1
        else:
            assert proc.returncode == 0, what
            summary = json.loads(out.strip().splitlines()[-1])
            assert summary["final_state"] == "IDLE" and summary["faults"] == [], what
            if sent and summary.get("stopped_by"):
                assert summary["stopped_by"] == sig.name, what
                seen["after RUNNING"] += 1
        if log.exists():
            read_log(log)                                   # readable, whatever the instant
        st = _drives_off(sim, t_exit)
        for w in WHEELS:
            dr = st["drives"][w]
            assert dr["current_A"] == 0.0 and dr["state"] == "SWITCH ON DISABLED", (what, w, dr)
            assert dr["heartbeat_events"] == events0[w] and dr["error_code"] == 0, (what, w, dr)
    # the instants did land on both sides of RUNNING
    assert seen["before RUNNING"] >= 3 and seen["after RUNNING"] >= 3, seen


@pytest.mark.slow
def test_sigkill_after_configure_the_drives_stop_by_themselves(sim, tmp_path):
    """Killed once configured (NMT operational, consumers armed) but before the loop's first
    heartbeat could keep them alive for long: each drive's consumer fires within its
    consumer time and the drive ends switched off (0x6007 = quick stop, 0x605A = 2)."""
    st = sim.status()
    assert all(st["drives"][w]["nmt"] == "PRE-OPERATIONAL" for w in WHEELS), st   # after a clean stop
    events0 = {w: st["drives"][w]["heartbeat_events"] for w in WHEELS}
    proc = _run(sim, tmp_path / "kill.h5", duration="5")
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:                   # configured: the drives report NMT OPERATIONAL
        st = sim.status()
        if all(st["drives"][w]["nmt"] == "OPERATIONAL" for w in WHEELS):
            break
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait(5)
    t_kill = time.monotonic()
    st = sim.wait_status(lambda s: s["t"] > t_kill + CONSUMER_S + 0.2
                         and all(s["drives"][w]["heartbeat_events"] > events0[w] for w in WHEELS), timeout_s=5.0)
    for w in WHEELS:
        dr = st["drives"][w]
        assert dr["current_A"] == 0.0 and dr["state"] in ("SWITCH ON DISABLED", "FAULT"), dr
        assert dr["error_code"] in (0x8130, 0x8250), dr        # heartbeat lost (or its RPDO watchdog, if armed)
