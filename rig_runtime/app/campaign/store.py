"""The campaign's table: SQLite in ``DIR/campaign.sqlite``.

Why SQLite and not Parquet: rows arrive one by one over hours and the campaign must survive
a Ctrl-C, a killed worker or a lost scheduler. SQLite commits each row in its own
transaction (a kill loses at most the row being written, never the file), its primary key
on ``run_id`` makes a duplicate row impossible (``--resume`` reads what is done and runs
the rest), the file is readable while the campaign runs (``sqlite3``, pandas
``read_sql``), and it is in Python's standard library. A Parquet file is written whole at
close: streaming would need a file per batch, compaction, and our own de-duplication.

Tables: ``meta`` (the spec, the parameter names), ``samples`` (each run's parameters, seed,
files and reproducing command, written before any run), ``results`` (one row per finished
run), ``dispatches`` (one row each time a run was handed to Dask); the view ``runs`` joins
samples and results: the table of the campaign."""

from __future__ import annotations

import datetime as _dt
import json
import sqlite3
from pathlib import Path
from typing import Iterable, Optional, Sequence

from .outcome import METRICS

DB_NAME = "campaign.sqlite"
BASE_COLUMNS = ("status", "why", "error", "final_state", "exit_code", "n_faults_raised", "faults",
                "sim_s", "wall_s", "worker", "log", "finished_at")
RESULT_COLUMNS = BASE_COLUMNS + tuple(METRICS)


def _q(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


class Store:
    """``metrics``: the result columns after the run's own (the campaign metrics; ``rig
    synthesize`` adds its linear criteria)."""

    def __init__(self, path: Path, metrics: Sequence[str] = tuple(METRICS)):
        self.path = Path(path)
        self.metrics = tuple(metrics)
        self.db = sqlite3.connect(self.path)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute("PRAGMA synchronous=NORMAL")

    def close(self) -> None:
        self.db.close()

    # ------------------------------------------------------------------ creation
    def create(self, meta: dict, names: Sequence[str]) -> None:
        params = ", ".join(f"{_q('p:' + n)} REAL" for n in names)
        metrics = ", ".join(f"{_q(m)} REAL" for m in self.metrics)
        with self.db:
            self.db.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT)")
            self.db.execute(f"CREATE TABLE samples (run_id INTEGER PRIMARY KEY, seed INTEGER, {params}, "
                            "config TEXT, scenario TEXT, command TEXT)")
            self.db.execute("CREATE TABLE results (run_id INTEGER PRIMARY KEY, status TEXT, why TEXT, error TEXT, "
                            "final_state TEXT, exit_code INTEGER, n_faults_raised INTEGER, faults TEXT, sim_s REAL, "
                            f"wall_s REAL, worker TEXT, log TEXT, finished_at TEXT, {metrics})")
            self.db.execute("CREATE TABLE dispatches (run_id INTEGER, at TEXT)")
            pcols = ", ".join(f"s.{_q('p:' + n)}" for n in names)
            self.db.execute(f"CREATE VIEW runs AS SELECT s.run_id, s.seed, {pcols}, r.status, r.why, r.error, "
                            "r.final_state, r.exit_code, r.faults, " + ", ".join(f"r.{_q(m)}" for m in self.metrics) +
                            ", r.sim_s, r.wall_s, r.worker, r.log, s.command, r.finished_at "
                            "FROM samples s JOIN results r USING (run_id)")
            self.db.executemany("INSERT INTO meta VALUES (?, ?)", [(k, json.dumps(v)) for k, v in meta.items()])

    def add_samples(self, rows: Iterable[tuple], *, skip_existing: bool = False) -> None:
        """``skip_existing``: a run_id that has its sample row already keeps it (``rig
        synthesize --resume`` writes a generation's samples again)."""
        verb = "INSERT OR IGNORE" if skip_existing else "INSERT"
        with self.db:
            self.db.executemany(f"{verb} INTO samples VALUES ({','.join('?' * self._n_sample_cols())})", rows)

    def _n_sample_cols(self) -> int:
        return len(self.db.execute("SELECT * FROM samples LIMIT 0").description)

    def set_meta(self, key: str, value) -> None:
        with self.db:
            self.db.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)", (key, json.dumps(value)))

    # ------------------------------------------------------------------ reading
    def meta(self) -> dict:
        return {k: json.loads(v) for k, v in self.db.execute("SELECT key, value FROM meta")}

    def done_ids(self) -> set[int]:
        return {r[0] for r in self.db.execute("SELECT run_id FROM results")}

    def sample_ids(self) -> list[int]:
        return [r[0] for r in self.db.execute("SELECT run_id FROM samples ORDER BY run_id")]

    def sample(self, run_id: int) -> dict:
        cur = self.db.execute("SELECT * FROM samples WHERE run_id = ?", (run_id,))
        return dict(zip([d[0] for d in cur.description], cur.fetchone()))

    def table(self, order: str = "run_id") -> tuple[list[str], list[tuple]]:
        cur = self.db.execute(f"SELECT * FROM runs ORDER BY {order}")
        return [d[0] for d in cur.description], cur.fetchall()

    def counts(self) -> dict[str, int]:
        return dict(self.db.execute("SELECT status, COUNT(*) FROM results GROUP BY status").fetchall())

    # ------------------------------------------------------------------ writing results
    def note_dispatch(self, run_id: int) -> None:
        with self.db:
            self.db.execute("INSERT INTO dispatches VALUES (?, ?)", (run_id, _now()))

    def add_result(self, row: dict, log: Optional[str]) -> bool:
        """Insert one finished run; False if the run already has a row (never two)."""
        values = dict(row, log=log or "", finished_at=_now(),
                      n_faults_raised=len(json.loads(row.get("faults") or "[]")))
        cols = ("run_id",) + BASE_COLUMNS + self.metrics
        with self.db:
            cur = self.db.execute(f"INSERT OR IGNORE INTO results ({','.join(_q(c) for c in cols)}) "
                                  f"VALUES ({','.join('?' * len(cols))})", [values.get(c) for c in cols])
        return cur.rowcount == 1


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")
