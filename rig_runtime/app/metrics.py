"""Step-response figures of a run (python-control's ``step_info`` names, per reference step).

Definitions (also in docs/dry-run.md): for a reference step from ``a`` to ``b`` at ``t0``
(window up to the next change of any controlled carrier's reference, or the end of the run:
the other carrier's step is judged by its own figures and the held-carrier excursion), with the response
normalised as ``r = (y − a)/(b − a)`` and ``y`` smoothed by a centred 50 ms moving average
(removes sensor noise, not dynamics):
- rise time: first time ``r`` reaches 0.9 minus first time it reaches 0.1;
- overshoot: ``max(r) − 1`` in percent (0 if it never exceeds 1);
- settling time: from ``t0`` to the last time ``|r − 1| > 0.02`` in the window;
- steady-state error: mean of ``y − b`` over the last second of the window, in mm;
- held-carrier excursion (two controlled carriers, the other one's reference holding through
  the window): max |y_other − y_ref,other| over the window (smoothed), in mm and in % of
  |b − a| — how far a step on one carrier knocks the other off its reference.

``y`` is the y the lane controlled on: the measured one, the observer's ŷ while the carrier
was DEGRADED (:func:`controlled_y`).
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np


def _smooth(y: np.ndarray, n: int) -> np.ndarray:
    if n <= 1 or len(y) < n:
        return y
    k = np.ones(n) / n
    pad = n // 2
    yp = np.pad(y, (pad, n - 1 - pad), mode="edge")
    return np.convolve(yp, k, mode="valid")


def step_info(t: np.ndarray, y: np.ndarray, steps: list[tuple[float, float, float]], t_end: float,
              h: float = 0.005, smooth_s: float = 0.05, changes: Optional[list[float]] = None) -> list[dict]:
    """Figures for each (t0, from_m, to_m) step; times in s, values in mm. ``changes``: the
    times at which any reference changes (a window ends at the first one after its t0);
    None: the steps' own times."""
    ys = _smooth(np.asarray(y, float), max(1, int(round(smooth_s / h))))
    ends = sorted(changes) if changes is not None else [s[0] for s in steps]
    out = []
    for i, (t0, a, b) in enumerate(steps):
        t1 = next((c for c in ends if c > t0), t_end)
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
    """``step_info`` for every reference step of ``scenario`` from a recorded run (its path,
    or what ``export.read_log`` returned for it), per
    controlled carrier (the log's ``controlled``) on that carrier's own reference
    (``scenario.reference_for``) and the y its lane controlled on (:func:`controlled_y`);
    each step names its ``carrier``. A window ends at the next change of any controlled
    carrier's reference; with another controlled carrier whose reference holds through the
    window, the step also has ``held`` (that carrier) and its ``held_excursion_mm`` / ``_pct``."""
    from ..scenario import Reference
    from .export import read_log
    if scenario is None:
        return []
    log_d = log if isinstance(log, dict) else read_log(log)     # a path, or the log as read_log read it
    d = log_d["columns"]
    carriers = log_d["attrs"].get("controlled") or ["rear"]
    if isinstance(carriers, str):
        carriers = [carriers]
    carriers = [c for c in carriers if f"y_{c[0]}" in d]
    run = d["t_run"] > 0
    t = d["t_run"][run]
    if not len(t):
        return []
    refs = {c: Reference(scenario.reference_for(c)) for c in carriers}
    own = {c: refs[c].steps() for c in carriers}
    changes = sorted({s[0] for c in carriers for s in own[c]})
    t_end = float(t[-1]) + h
    n_smooth = max(1, int(round(0.05 / h)))
    out = []
    for c in carriers:
        y = controlled_y(d, c)
        for (t0, a, b), s in zip(own[c], step_info(t, y[run], own[c], t_end=t_end, h=h, changes=changes)):
            rec = {"carrier": c, **s}
            for k in carriers:
                if k == c or any(st[0] == t0 for st in own[k]):
                    continue                    # the same carrier, or it steps at the same time
                t1 = next((x for x in changes if x > t0), t_end)
                sel = (t >= t0) & (t < t1)
                if sel.sum() < 2 or a == b:
                    continue
                yk = _smooth(np.asarray(controlled_y(d, k)[run], float), n_smooth)
                exc = float(np.max(np.abs(yk[sel] - refs[k](t0))))
                rec.update(held=k, held_excursion_mm=exc * 1e3, held_excursion_pct=100.0 * exc / abs(b - a))
            out.append(rec)
    return out
