"""A varied quantity's distribution: a map from a unit sample ``q ∈ (0, 1)`` (a QMC or SALib
design's coordinate) to a value, by the inverse CDF. Sampling in the unit cube and mapping
afterwards keeps one design for every distribution, and Sobol indices of the unit
coordinates are those of the values (monotone maps of independent inputs)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy import stats

Q_EPS = 1e-12       # a unit sample is kept inside (0, 1): a normal's ppf(0) is -inf


@dataclass(frozen=True, kw_only=True)
class Distribution:
    """``kind``: uniform (``lo``..``hi``), normal (``mean``, ``sd``) or values (a finite set,
    a grid's levels). ``levels``: points per axis of a full-factorial grid."""

    kind: str
    lo: float = math.nan
    hi: float = math.nan
    mean: float = math.nan
    sd: float = math.nan
    values: tuple[float, ...] = ()
    levels: Optional[int] = None

    def ppf(self, q: np.ndarray) -> np.ndarray:
        q = np.clip(np.asarray(q, float), Q_EPS, 1 - Q_EPS)
        if self.kind == "uniform":
            return self.lo + q * (self.hi - self.lo)
        if self.kind == "normal":
            return stats.norm.ppf(q, loc=self.mean, scale=self.sd) if self.sd > 0 else np.full_like(q, self.mean)
        idx = np.minimum((q * len(self.values)).astype(int), len(self.values) - 1)
        return np.asarray(self.values, float)[idx]

    def grid(self) -> np.ndarray:
        """The levels of a full-factorial grid: the listed values, or ``levels`` points
        from ``lo`` to ``hi`` (a normal: mean ± 2 sd)."""
        if self.kind == "values":
            return np.asarray(self.values, float)
        n = self.levels or 3
        lo, hi = (self.lo, self.hi) if self.kind == "uniform" else (self.mean - 2 * self.sd, self.mean + 2 * self.sd)
        return np.linspace(lo, hi, n)

    def extremes(self) -> tuple[float, float]:
        """The values to check against the config's rules and hardware ceilings before any
        run: the range's ends, the extreme listed values, a normal's mean ± 5 sd (beyond it:
        less than one sample in 3 million)."""
        if self.kind == "uniform":
            return self.lo, self.hi
        if self.kind == "normal":
            return self.mean - 5 * self.sd, self.mean + 5 * self.sd
        return min(self.values), max(self.values)

    def describe(self) -> str:
        if self.kind == "uniform":
            return f"uniform [{self.lo:.6g}, {self.hi:.6g}]"
        if self.kind == "normal":
            return f"normal (mean {self.mean:.6g}, sd {self.sd:.6g})"
        return "values " + ", ".join(f"{v:.6g}" for v in self.values)
