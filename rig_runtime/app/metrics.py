"""Step-response figures of a run (python-control's ``step_info`` names, per reference step).

Definitions (also in docs/dry-run.md): for a reference step from ``a`` to ``b`` at ``t0``
(window up to the next reference change or the end of the run), with the response
normalised as ``r = (y − a)/(b − a)`` and ``y`` smoothed by a centred 50 ms moving average
(removes sensor noise, not dynamics):
- rise time: first time ``r`` reaches 0.9 minus first time it reaches 0.1;
- overshoot: ``max(r) − 1`` in percent (0 if it never exceeds 1);
- settling time: from ``t0`` to the last time ``|r − 1| > 0.02`` in the window;
- steady-state error: mean of ``y − b`` over the last second of the window, in mm.

``y`` is the y the lane controlled on: the measured one, the observer's ŷ while the carrier
was DEGRADED (:func:`controlled_y`).
"""

from __future__ import annotations

import math

import numpy as np


def _smooth(y: np.ndarray, n: int) -> np.ndarray:
    if n <= 1 or len(y) < n:
        return y
    k = np.ones(n) / n
    pad = n // 2
    yp = np.pad(y, (pad, n - 1 - pad), mode="edge")
    return np.convolve(yp, k, mode="valid")


def step_info(t: np.ndarray, y: np.ndarray, steps: list[tuple[float, float, float]], t_end: float,
              h: float = 0.005, smooth_s: float = 0.05) -> list[dict]:
    """Figures for each (t0, from_m, to_m) step; times in s, values in mm."""
    ys = _smooth(np.asarray(y, float), max(1, int(round(smooth_s / h))))
    out = []
    for i, (t0, a, b) in enumerate(steps):
        t1 = steps[i + 1][0] if i + 1 < len(steps) else t_end
        sel = (t >= t0) & (t < t1)
        tw, yw = t[sel], ys[sel]
        d = b - a
        rec = {"t0": t0, "from_mm": a * 1e3, "to_mm": b * 1e3, "rise_time_s": None, "overshoot_pct": None,
               "settling_time_s": None, "steady_state_error_mm": None}
        if len(tw) < 2 or d == 0:
            out.append(rec)
            continue
        r = (yw - a) / d
        i10 = np.argmax(r >= 0.1) if np.any(r >= 0.1) else None
        i90 = np.argmax(r >= 0.9) if np.any(r >= 0.9) else None
        if i10 is not None and i90 is not None:
            rec["rise_time_s"] = float(tw[i90] - tw[i10])
        rec["overshoot_pct"] = float(max(0.0, (r.max() - 1.0) * 100.0))
        outside = np.nonzero(np.abs(r - 1.0) > 0.02)[0]
        if len(outside) == 0:
            rec["settling_time_s"] = 0.0
        elif outside[-1] < len(r) - 1:
            rec["settling_time_s"] = float(tw[outside[-1] + 1] - t0)
        last = tw >= tw[-1] - 1.0
        rec["steady_state_error_mm"] = float(np.mean(y[sel][last] - b) * 1e3)
        out.append(rec)
    return out


def clean(v):
    """JSON-safe: NaN/inf -> None."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [clean(x) for x in v]
    return v


def controlled_y(columns: dict, carrier: str = "rear") -> np.ndarray:
    """The y the carrier's lane controlled on, row by row: the measured y, and the observer's
    ŷ where the carrier was DEGRADED (``{carrier}_obs_degraded``; the measured y is the lost
    laser's stale value then, docs/observer.md)."""
    y = columns["y_r" if carrier == "rear" else "y_f"]
    deg = columns.get(f"{carrier}_obs_degraded")
    if deg is None:
        return y
    return np.where(deg == 1.0, columns[f"{carrier}_obs_y_hat"], y)


def steps_from_log(log, scenario, h: float) -> list[dict]:
    """``step_info`` for every reference step of ``scenario`` from a recorded run, per
    controlled carrier (the log's ``controlled``) on that carrier's own reference
    (``scenario.reference_for``) and the y its lane controlled on (:func:`controlled_y`);
    each step names its ``carrier``."""
    from ..scenario import Reference
    from .export import read_log
    if scenario is None:
        return []
    log_d = read_log(log)
    d = log_d["columns"]
    carriers = log_d["attrs"].get("controlled") or ["rear"]
    if isinstance(carriers, str):
        carriers = [carriers]
    run = d["t_run"] > 0
    t = d["t_run"][run]
    if not len(t):
        return []
    out = []
    for c in carriers:
        if f"y_{c[0]}" not in d:
            continue
        y = controlled_y(d, c)
        for s in step_info(t, y[run], Reference(scenario.reference_for(c)).steps(), t_end=float(t[-1]) + h, h=h):
            out.append({"carrier": c, **s})
    return out
