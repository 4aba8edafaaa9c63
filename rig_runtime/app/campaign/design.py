"""The samples of a campaign, drawn once from the spec's design (reproducible from its seed)
and stored with the campaign: a QMC Sobol' sequence or a Latin hypercube
(``scipy.stats.qmc``), plain random, a full-factorial grid (sweeps), or SALib's Saltelli
design for Sobol' indices (first and total order: ``n·(d + 2)`` runs)."""

from __future__ import annotations

import inspect
import itertools
from dataclasses import dataclass

import numpy as np

from .spec import Spec


@dataclass(frozen=True, kw_only=True)
class Samples:
    names: tuple[str, ...]
    values: np.ndarray          # (runs, parameters), the parameter values of each run
    seeds: tuple[int, ...]      # each run's seed

    def row(self, i: int) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, self.values[i])}


def _rng_kw(cls, seed: int) -> dict:
    """scipy >= 1.15 names the generator ``rng``; older versions ``seed``."""
    key = "rng" if "rng" in inspect.signature(cls.__init__).parameters else "seed"
    return {key: np.random.default_rng(seed)}


def unit_design(method: str, n: int, d: int, seed: int) -> np.ndarray:
    """Points in the unit cube (0, 1)^d for the sampled methods."""
    if method == "sobol":
        from scipy.stats import qmc
        return qmc.Sobol(d, scramble=True, **_rng_kw(qmc.Sobol, seed)).random_base2(int(np.log2(n)))
    if method == "lhs":
        from scipy.stats import qmc
        return qmc.LatinHypercube(d, **_rng_kw(qmc.LatinHypercube, seed)).random(n)
    if method == "random":
        return np.random.default_rng(seed).random((n, d))
    if method == "saltelli":
        from SALib.sample import sobol as salib_sobol
        problem = {"num_vars": d, "names": [f"x{i}" for i in range(d)], "bounds": [[0.0, 1.0]] * d}
        return salib_sobol.sample(problem, n, calc_second_order=False, seed=seed)
    raise ValueError(method)


def draw(spec: Spec) -> Samples:
    """Every run's parameter values and seed."""
    names = tuple(p.name for p in spec.parameters)
    if spec.design.method == "grid":
        values = np.array(list(itertools.product(*(p.dist.grid() for p in spec.parameters))), float)
    else:
        q = unit_design(spec.design.method, spec.design.n, len(names), spec.design.seed)
        values = np.column_stack([p.dist.ppf(q[:, j]) for j, p in enumerate(spec.parameters)])
    n = len(values)
    seeds = tuple(spec.seed_value + i if spec.seed_per_run else spec.seed_value for i in range(n))
    return Samples(names=names, values=values, seeds=seeds)
