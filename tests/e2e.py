"""Helpers for end-to-end tests against the lockstep simulated plant."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from drivers import cia402 as co
from rig_runtime import config
from rig_runtime.app.export import read_log
from rig_runtime.scenario import load_scenario
from rig_runtime.app.dryrun import run_lockstep


@dataclasses.dataclass
class Run:
    summary: dict
    code: int
    log: dict
    wire: list          # (sync_index, wheel, current_A) of every RPDO on the wire
    syncs: int

    @property
    def fault(self):
        return self.summary["faults"][0] if self.summary["faults"] else None

    def col(self, name):
        return self.log["columns"][name]

    def fault_row(self) -> int:
        t = self.col("t")
        return int(np.argmin(np.abs(t - self.fault["t"])))


def run(tmp_path: Path, scenario, cfg=None, **kw) -> Run:
    cfg = cfg or config.load()
    sc = load_scenario(scenario) if isinstance(scenario, str) else scenario
    taps = []
    rated = {d.node_id: (d.wheel, d.rated_current_A) for d in cfg.devices.can.drives}

    def prepare(sim, devices, clock):
        taps.append(sim.runtime_bus())
        if kw.get("prepare"):
            kw["prepare"](sim, devices, clock)

    log = tmp_path / f"{sc.name}.h5"
    summary, code = run_lockstep(cfg, sc, log, seed=kw.get("seed"), duration_s=kw.get("duration_s"),
                                 prepare=prepare)
    wire, syncs = [], 0
    tap = taps[0]
    while True:
        m = tap.recv(0)
        if m is None:
            break
        cid = m.arbitration_id
        if cid == co.COB_SYNC:
            syncs += 1
        elif co.COB_RPDO1 < cid <= co.COB_RPDO1 + 127 and len(m.data) == co.RPDO1.size:
            node = cid - co.COB_RPDO1
            cw, tq = co.decode_rpdo1(m.data)
            wheel, r = rated[node]
            wire.append((syncs, wheel, co.permille_to_amps(tq, r)))
    tap.shutdown()
    return Run(summary, code, read_log(log), wire, syncs)


def assert_safe_stop(r, device, check):
    s = r.summary
    assert s["final_state"] == "FAULT" and r.code == 3
    f = r.fault
    assert (f["device"], f["check"]) == (device, check), f
    k = r.fault_row()
    # the detecting cycle and every later one command zero, in the log …
    for c in ("rear_u_lim", "i_fl", "i_fr", "i_rl", "i_rr"):
        assert np.all(r.col(c)[k:] == 0.0), c
    assert np.any(r.col("rear_u_lim")[:k] != 0.0)     # it was actually controlling before
    # … and on the wire: RPDOs sent in cycle k (its SYNC is the (k+1)-th) and after carry 0 A
    after = [i for n, _, i in r.wire if n >= k + 1]
    assert after and all(i == 0.0 for i in after)
    assert any(i != 0.0 for n, _, i in r.wire if n <= k)
    ev = r.log["events"]
    kinds = list(ev["kind"])
    j = kinds.index("fault")
    assert (ev["device"][j], ev["check"][j]) == (device, check)
    assert r.log["rows"] == s["cycles"]
