"""A run's metrics (from its summary and its log) and its verdict against the spec's pass
criteria. The same function serves the campaign and a run reproduced alone, so a row's
metrics can be recomputed from its reproducing command's log."""

from __future__ import annotations

import math
from typing import Mapping, Optional

import numpy as np

# name -> what it is (every criterion is an upper bound: metric <= limit)
METRICS: dict[str, str] = {
    "max_abs_e_y_mm": "max |y_ref - y| of the rear carrier while RUNNING, mm",
    "rms_e_y_mm": "RMS of y_ref - y while RUNNING, mm",
    "max_abs_y_mm": "max |y| while RUNNING, mm",
    "max_abs_psi_mrad": "max |psi| while RUNNING, mrad",
    "max_abs_u_A": "max |u|, the differential current of a carrier, A",
    "n_faults": "faults the supervisor raised",
    "rise_time_s": "worst 10-90 % rise time over the reference steps, s",
    "overshoot_pct": "worst overshoot over the reference steps, %",
    "settling_time_s": "worst 2 % settling time over the reference steps, s",
    "steady_state_error_mm": "worst |steady-state error| over the reference steps, mm",
}
STEP_METRICS = ("rise_time_s", "overshoot_pct", "settling_time_s", "steady_state_error_mm")
STATUSES = ("pass", "fail", "refused", "error")


def _worst(steps: list[dict], key: str, absolute: bool = False) -> Optional[float]:
    """The worst value over the steps; None if there is no step or one never got there
    (never rose, never settled): that is not a number to compare, it fails a criterion."""
    vals = [s.get(key) for s in steps]
    if not vals or any(v is None for v in vals):
        return None
    return float(max(abs(v) for v in vals) if absolute else max(vals))


def metrics(summary: Mapping, log_path, settle_s: float = 0.0) -> dict[str, Optional[float]]:
    """The campaign metrics of one lockstep run: ``summary`` as :func:`run_lockstep` (and
    ``rig dry-run --json``) returns it, ``log_path`` its HDF5 log. ``settle_s``: the y, ψ
    metrics leave out the first seconds of RUNNING (the carrier settling from its rest
    state, which is not what a disturbance campaign asks about)."""
    from rig_runtime.app.export import read_log
    d = read_log(log_path)["columns"]
    run = d["t_run"] > settle_s
    y, y_ref, psi = d["y_r"][run], d["y_ref"][run], d["psi_r"][run]
    e = y_ref - y
    have = bool(len(y))
    steps = summary.get("steps") or []
    return {
        "max_abs_e_y_mm": float(np.max(np.abs(e)) * 1e3) if have else None,
        "rms_e_y_mm": float(np.sqrt(np.mean(e ** 2)) * 1e3) if have else None,
        "max_abs_y_mm": float(np.max(np.abs(y)) * 1e3) if have else None,
        "max_abs_psi_mrad": float(np.max(np.abs(psi)) * 1e3) if have else None,
        "max_abs_u_A": float(summary["max_abs_current_A"]),
        "n_faults": float(len(summary.get("faults") or [])),
        "rise_time_s": _worst(steps, "rise_time_s"),
        "overshoot_pct": _worst(steps, "overshoot_pct"),
        "settling_time_s": _worst(steps, "settling_time_s"),
        "steady_state_error_mm": _worst(steps, "steady_state_error_mm", absolute=True),
    }


def verdict(values: Mapping[str, Optional[float]], final_state: str, exit_code: int,
            criteria: Mapping[str, float], no_fault: bool) -> tuple[bool, str]:
    """(passed, why not): every criterion ``metric <= limit``; ``no_fault``: the run ended
    without a FAULT and without a fault raised. A metric that is None fails its criterion."""
    why = []
    if no_fault and (final_state == "FAULT" or exit_code != 0 or (values.get("n_faults") or 0) > 0):
        why.append(f"fault (final state {final_state})")
    for name, limit in criteria.items():
        v = values.get(name)
        if v is None or (isinstance(v, float) and math.isnan(v)):
            why.append(f"{name} undefined")
        elif v > limit:
            why.append(f"{name} {v:.4g} > {limit:.4g}")
    return not why, "; ".join(why)
