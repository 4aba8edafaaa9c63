"""Helpers for end-to-end tests against the lockstep simulated plant."""

from __future__ import annotations

import copy
import dataclasses
import functools
from pathlib import Path

import numpy as np
import yaml

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
    log_path: Path | None = None    # the log file (HDF5) the run wrote

    @property
    def fault(self):
        return self.summary["faults"][0] if self.summary["faults"] else None

    def col(self, name):
        return self.log["columns"][name]

    def fault_row(self) -> int:
        t = self.col("t")
        return int(np.argmin(np.abs(t - self.fault["t"])))


SCENARIO_CONFIGS = (("vehicle-", "vehicle.yaml"),         # both carriers on the rollers (issue 18)
                    ("ident-front-", "sim-ident-front.yaml"))  # the front's mirrored identification set-up


def shipped_config_for(scenario_name: str) -> Path | None:
    """The shipped config a shipped scenario is written for, when it is not the default
    ``sim.yaml`` (None)."""
    for prefix, name in SCENARIO_CONFIGS:
        if scenario_name.startswith(prefix):
            return config.CONFIG_DIR / name
    return None


@functools.lru_cache(maxsize=1)
def shipped_config():
    """The shipped configuration, loaded once per process (a frozen value: every run may share
    it; a load is ~50 ms of YAML and checks)."""
    return config.load()


def run(tmp_path: Path, scenario, cfg=None, **kw) -> Run:
    cfg = cfg or shipped_config()
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
    return Run(summary, code, read_log(log), wire, syncs, log)


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


# The real-time end-to-end tests run on a shared 2-CPU machine whose scheduling they do not
# test: each states the tolerance it needs in a run config of its own. Measured on this
# machine (docs/sim-process.md, "Runtime-side issues" item 6): the loop at SCHED_FIFO 80
# blocks in read()/poll() of a pty until a SCHED_OTHER kworker has moved the pty's input
# to the line discipline (n_tty_read -> tty_buffer_flush_work), and with four other agents
# loading two CPUs that kworker waits 10–150 ms; the simulator's data reaches the runtime
# through the same kworkers. The hardware's ceilings (50 ms blind, a 100 ms drive watchdog)
# cannot take that, so these tests run the simulated rig under a hardware description of
# their own that allows REALTIME_STALL_S of stall, and set the limits to it: a longer stall
# is still a fault, and fails the test that meets it.
REALTIME_STALL_S = 0.3
_PERIODS = 60                          # REALTIME_STALL_S / h (h = 5 ms)
REALTIME_CEILINGS = {"overrun_s": REALTIME_STALL_S, "stale_s": REALTIME_STALL_S,
                     "drive_watchdog_ms": int(REALTIME_STALL_S * 1000)}
REALTIME_TOLERANCE = {
    "limits.overrun_burst": _PERIODS,               # the loop may lose up to 59 periods in a row
    "limits.stale_periods": _PERIODS,               # an input may be up to 60 periods old
    "devices.can.watchdog_ms": int(REALTIME_STALL_S * 1000),   # the drives' RPDO watchdog
    "devices.can.heartbeat_timeout_factor": 5.0,    # consumers: 100 ms x 5 = the 500 ms ceiling
    "degraded.torque_hold_s": REALTIME_STALL_S,     # a drive's torque answer may be as late as its other inputs
}


