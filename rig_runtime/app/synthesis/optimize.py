"""The optimizer's loop: pymoo's NSGA-II (or NSGA-III) asks for a generation of candidates,
Dask evaluates every (candidate, case) run that has no row yet (the campaign's dispatch:
a window of the cluster's threads, a clean stop, a lost scheduler), the min-max verdict of
each candidate is told back.

Cheap first: a candidate's simulated runs are dispatched only if its configs meet every
linear criterion with a demand (:func:`_linear_first`: the design checks and the stability
at every damping case are decided by the analysis in a fraction of a second; a lockstep run
takes tens of seconds).

Resumable: the algorithm is seeded from the spec, so replaying it from the start with the
stored results (told back as they were) proposes the same candidates again — each proposal
is compared with the one recorded (:func:`.store.propose`) — and only runs without a row are
dispatched. Nothing is evaluated twice."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..campaign import dispatch, materialize
from ..campaign.design import unit_design
from ..campaign.task import Job
from . import store as sstore
from .criteria import judge
from .task import CaseJob, evaluate


class ReplayMismatch(Exception):
    """On --resume the optimizer proposed another candidate than the one recorded."""


@dataclass
class Outcome:
    finished: bool                          # every generation evaluated (False: stopped)
    best: Optional[dict] = None             # the best feasible candidate so far
    evaluated: int = 0                      # runs dispatched in this invocation
    skipped: int = 0                        # simulated runs not dispatched: a hard linear constraint failed
    candidates: list = field(default_factory=list)


def initial_population(spec) -> np.ndarray:
    """The first generation: the base config's tunables (``start: config``, clipped to the
    bounds), the rest a Latin hypercube over the bounds from the optimizer's seed."""
    lo = np.array([t.lo for t in spec.tunables])
    hi = np.array([t.hi for t in spec.tunables])
    n = spec.optimizer.population
    first = []
    if spec.optimizer.start == "config":
        first = [np.clip([t.nominal for t in spec.tunables], lo, hi)]
    q = unit_design("lhs", n - len(first), len(lo), spec.optimizer.seed) if n > len(first) else np.zeros((0, len(lo)))
    return np.vstack(first + [lo + q * (hi - lo)])


