"""One optimisation problem (1): bounded nonlinear least squares with 95 % intervals.

``solve`` wraps ``scipy.optimize.least_squares``. Intervals come from the Jacobian at the
optimum: cov = s² (JᵀJ)⁻¹ with s² = 2·cost/(m − n), inflated for the residual's lag-one
autocorrelation, interval = value ± 1.96 σ (a local, linearised interval: where the model
misses part of the dynamics it is still too narrow; docs/identification.md says how to read it).
Correlations with |ρ| > 0.95 are flagged: those parameters are poorly identifiable apart.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import multiprocessing
import os
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import least_squares

CORR_FLAG = 0.95
WORKERS = min(2, os.cpu_count() or 1)   # processes for the Jacobian columns of the costly fits

_FUN: Callable | None = None            # the objective, inherited by the forked workers


def _eval(x: np.ndarray) -> np.ndarray:
    return _FUN(x)


@dataclass(frozen=True)
class Fit:
    names: tuple[str, ...]
    values: np.ndarray
    ci95: np.ndarray            # (n, 2)
    corr: np.ndarray            # (n, n)
    rms: float                  # RMS of the residual at the optimum
    n_residuals: int
    nfev: int
    message: str
    cov: np.ndarray = field(repr=False, default=None)

    def value(self, name: str) -> float:
        return float(self.values[self.names.index(name)])

    def poorly_identifiable(self) -> list[tuple[str, str, float]]:
        out = []
        for i in range(len(self.names)):
            for j in range(i + 1, len(self.names)):
                r = self.corr[i, j]
                if np.isfinite(r) and abs(r) > CORR_FLAG:
                    out.append((self.names[i], self.names[j], float(r)))
        return out

    def as_dict(self) -> dict:
        return {
            "parameters": {n: {"value": float(v), "ci95": [float(a), float(b)]}
                           for n, v, (a, b) in zip(self.names, self.values, self.ci95)},
            "residual_rms": self.rms, "n_residuals": self.n_residuals, "nfev": self.nfev,
            "poorly_identifiable": [{"a": a, "b": b, "correlation": r} for a, b, r in self.poorly_identifiable()],
        }


def covariance(jac: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """s² (JᵀJ)⁻¹, inflated by (1 + ρ)/(1 − ρ) for the lag-one autocorrelation ρ > 0 of the
    residual (an AR(1) reading of correlated residuals: fewer independent samples).

    (JᵀJ)⁻¹ is computed with J's columns scaled to unit norm: the columns differ by up to
    10⁹ in size (K against beta − gamma), and a pseudo-inverse of the raw JᵀJ (condition
    ~10¹⁷) drops the small singular directions, which made the interval of beta − gamma 100×
    too narrow. A column that is zero (a parameter the data do not contain) keeps a zero
    variance, as before."""
    m, n = jac.shape
    norm = np.sqrt(np.sum(jac * jac, axis=0))
    scale = np.where(norm > 0, 1.0 / np.where(norm > 0, norm, 1.0), 0.0)
    js = jac * scale
    s2 = float(residual @ residual) / max(m - n, 1)
    r = residual - residual.mean()
    den = float(r @ r)
    rho = float(r[1:] @ r[:-1]) / den if den > 0 and m > 2 else 0.0
    rho = min(max(rho, 0.0), 0.99)
    return np.linalg.pinv(js.T @ js) * np.outer(scale, scale) * s2 * (1 + rho) / (1 - rho)


def _corr(cov: np.ndarray) -> np.ndarray:
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        return cov / np.outer(sd, sd)


def solve(fun: Callable[[np.ndarray], np.ndarray], x0: Sequence[float], names: Sequence[str],
          lower: Sequence[float], upper: Sequence[float], *, loss: str = "linear",
          x_scale: Sequence[float] | str = "jac", diff_step: float | None = None, tol: float = 1e-8,
          parallel: bool = False) -> Fit:
    """Minimise ``sum(fun(x)**2)`` within bounds; intervals from the Jacobian at the optimum.
    ``tol``: scipy's ftol = xtol (relative change of cost / parameters that ends the search).
    ``parallel``: forward-difference Jacobian columns (steps relative to each parameter) evaluated
    in ``WORKERS`` forked processes; the numbers do not depend on the number of workers."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    kw = dict(bounds=(lo, hi), loss=loss, x_scale=x_scale, method="trf", ftol=tol, xtol=tol)
    if not parallel or WORKERS < 2:
        r = least_squares(fun, np.asarray(x0, float), diff_step=diff_step, **kw)
        return from_result(names, r.x, r.jac, r.fun, r.nfev, r.message)
    global _FUN
    _FUN = fun
    cache: dict = {}

    def f(x):
        y = fun(x)
        cache["x"], cache["y"] = np.array(x), y
        return y
    rel = np.sqrt(np.finfo(float).eps) if diff_step is None else diff_step
    with multiprocessing.get_context("fork").Pool(WORKERS) as pool:
        def jac(x):
            f0 = cache["y"] if "x" in cache and np.array_equal(cache["x"], x) else fun(x)
            steps = rel * np.maximum(np.abs(x), 1e-6) * np.where(x >= 0, 1.0, -1.0)   # relative steps
            steps = np.where((x + steps > hi) | (x + steps < lo), -steps, steps)
            pts = [x + np.eye(len(x))[i] * steps[i] for i in range(len(x))]
            cols = pool.map(_eval, pts)
            return np.column_stack([(c - f0) / s_ for c, s_ in zip(cols, steps)])
        r = least_squares(f, np.asarray(x0, float), jac=jac, **kw)
    _FUN = None
    return from_result(names, r.x, r.jac, r.fun, r.nfev, r.message)


def from_result(names, x, jac, res, nfev=0, message="") -> Fit:
    cov = covariance(np.asarray(jac), np.asarray(res))
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    ci = np.column_stack([x - 1.96 * sd, x + 1.96 * sd])
    return Fit(tuple(names), np.asarray(x, float), ci, _corr(cov), float(np.sqrt(np.mean(np.square(res)))),
               len(res), int(nfev), str(message), cov)


def transform(fit: Fit, names: Sequence[str], values: np.ndarray, T: np.ndarray) -> Fit:
    """The same fit in other parameters p = values with dp = T dx (delta method)."""
    cov = T @ fit.cov @ T.T
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    ci = np.column_stack([values - 1.96 * sd, values + 1.96 * sd])
    return Fit(tuple(names), np.asarray(values, float), ci, _corr(cov), fit.rms, fit.n_residuals, fit.nfev,
               fit.message, cov)
