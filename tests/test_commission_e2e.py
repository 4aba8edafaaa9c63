"""``rig commission`` unchanged against a real ``rig sim`` process with one miswiring (the
drives of rl and rr at each other's node IDs): it fails and names the fault; the lifted
bumps, with the carriers the simulated operator lifted (``sim: {operator: commission}``),
pass (a node swap moves a drive with its encoder: only the yaw on the rollers sees it), and
``rig log info`` shows the report from the commissioning's log. The stated tolerance of the
real-time tests (tests/e2e.py) applies."""

from __future__ import annotations

import json
import subprocess
import sys

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
