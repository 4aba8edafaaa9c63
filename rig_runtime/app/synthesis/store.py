"""The synthesis' directory and tables: the campaign's table (``campaign/store.py``: one row per
(candidate, case) run — its parameters, seed, metrics, reproducing command — committed as it
arrives, the dispatches) with the linear criteria as extra metric columns, and beside it:

- ``proposals``: each candidate the optimizer asked for (its generation and tunables), written
  before any of its runs — on ``--resume`` the optimizer is replayed from its seed and must
  propose the same ones (checked), so that nothing is evaluated twice;
- ``evaluations``: which candidate and case each run is;
- ``candidates``: each fully evaluated candidate's worst value per criterion over the cases,
  the case that gives it, its objectives, its constraint violation, feasible or not;
- the view ``case_runs``: the campaign's ``runs`` with candidate and case."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Optional

import yaml

from rig_runtime.errors import ConfigError

from ..campaign.outcome import METRICS
from ..campaign.store import DB_NAME, Store

SPEC_COPY = "spec.yaml"


def spec_hash(spec) -> str:
    return hashlib.sha256(Path(spec.source).read_bytes()).hexdigest()


def metric_columns(spec) -> tuple[str, ...]:
    return spec.linear_names + tuple(METRICS)


def case_scenario(out: Path, j: int) -> Path:
    return out / "scenarios" / f"case-{j:02d}.yaml"


def create(spec, out: Path) -> Store:
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(spec.source, out / SPEC_COPY)
    (out / "scenarios").mkdir(exist_ok=True)
    for j, case in enumerate(spec.cases):
        if case.scenario is not None:
            case_scenario(out, j).write_text(yaml.safe_dump(case.scenario, sort_keys=False))
    store = Store(out / DB_NAME, metrics=metric_columns(spec))
    store.create({"spec": spec.to_json(), "spec_sha256": spec_hash(spec), "names": [t.name for t in spec.tunables],
                  "kind": "synthesis", "complete": True}, [t.name for t in spec.tunables])
    with store.db:
        store.db.execute("CREATE TABLE proposals (candidate INTEGER PRIMARY KEY, generation INTEGER, x TEXT)")
        store.db.execute("CREATE TABLE evaluations (run_id INTEGER PRIMARY KEY, candidate INTEGER, case_name TEXT)")
        store.db.execute("CREATE TABLE candidates (candidate INTEGER PRIMARY KEY, generation INTEGER, x TEXT, "
                         "worst TEXT, worst_case TEXT, objectives TEXT, violation REAL, feasible INTEGER)")
        store.db.execute("CREATE VIEW case_runs AS SELECT e.candidate, e.case_name, r.* FROM evaluations e "
                         "JOIN runs r USING (run_id)")
    return store


def reopen(spec, out: Path) -> Store:
    db = out / DB_NAME
    if not db.is_file():
        raise ConfigError(None, "--resume", f"a synthesis directory (no {DB_NAME} in {out})", str(out))
    store = Store(db, metrics=metric_columns(spec))
    meta = store.meta()
    if meta.get("kind") != "synthesis" or meta.get("spec_sha256") != spec_hash(spec):
        store.close()
        raise ConfigError(spec.source, "", f"the spec the synthesis in {out} was started with (it differs; its copy "
                          f"is {out / SPEC_COPY})")
    return store


def open_existing(out: Path) -> Store:
    """A finished or interrupted synthesis, for its report."""
    db = out / DB_NAME
    if not db.is_file():
        raise ConfigError(None, "DIR", f"a synthesis directory (no {DB_NAME} in it)", str(out))
    store = Store(db)
    if store.meta().get("kind") != "synthesis":
        store.close()
        raise ConfigError(None, "DIR", "a synthesis directory (this one holds a campaign)", str(out))
    return store


def propose(store: Store, candidate: int, generation: int, x: list[float]) -> Optional[list[float]]:
    """Record a proposal; returns the one recorded before for this candidate (resume), else None."""
    old = store.db.execute("SELECT x FROM proposals WHERE candidate = ?", (candidate,)).fetchone()
    if old is not None:
        return json.loads(old[0])
    with store.db:
        store.db.execute("INSERT INTO proposals VALUES (?, ?, ?)", (candidate, generation, json.dumps(x)))
    return None


def add_evaluations(store: Store, rows: list[tuple[int, int, str]]) -> None:
    with store.db:
        store.db.executemany("INSERT OR IGNORE INTO evaluations VALUES (?, ?, ?)", rows)


def results(store: Store, run_ids: list[int]) -> dict[int, dict]:
    """The result rows of these runs that have one (by run_id)."""
    cols = ["run_id", "status", "why", "error"] + list(store.metrics)
    q = ", ".join('"' + c + '"' for c in cols)
    out = {}
    for i in range(0, len(run_ids), 500):
        part = run_ids[i:i + 500]
        cur = store.db.execute(f"SELECT {q} FROM results WHERE run_id IN ({','.join('?' * len(part))})", part)
        for r in cur.fetchall():
            out[r[0]] = dict(zip(cols, r))
    return out


def add_candidate(store: Store, candidate: int, generation: int, x: list[float], verdict) -> None:
    with store.db:
        store.db.execute("INSERT OR REPLACE INTO candidates VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                         (candidate, generation, json.dumps(x), json.dumps(verdict.worst),
                          json.dumps(verdict.worst_case), json.dumps(verdict.objectives), verdict.violation,
                          int(verdict.feasible)))


def candidates(store: Store) -> list[dict]:
    cur = store.db.execute("SELECT candidate, generation, x, worst, worst_case, objectives, violation, feasible "
                           "FROM candidates ORDER BY candidate")
    out = []
    for c, g, x, w, wc, f, v, ok in cur.fetchall():
        out.append({"candidate": c, "generation": g, "x": json.loads(x), "worst": json.loads(w),
                    "worst_case": json.loads(wc), "objectives": json.loads(f), "violation": v, "feasible": bool(ok)})
    return out
