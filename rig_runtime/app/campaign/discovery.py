"""Where the runs fail, as scenario-discovery tools put it: the bounds that every failure
keeps (a one-line statement), and a PRIM box (patient rule induction, Friedman & Fisher
1999): peel small slices off the sampled box, each time the slice that raises the failure
density inside most, until the box would hold less than ``min_coverage`` of the failures.
The box is reported with its coverage (failures inside / all failures) and density
(failures inside / runs inside)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, kw_only=True)
class Box:
    limits: dict[str, tuple[float, float]]      # only the restricted parameters
    coverage: float
    density: float
    runs_inside: int


def failure_bounds(names, X: np.ndarray, failed: np.ndarray, min_cut: float = 0.1) -> list[str]:
    """Statements ``NAME < v`` / ``NAME > v`` true of every failure, where the bound cuts off
    at least ``min_cut`` of the sampled range (weaker bounds say nothing)."""
    out = []
    if not failed.any():
        return out
    for j, n in enumerate(names):
        lo, hi = X[:, j].min(), X[:, j].max()
        span = hi - lo
        if span <= 0:
            continue
        flo, fhi = X[failed, j].min(), X[failed, j].max()
        if (hi - fhi) / span >= min_cut:
            out.append(f"{n} <= {fhi:.4g}")
        if (flo - lo) / span >= min_cut:
            out.append(f"{n} >= {flo:.4g}")
    return out


def prim_box(names, X: np.ndarray, failed: np.ndarray, alpha: float = 0.05, min_coverage: float = 0.8) -> Box | None:
    if failed.sum() < 2 or failed.all():
        return None
    inside = np.ones(len(X), bool)
    lo, hi = X.min(axis=0).astype(float), X.max(axis=0).astype(float)
    total_fail = failed.sum()
    while True:
        best = None
        dens_now = failed[inside].mean()
        for j in range(X.shape[1]):
            xj = X[inside, j]
            for side in (0, 1):
                cut = np.quantile(xj, alpha if side == 0 else 1 - alpha)
                keep = inside & ((X[:, j] >= cut) if side == 0 else (X[:, j] <= cut))
                if keep.sum() == inside.sum() or keep.sum() < 2:
                    continue
                cov = failed[keep].sum() / total_fail
                if cov < min_coverage:
                    continue
                dens = failed[keep].mean()
                if best is None or dens > best[0]:
                    best = (dens, j, side, cut, keep)
        if best is None or best[0] <= dens_now:
            break
        _, j, side, cut, keep = best
        if side == 0:
            lo[j] = cut
        else:
            hi[j] = cut
        inside = keep
    full_lo, full_hi = X.min(axis=0), X.max(axis=0)
    limits = {n: (float(lo[j]), float(hi[j])) for j, n in enumerate(names)
              if lo[j] > full_lo[j] or hi[j] < full_hi[j]}
    return Box(limits=limits, coverage=float(failed[inside].sum() / total_fail), density=float(failed[inside].mean()),
               runs_inside=int(inside.sum()))
