"""Numbers of the report: the pass rate with its exact (Clopper-Pearson) interval, which
parameters separate passing from failing runs (regional sensitivity: the Kolmogorov-Smirnov
distance between the two groups' values), and Sobol' indices with their bootstrap
confidence intervals (SALib) for a Saltelli design."""

from __future__ import annotations

from typing import Optional

import numpy as np
from scipy import stats


def pass_rate(passed: int, judged: int, level: float = 0.95) -> tuple[float, float, float]:
    """(rate, lo, hi) as fractions; the exact binomial interval."""
    if judged == 0:
        return float("nan"), float("nan"), float("nan")
    ci = stats.binomtest(passed, judged).proportion_ci(confidence_level=level, method="exact")
    return passed / judged, float(ci.low), float(ci.high)


def separation(X: np.ndarray, failed: np.ndarray) -> np.ndarray:
    """Per parameter, the KS distance between the failing and the passing runs' values
    (0: failures spread like passes; 1: the parameter alone separates them)."""
    if failed.all() or not failed.any():
        return np.zeros(X.shape[1])
    return np.array([stats.ks_2samp(X[failed, j], X[~failed, j]).statistic for j in range(X.shape[1])])


def rank_correlation(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    ok = np.isfinite(y)
    if ok.sum() < 3:
        return np.zeros(X.shape[1])
    out = []
    for j in range(X.shape[1]):
        r = stats.spearmanr(X[ok, j], y[ok]).statistic
        out.append(0.0 if not np.isfinite(r) else abs(r))
    return np.array(out)


def sobol_indices(names: list[str], y: np.ndarray, seed: int = 0) -> Optional[dict]:
    """First- and total-order indices with 95 % bootstrap intervals for a Saltelli design
    without second order (rows in design order); None if a value is missing."""
    if not np.all(np.isfinite(y)):
        return None
    from SALib.analyze import sobol
    d = len(names)
    problem = {"num_vars": d, "names": list(names), "bounds": [[0.0, 1.0]] * d}
    if np.var(y) == 0:
        z = np.zeros(d)
        return {"S1": z, "S1_conf": z, "ST": z, "ST_conf": z, "constant": True}
    r = sobol.analyze(problem, y, calc_second_order=False, num_resamples=200, conf_level=0.95, seed=seed)
    return {k: np.asarray(r[k], float) for k in ("S1", "S1_conf", "ST", "ST_conf")} | {"constant": False}
