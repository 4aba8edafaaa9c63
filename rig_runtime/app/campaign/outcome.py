"""A run's metrics (from its summary and its log) and its verdict against the spec's pass
criteria. The same function serves the campaign and a run reproduced alone, so a row's
metrics can be recomputed from its reproducing command's log."""

from __future__ import annotations

import math
from typing import Mapping, Optional

import numpy as np

CARRIERS = ("front", "rear")
# name -> what it is (every criterion is an upper bound: metric <= limit). Each carrier
# metric is the worst over the controlled carriers; FRONT_NAME / REAR_NAME is that carrier's own.
CARRIER_METRICS: dict[str, str] = {
    "max_abs_e_y_mm": "max |y_ref - y| while RUNNING (each carrier on its own reference), mm",
    "rms_e_y_mm": "RMS of y_ref - y while RUNNING, mm",
    "max_abs_y_mm": "max |y| while RUNNING, mm",
    "max_abs_psi_mrad": "max |psi| (carrier to rail) while RUNNING, mrad",
    "max_abs_u_A": "max |u|, the differential current of a carrier, A",
    "rms_u_A": "RMS of u while RUNNING (an effort and wear proxy), A",
    "rise_time_s": "worst 10-90 % rise time over the reference steps, s",
    "overshoot_pct": "worst overshoot over the reference steps, %",
    "settling_time_s": "worst 2 % settling time over the reference steps, s",
    "steady_state_error_mm": "worst |steady-state error| over the reference steps, mm",
    "held_excursion_mm": "worst excursion of a carrier whose reference holds while the other steps, mm",
    "held_excursion_pct": "the same in % of the other carrier's step",
}
STEP_METRICS = ("rise_time_s", "overshoot_pct", "settling_time_s", "steady_state_error_mm")
HELD_METRICS = ("held_excursion_mm", "held_excursion_pct")     # judged on the held carrier (two controlled)
METRICS: dict[str, str] = {
    **CARRIER_METRICS,
    "n_faults": "faults the supervisor raised",
    **{f"{c}_{k}": f"{c} carrier: {v}" for c in CARRIERS for k, v in CARRIER_METRICS.items()},
}
STATUSES = ("pass", "fail", "refused", "error")
METRIC_NAMES = ", ".join(m for m in METRICS if m.split("_")[0] not in CARRIERS) + "; each carrier metric also as front_NAME, rear_NAME"


def split_name(name: str) -> tuple[str | None, str]:
    """(carrier or None for the worst over carriers, base metric): ``front_overshoot_pct``
    → (front, overshoot_pct)."""
    for c in CARRIERS:
        if name.startswith(c + "_") and name[len(c) + 1:] in CARRIER_METRICS:
            return c, name[len(c) + 1:]
    return None, name


def unavailable(name: str, scenario, controlled) -> Optional[str]:
    """Why metric ``name`` cannot be had from runs of ``scenario`` (a loaded Scenario) with
    these controlled carriers, or None: a step metric needs a step of that carrier's (or any
    controlled carrier's) reference; a held excursion two controlled carriers with a step of
    one while the other's reference holds; a carrier's metric that carrier controlled."""
    from rig_runtime.scenario import Reference
    carrier, base = split_name(name)
    if carrier is not None and carrier not in controlled:
        return f"a metric of a controlled carrier (the config controls {', '.join(controlled)})"
    steps = {c: Reference(scenario.reference_for(c)).steps() for c in controlled}
    if base in STEP_METRICS and not any(steps[c] for c in ([carrier] if carrier else controlled)):
        return "a metric the scenario has: it has no reference step" + (f" of the {carrier} carrier" if carrier else "")
    if base in HELD_METRICS:
        held = [k for c in controlled for (t0, _, _) in steps[c] for k in controlled
                if k != c and not any(t == t0 for t, _, _ in steps[k])]
        if not held or (carrier and carrier not in held):
            return ("a metric the scenario has: no step of one controlled carrier while the other's reference "
                    "holds" + (f" (held: {carrier})" if carrier else ""))
    return None