def algorithm(spec):
    from pymoo.algorithms.moo.nsga2 import NSGA2
    from pymoo.algorithms.moo.nsga3 import NSGA3
    from pymoo.core.problem import Problem
    from pymoo.util.ref_dirs import get_reference_directions
    n_con = sum(c.demand is not None for c in spec.criteria)
    problem = Problem(n_var=len(spec.tunables), n_obj=len(spec.objectives), n_ieq_constr=n_con,
                      xl=np.array([t.lo for t in spec.tunables]), xu=np.array([t.hi for t in spec.tunables]))
    opt = spec.optimizer
    X0 = initial_population(spec)
    if opt.method == "nsga3":
        ref = get_reference_directions("das-dennis", len(spec.objectives), n_partitions=max(1, opt.population // 2))
        alg = NSGA3(ref_dirs=ref, pop_size=opt.population, sampling=X0, seed=opt.seed)
    else:
        alg = NSGA2(pop_size=opt.population, sampling=X0, seed=opt.seed)
    alg.setup(problem, termination=("n_gen", opt.generations), verbose=False)
    return problem, alg


def run(spec, out: Path, store, client, *, stop_requested: Callable[[], bool],
        on_row: Callable[[dict], None], on_candidate: Callable[[dict, Optional[dict]], None]) -> Outcome:
    from pymoo.core.evaluator import Evaluator
    from pymoo.problems.static import StaticProblem
    problem, alg = algorithm(spec)
    base = materialize.config_base(spec.config, {})
    n_cases = len(spec.cases)
    names = [t.name for t in spec.tunables]
    outcome = Outcome(finished=False)
    next_id, gen = 0, 0
    texts = {j: sstore.case_scenario(out, j).read_text() for j, c in enumerate(spec.cases) if c.scenario is not None}
    while alg.has_next():
        pop = alg.ask()
        X = pop.get("X")
        ids = list(range(next_id, next_id + len(X)))
        next_id += len(X)
        jobs: list[CaseJob] = []
        for k, x in zip(ids, X):
            x = [float(v) for v in x]
            old = sstore.propose(store, k, gen, x)
            if old is not None and not np.array_equal(np.array(old), np.array(x)):
                raise ReplayMismatch(f"candidate {k} (generation {gen}) was {old}, the optimizer now proposes {x} "
                                     "(another pymoo version?); start a new synthesis")
            jobs += _jobs(spec, out, store, base, texts, k, gen, dict(zip(names, x)))
        done = store.done_ids()
        todo = [j for j in jobs if j.run_id not in done]
        todo = _linear_first(spec, store, todo, on_row, outcome)
        if todo:
            def row_in(job, row):
                store.add_result(row, None)
                outcome.evaluated += 1
                on_row(row)
            finished = dispatch.run_all(client, todo, on_dispatch=store.note_dispatch, on_row=row_in,
                                        stop_requested=stop_requested, task=evaluate)
            if not finished:
                return outcome
        rows = sstore.results(store, [k * n_cases + j for k in ids for j in range(n_cases)])
        F, G = [], []
        for k, x in zip(ids, X):
            by_case = {c.name: rows[k * n_cases + j] for j, c in enumerate(spec.cases)}
            v = judge(spec, by_case)
            sstore.add_candidate(store, k, gen, [float(a) for a in x], v)
            F.append(v.objectives)
            G.append(v.constraints)
            cand = {"candidate": k, "x": dict(zip(names, map(float, x))), "verdict": v}
            outcome.candidates.append(cand)
            if v.feasible and (outcome.best is None or _better(spec, v, outcome.best["verdict"])):
                outcome.best = cand
            on_candidate(cand, outcome.best)
        told = {"F": np.array(F, float)}
        if problem.n_ieq_constr:
            told["G"] = np.array(G, float)
        Evaluator().eval(StaticProblem(problem, **told), pop)
        alg.tell(infills=pop)
        gen += 1
    outcome.finished = True
    return outcome


def hard_linear(spec) -> tuple:
    """The linear criteria with a demand: constraints the analysis decides without a run."""
    return tuple(c for c in spec.criteria if c.linear and c.demand is not None)


def linear_refusal(spec, values: dict) -> Optional[str]:
    """Why a config's linear criteria (``values``) break a hard constraint, or None."""
    for c in hard_linear(spec):
        v = values.get(c.name)
        if v is None or not v <= c.demand:
            return f"linear constraint {c.name} = {'undefined' if v is None else f'{v:.6g}'} > {c.demand:g}"
    return None


def _linear_first(spec, store, todo: list, on_row, outcome: Outcome) -> list:
    """Cheap first: the linear criteria of each simulated run's config, here, before any
    lockstep run; a run whose config breaks a hard linear constraint (a design check, the
    stability at every damping case) gets its row now — status ``skipped``, the linear values,
    no metrics (undefined: the candidate is infeasible) — and is not dispatched. One analysis
    per distinct config (the cases of a candidate differ mostly in scenario and seed)."""
    if not hard_linear(spec):
        return todo
    from .task import evaluate
    cache: dict[str, dict] = {}
    keep = []
    for job in todo:
        if not job.simulate:
            keep.append(job)
            continue
        text = job.run.config_text
        if text not in cache:
            lin = evaluate(replace(job, simulate=False))
            cache[text] = {n: lin.get(n) for n in spec.linear_names} if lin.get("status") != "error" else None
        values = cache[text]
        why = "linear criteria not computable" if values is None else linear_refusal(spec, values)
        if why is None:
            keep.append(job)
            continue
        row = {"run_id": job.run_id, "status": "skipped", "why": why, "error": "", "faults": "[]", **(values or {})}
        store.add_result(row, None)
        outcome.skipped += 1
        on_row(row)
    return keep


def _better(spec, a, b) -> bool:
    from .criteria import normalised
    ref = [1.0] * len(spec.objectives)
    return normalised(spec, a.objectives, ref) < normalised(spec, b.objectives, ref)


def _jobs(spec, out: Path, store, base, texts: dict, k: int, gen: int, x: dict) -> list[CaseJob]:
    """The runs of candidate ``k``: files written, sample rows (kept if they exist)."""
    n_cases = len(spec.cases)
    hardware = None
    jobs, samples, evals = [], [], []
    for j, case in enumerate(spec.cases):
        run_id = k * n_cases + j
        values = {**case.values, **x}
        sc = sstore.case_scenario(out, j)
        cfg, _ = materialize.write_run_files(out, base, values, run_id, sc)
        if hardware is None:
            hardware = (out / "configs" / materialize.HARDWARE_NAME).read_text()
        simulate = case.scenario is not None
        cmd = (materialize.reproduce_command(cfg, sc, case.seed, case.duration_s) if simulate
               else f"rig tune --config {cfg}")
        samples.append((run_id, case.seed, *x.values(), str(cfg), str(sc) if simulate else "", cmd))
        evals.append((run_id, k, case.name))
        job = Job(run_id=run_id, config_text=cfg.read_text(), hardware_text=hardware,
                  scenario_text=texts.get(j, ""), seed=case.seed, duration_s=case.duration_s, settle_s=spec.settle_s,
                  criteria={}, no_fault=False, keep_logs="none", audit_path=str(out / "started.log"))
        jobs.append(CaseJob(run_id=run_id, run=job, simulate=simulate, linear=spec.linear_names))
    store.add_samples(samples, skip_existing=True)
    sstore.add_evaluations(store, evals)
    return jobs
