"""Min-max over the cases, as MOPS does it: each criterion's worst value over the cases (and
the case that gives it); the optimizer minimises the objectives' worst values subject to
``worst <= demand`` for every criterion with a demand. A value that is missing — a run the
stability gate refused, a step that never settled, an analysis that overflowed — counts as
:data:`UNDEFINED` (far beyond any demand)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

UNDEFINED = 1e6


@dataclass(frozen=True, kw_only=True)
class Verdict:
    worst: dict             # criterion -> its worst value over the cases (None: undefined in a case)
    worst_case: dict        # criterion -> the case that gives it
    objectives: list        # the objectives' worst values (UNDEFINED for None), in the spec's order
    constraints: list       # (worst - demand) / scale per criterion with a demand (<= 0: met)
    violation: float        # sum of the positive constraints
    feasible: bool


def _value(row: Mapping, name: str) -> Optional[float]:
    v = row.get(name)
    if v is None or not math.isfinite(float(v)):
        return None
    return float(v)


def judge(spec, rows: Mapping[str, Mapping]) -> Verdict:
    """``rows``: each case's row (by case name), as the task returned it or the table holds it."""
    worst, where = {}, {}
    for c in spec.criteria:
        cases = [k for k in spec.cases if c.linear or k.scenario is not None]
        vals = [(_value(rows[k.name], c.name), k.name) for k in cases]
        missing = [n for v, n in vals if v is None]
        if missing:
            worst[c.name], where[c.name] = None, missing[0]
        else:
            v, n = max(vals)
            worst[c.name], where[c.name] = v, n
    objectives = [UNDEFINED if worst[c.name] is None else worst[c.name] for c in spec.objectives]
    constraints = []
    for c in spec.criteria:
        if c.demand is None:
            continue
        w = UNDEFINED if worst[c.name] is None else worst[c.name]
        constraints.append((w - c.demand) / scale(c.demand))
    violation = sum(max(0.0, g) for g in constraints)
    return Verdict(worst=worst, worst_case=where, objectives=objectives, constraints=constraints,
                   violation=violation, feasible=violation == 0.0)


def scale(demand: float) -> float:
    """A demand's magnitude, to put different units' violations on one scale."""
    return abs(demand) if demand else 1.0


def normalised(spec, objectives: Sequence[float], ref: Sequence[float]) -> float:
    """The sum of the objectives, each divided by its demand (or by ``ref``, the front's
    median, for an objective without one): how the chosen point is picked from the front."""
    total = 0.0
    for c, f, r in zip(spec.objectives, objectives, ref):
        total += f / (scale(c.demand) if c.demand is not None else (abs(r) or 1.0))
    return total