def _worst(steps: list[dict], key: str, absolute: bool = False) -> Optional[float]:
    """The worst value over the steps; None if there is no step or one never got there
    (never rose, never settled): that is not a number to compare, it fails a criterion."""
    vals = [s.get(key) for s in steps]
    if not vals or any(v is None for v in vals):
        return None
    return float(max(abs(v) for v in vals) if absolute else max(vals))


def _max(vals) -> Optional[float]:
    vals = list(vals)
    if not vals or any(v is None for v in vals):
        return None
    return float(max(vals))


def _carrier(d: Mapping, carrier: str, run: np.ndarray, steps: list[dict]) -> dict[str, Optional[float]]:
    y = d["y_" + carrier[0]][run]
    ref = d.get(f"{carrier}_y_ref", d["y_ref"])[run]
    psi = d["psi_" + carrier[0]][run]
    u_all = d.get(f"{carrier}_u_lim")
    u = u_all[run] if u_all is not None else None
    e = ref - y
    have = bool(len(y))
    mine = [s for s in steps if s.get("carrier", carrier) == carrier]
    held = [s for s in steps if s.get("held") == carrier]
    return {
        "max_abs_e_y_mm": float(np.max(np.abs(e)) * 1e3) if have else None,
        "rms_e_y_mm": float(np.sqrt(np.mean(e ** 2)) * 1e3) if have else None,
        "max_abs_y_mm": float(np.max(np.abs(y)) * 1e3) if have else None,
        "max_abs_psi_mrad": float(np.max(np.abs(psi)) * 1e3) if have else None,
        "max_abs_u_A": float(np.max(np.abs(u_all))) if u_all is not None and len(u_all) else None,
        "rms_u_A": float(np.sqrt(np.mean(u ** 2))) if u is not None and len(u) else None,
        "rise_time_s": _worst(mine, "rise_time_s"),
        "overshoot_pct": _worst(mine, "overshoot_pct"),
        "settling_time_s": _worst(mine, "settling_time_s"),
        "steady_state_error_mm": _worst(mine, "steady_state_error_mm", absolute=True),
        "held_excursion_mm": _worst(held, "held_excursion_mm"),
        "held_excursion_pct": _worst(held, "held_excursion_pct"),
    }


def metrics(summary: Mapping, log_path, settle_s: float = 0.0) -> dict[str, Optional[float]]:
    """The campaign metrics of one lockstep run: ``summary`` as :func:`run_lockstep` (and
    ``rig dry-run --json``) returns it, ``log_path`` its HDF5 log (or the log as
    ``export.read_log`` returned it: :func:`~rig_runtime.app.dryrun.run_lockstep_read`). Each carrier metric per
    controlled carrier (the log's ``controlled``; ``{carrier}_NAME``) on that carrier's own
    columns and reference, and the worst over them (``NAME``; ``max_abs_u_A``: the run's
    summary, the largest current any lane applied). ``settle_s``: the y, ψ, e and RMS metrics
    leave out the first seconds of RUNNING (the carrier settling from its rest state, which is
    not what a disturbance campaign asks about)."""
    from rig_runtime.app.export import read_log
    log = log_path if isinstance(log_path, dict) else read_log(log_path)
    d = log["columns"]
    carriers = log["attrs"].get("controlled") or ["rear"]
    carriers = [carriers] if isinstance(carriers, str) else [c for c in carriers if f"y_{c[0]}" in d]
    run = d["t_run"] > settle_s
    steps = summary.get("steps") or []
    per = {c: _carrier(d, c, run, steps) for c in carriers}
    out: dict[str, Optional[float]] = {}
    for k in CARRIER_METRICS:
        if k in HELD_METRICS:
            vals = [per[c][k] for c in carriers if any(s.get("held") == c for s in steps)]
        elif k in STEP_METRICS:
            vals = [per[c][k] for c in carriers if any(s.get("carrier", c) == c for s in steps)]
        else:
            vals = [per[c][k] for c in carriers]
        out[k] = _max(vals)
    out["max_abs_u_A"] = float(summary["max_abs_current_A"])
    if not steps:
        for k in STEP_METRICS:
            out[k] = None
    out["n_faults"] = float(len(summary.get("faults") or []))
    for c in CARRIERS:
        for k in CARRIER_METRICS:
            out[f"{c}_{k}"] = per[c][k] if c in per else None
    return {k: out.get(k) for k in METRICS}


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
