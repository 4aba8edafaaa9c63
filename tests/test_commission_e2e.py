"""``rig commission`` unchanged against a real ``rig sim`` process with one miswiring (the
drives of rl and rr at each other's node IDs): it fails and names the fault; the lifted
bumps, with the carriers the simulated operator lifted (``sim: {operator: commission}``),
pass (a node swap moves a drive with its encoder: only the yaw on the rollers sees it), and
``rig log info`` shows the report from the commissioning's log. And an operator at a
terminal who takes longer at each prompt than the drives' heartbeat consumers wait: the
cycle goes on while the prompt waits, so every check runs and passes. The stated tolerance
of the real-time tests (tests/e2e.py) applies."""

from __future__ import annotations

import json
import os
import pty
import select
import subprocess
import sys
import time

import yaml

from sim_backend.launcher import start_sim_process

from .e2e import realtime_config, realtime_sim_config
from .test_sim_process import SIM_RT_ARGS


def test_commission_against_rig_sim_names_swapped_drive_nodes(tmp_path):
    src = realtime_sim_config(tmp_path)
    data = yaml.safe_load(src.read_text())
    data.setdefault("sim", {}).update(operator="commission", miswire={"node_swap": [["rl", "rr"]]})
    src.write_text(yaml.safe_dump(data, sort_keys=False))
    with start_sim_process(config=src, extra_args=SIM_RT_ARGS, workdir=tmp_path / "sim") as sp:
        run_config = realtime_config(sp.config_path, tmp_path / "rig-run.yaml")
        r = subprocess.run([sys.executable, "-m", "rig_runtime", "commission", "--config", str(run_config), "--yes",
                            "--passive-s", "2.5", "--json", "--report", str(tmp_path / "report.json"),
                            "--record", str(tmp_path / "record.jsonl")],
                           capture_output=True, text=True, timeout=180, stdin=subprocess.DEVNULL)
    assert r.returncode == 3, (r.returncode, r.stderr[-2000:])
    rep = json.loads(r.stdout.strip().splitlines()[-1])
    items = {i["name"]: i for i in rep["items"]}
    assert all(items[c]["passed"] for c in ("lasers", "lifted-rear", "lifted-front", "encoders")), rep
    assert items["lifted-rear"]["measured"]["dw_rl_rad_s"] > 2 > -2 > items["lifted-rear"]["measured"]["dw_rr_rad_s"]
    assert not items["bump-rear"]["passed"]
    assert any("drives rl and rr appear swapped" in f for f in items["bump-rear"]["faults"]), rep
    assert json.loads((tmp_path / "record.jsonl").read_text().splitlines()[-1])["result"] == "fail"
    info = subprocess.run([sys.executable, "-m", "rig_runtime", "log", "info", rep["log"]], capture_output=True,
                          text=True, timeout=60)
    assert info.returncode == 0 and "mode: commission" in info.stdout, info.stderr
    assert "bump-rear FAIL" in info.stdout and "likely fault: drives rl and rr appear swapped" in info.stdout


OPERATOR_READS_S = 1.0      # at each prompt: twice the drives' heartbeat consumer time in tests/e2e.py (0.5 s)


def test_an_operator_at_a_terminal_slower_than_the_heartbeat_consumers(tmp_path):
    src = realtime_sim_config(tmp_path)
    data = yaml.safe_load(src.read_text())
    data.setdefault("sim", {}).update(operator="commission")
    src.write_text(yaml.safe_dump(data, sort_keys=False))
    err = tmp_path / "stderr.txt"
    with start_sim_process(config=src, extra_args=SIM_RT_ARGS, workdir=tmp_path / "sim") as sp:
        run_config = realtime_config(sp.config_path, tmp_path / "rig-run.yaml")
        master, slave = pty.openpty()
        with open(err, "w") as err_f:
            p = subprocess.Popen([sys.executable, "-m", "rig_runtime", "commission", "--config", str(run_config),
                                  "--passive-s", "2.5", "--report", str(tmp_path / "report.json"),
                                  "--record", str(tmp_path / "record.jsonl")],
                                 stdin=slave, stdout=slave, stderr=err_f)
        os.close(slave)
        answered = 0
        try:
            deadline = time.monotonic() + 150
            while p.poll() is None and time.monotonic() < deadline:
                if select.select([master], [], [], 0.1)[0]:
                    try:
                        os.read(master, 65536)      # the report as it is printed
                    except OSError:                 # EIO: the command has closed the terminal (it ended)
                        pass
                if err.read_text().count("Ready?") > answered:      # the prompt (input() writes it to stderr)
                    time.sleep(OPERATOR_READS_S)
                    os.write(master, b"y\n")
                    answered += 1
            code = p.wait(30)
        finally:
            if p.poll() is None:
                p.kill()
            os.close(master)
    assert answered == 4 and code == 0, (answered, code, err.read_text()[-2000:])
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["result"] == "pass" and [i["name"] for i in rep["items"]] == [
        "lasers", "lifted-rear", "lifted-front", "encoders", "bump-rear", "bump-front"], rep