def config_with(base: Path, out: Path, settings: dict, ceilings: dict | None = None) -> Path:
    """A run config at ``out``: ``base`` (and its includes) with ``settings`` (dotted keys,
    e.g. ``limits.overrun_burst``) set, every section written out except the hardware
    description, which stays an include — of ``base``'s file, or with ``ceilings`` of a
    copy next to ``out`` with those ceilings changed. Loaded once here, so a setting beyond a
    ceiling fails at once."""
    sections = config.load_sections(Path(base))
    known = config.load(base)
    out = Path(out)
    hw_value, hw_file = sections["hardware"]
    if ceilings:
        hw = copy.deepcopy(hw_value)
        hw["ceilings"].update(ceilings)
        hw_file = out.with_name(out.stem + "-hardware.yaml")
        Path(hw_file).write_text("# the simulated rig on a shared test machine (tests/e2e.py), not a machine's ceilings\n"
                                 + yaml.safe_dump({"hardware": hw}, sort_keys=False))
    data: dict = {"include": [str(hw_file)]}
    for name, (value, _) in sections.items():
        if name != "hardware":
            data[name] = copy.deepcopy(value)

    def put(key: str, value) -> None:
        *path, last = key.split(".")
        d = data
        for part in path:
            d = d.setdefault(part, {})
        d[last] = value

    def in_schema(key: str) -> bool:
        obj = known
        for part in key.split("."):
            if not hasattr(obj, part):
                return False
            obj = getattr(obj, part)
        return True

    for key, value in settings.items():
        assert in_schema(key), f"no setting {key}"
        put(key, value)
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    config.load(out)
    return out


def realtime_config(base: Path, out: Path) -> Path:
    """``base`` with the real-time tests' stated tolerance (REALTIME_TOLERANCE)."""
    return config_with(base, out, REALTIME_TOLERANCE, ceilings=REALTIME_CEILINGS)


def realtime_sim_config(directory: Path) -> Path:
    """configs/sim.yaml with the stated tolerance, for ``rig sim --config``: the simulated
    drives take their RPDO watchdog from the simulator's config, not from the runtime."""
    return realtime_config(config.CONFIG_DIR / "sim.yaml", Path(directory) / "sim-tolerant.yaml")


def read_with_truth(path: Path) -> tuple[dict, dict, dict, list[str]]:
    """A dry run's log with the simulated truth: (columns, truth columns, the truth group's
    attributes, event messages)."""
    import h5py
    from rig_runtime.app.dryrun import TRUTH_GROUP
    with h5py.File(path, "r") as f:
        cols = [c.decode() if isinstance(c, bytes) else c for c in f["cycles"].attrs["columns"]]
        data = {c: f["cycles"][c][:] for c in cols}
        truth = {k: f[TRUTH_GROUP][k][:] for k in f[TRUTH_GROUP]}
        attrs = dict(f[TRUTH_GROUP].attrs)
        messages = [m.decode() if isinstance(m, bytes) else str(m) for m in f["events"]["message"][:]]
    return data, truth, attrs, messages



def read_with_rear_truth(path: Path) -> tuple[dict, np.ndarray, list[str]]:
    """The log's cycle columns, the simulated true y_r at each cycle's time, and the event
    messages (:func:`read_with_truth`)."""
    data, truth, _, messages = read_with_truth(path)
    idx = np.clip(np.searchsorted(truth["t"], data["t"] - 1e-9), 0, len(truth["t"]) - 1)
    return data, truth["y_r"][idx], messages


def assert_steps_tracked(r: Run, cfg, n_steps: int) -> None:
    """Sec. 5.2.4 ("negligible steady-state error") for a closed-loop run of steps (the
    step-sequence scenario or a part of it): ``n_steps`` steps, each tracked with a
    steady-state error < 2 % of the step or, for the 0.1 mm steps where 2 % is 2 µm,
    < 5 µm (the hysteresis' slow tail can outlast their 20 s window: 3.7 µm on one of them
    at seed 0 since the drives are enabled at ARM); current within ±u_max in the log and on
    the wire, no faults, median rise/settling times of a few seconds. Used by
    tests/test_closed_loop.py and by the full-length acceptance run,
    benchmarks/step_sequence.py."""
    s = r.summary
    assert s["final_state"] == "IDLE" and s["faults"] == []
    assert s["max_abs_current_A"] <= cfg.limits.u_max
    assert all(abs(i) <= cfg.limits.u_max for _, _, i in r.wire)
    steps = s["steps"]
    assert len(steps) == n_steps
    for st in steps:
        size = abs(st["to_mm"] - st["from_mm"])
        assert abs(st["steady_state_error_mm"]) < max(0.02 * size, 0.005), st
    rise = np.median([st["rise_time_s"] for st in steps])
    settle = np.median([st["settling_time_s"] for st in steps if st["settling_time_s"] is not None])
    assert 0.5 < rise < 5.0 and 2.0 < settle < 15.0
