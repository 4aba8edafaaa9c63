"""The loop's status snapshot for the live views: bounded in size however many faults a
held run collects, and a snapshot that does not fit its slot is not lost silently."""

from __future__ import annotations

import json

from rig_runtime.app.live import STATUS_FAULTS, snapshot
from rig_runtime.clock import LockstepClock
from rig_runtime.app.export import read_log
from rig_runtime.loop import ControlLoop
from rig_runtime.recorder import Recorder
from rig_runtime.safety import Fault

from .test_ctl_loop import FakeDevices


def test_snapshot_carries_the_newest_faults_and_their_count(cfg):
    loop = ControlLoop(cfg, FakeDevices(cfg), LockstepClock())
    loop.t_start = 1.0
    loop.cycle.t = 100.0
    loop.supervisor.faults.extend(Fault(1.0 + k, "s_rl", "stale", float(k), 0.02, f"fault {k}") for k in range(25))
    st = snapshot(loop, 60.0)
    assert st["faults_total"] == 25 and len(st["faults"]) == STATUS_FAULTS
    assert [f["message"] for f in st["faults"]] == [f"fault {k}" for k in range(25 - STATUS_FAULTS, 25)]
    f = st["faults"][-1]
    assert f["t_run"] == 24.0 and f["t"] == 25.0 and f["value"] == 24.0 and f["limit"] == 0.02
    json.dumps(st, allow_nan=False)                         # JSON as it is sent (no NaN)


def test_a_snapshot_too_large_for_its_slot_is_counted_and_recorded(tmp_path):
    rec = Recorder(tmp_path / "s.h5", ["t"], attrs={})
    rec.open()
    try:
        rec.append([0.0])
        rec.publish_status({"t": 0.5, "state": "RUNNING"})
        assert rec.status_refused == 0
        for _ in range(3):
            rec.publish_status({"t": 1.0, "pad": "x" * 20000})
        assert rec.status_refused == 3
    finally:
        rec.close()
    ev = read_log(tmp_path / "s.h5")["events"]
    msgs = [m for k, m in zip(ev["kind"], ev["message"]) if k == "recorder"]
    assert len(msgs) == 1 and "does not fit its slot" in msgs[0], list(ev["message"])
