"""`rig sim` stopped and resumed (SIGSTOP/SIGCONT: a debugger, a suspended terminal, a loaded
host) goes on serving: it notes each pause in its status and a `rig run` afterwards connects,
arms and runs; SIGINT still ends it with exit 0 (issue 29)."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from sim_backend.launcher import start_sim_process

from .e2e import realtime_config, realtime_sim_config

PAUSES_S = (0.2, 1.0, 3.0)
REPEATS = 5


@pytest.mark.slow
def test_rig_sim_survives_sigstop_and_sigcont(tmp_path):
    with start_sim_process(config=realtime_sim_config(tmp_path), workdir=tmp_path / "sim") as sp:
        sp.wait_status(lambda s: s["timing"]["steps"] > 10, timeout_s=10.0)
        count = 0
        for pause in PAUSES_S:
            for _ in range(REPEATS):
                os.kill(sp.proc.pid, signal.SIGSTOP)
                time.sleep(pause)
                os.kill(sp.proc.pid, signal.SIGCONT)
                t_cont = time.monotonic()
                count += 1
                st = sp.wait_status(lambda s: s["t"] > t_cont and s["timing"]["pauses"]["count"] >= count,
                                    timeout_s=5.0)
                p = st["timing"]["pauses"]
                assert p["count"] == count, p
                assert p["last"]["duration_s"] >= pause - 0.02, p
                assert p["last"]["caught_up_s"] + p["last"]["skipped_s"] == pytest.approx(p["last"]["duration_s"])
                assert st["error"] == "", st["error"]
        assert p["longest_s"] >= PAUSES_S[-1] - 0.02 and p["skipped_s"] > 0.0, p       # the 3 s pauses skip
        assert "paused" in sp.stderr()
        # still serving: a `rig run` connects, arms and runs, then ends by itself
        run_cfg = realtime_config(sp.config_path, tmp_path / "rig-run.yaml")
        log = tmp_path / "after-pauses.h5"
        proc = subprocess.run([sys.executable, "-m", "rig_runtime", "run", "--config", str(run_cfg),
                               "--scenario", "single-step", "--duration", "1.0", "--json", "--log", str(log),
                               "--ctl-socket", str(tmp_path / "ctl.sock")],
                              capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
        assert proc.returncode == 0, proc.stderr[-3000:]
        summary = json.loads(proc.stdout.strip().splitlines()[-1])
        assert summary["final_state"] == "IDLE" and summary["faults"] == [], summary
        assert summary["cycles"] > 0 and summary["run_started_t"] == summary["run_started_t"]   # it armed and ran
        assert sp.status()["error"] == ""
        code = sp.stop(signal.SIGINT)
        assert code == 0, sp.stderr()[-3000:]
