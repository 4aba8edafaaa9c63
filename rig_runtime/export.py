"""Read recorder logs (``rig_runtime.recorder``) and export them as CSV.

``read_log(path)`` returns everything in plain numpy/Python objects; ``to_csv`` writes the
cycles table (header = column names, in recording order) and, by default, the events
beside it as ``<out>.events.csv``. Layout: ``docs/log-format.md``.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .recorder import EVENT_FIELDS, EVENT_STR_FIELDS

_BLOCK = 65536          # rows read per block when exporting


def _decode(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.ndarray) and v.dtype.kind in "OS":
        return [_decode(x) for x in v.tolist()]
    if isinstance(v, np.generic):
        return v.item()
    return v


def _column_names(f: h5py.File) -> list[str]:
    if "columns" in f.attrs:
        return [str(c) for c in _decode(f.attrs["columns"])]
    return list(f["cycles"].keys()) if "cycles" in f else []


def _open(path: str | Path) -> h5py.File:
    # locking=False: a log still being written (flushed state) can be looked at, too
    return h5py.File(path, "r", locking=False)


def _read_events(f: h5py.File) -> dict[str, np.ndarray]:
    events: dict[str, np.ndarray] = {}
    g = f.get("events")
    for k in EVENT_FIELDS:
        if g is not None and k in g:
            d = g[k]
            a = np.asarray(d.asstr()[()], dtype=object) if k in EVENT_STR_FIELDS \
                else d[()].astype(np.float64, copy=False)
        else:
            a = np.array([], dtype=object if k in EVENT_STR_FIELDS else np.float64)
        events[k] = a
    m = min(len(a) for a in events.values())
    return {k: a[:m] for k, a in events.items()}


def read_log(path: str | Path) -> dict[str, Any]:
    """Read a whole log.

    Returns ``{"columns": {name: float64 array, ...} in column order, "events": {"t", "kind",
    "device", "check", "value", "limit", "message": arrays}, "attrs": {name: value},
    "rows": int}``. String attributes and event strings come back as ``str`` (event string
    fields as numpy object arrays). If the columns differ in length (a log cut by a crash or
    a failing disk between two flushes) every column is truncated to the shortest.
    """
    with _open(path) as f:
        names = _column_names(f)
        cols = {n: f["cycles"][n][()].astype(np.float64, copy=False) for n in names}
        rows = min((len(a) for a in cols.values()), default=0)
        cols = {n: a[:rows] for n, a in cols.items()}
        events = _read_events(f)
        attrs = {k: _decode(v) for k, v in f.attrs.items()}
    return {"columns": cols, "events": events, "attrs": attrs, "rows": rows}


def _fmt(v: float) -> str:
    """Shortest round-trip text; NaN/Inf spelled so MATLAB, pandas and spreadsheets read them."""
    if v != v:
        return "NaN"
    if math.isinf(v):
        return "Inf" if v > 0 else "-Inf"
    return repr(v)


def events_path_for(out_path: str | Path) -> Path:
    """``run.csv`` -> ``run.events.csv`` (``run`` -> ``run.events.csv``)."""
    p = Path(out_path)
    return p.with_suffix(".events.csv") if p.suffix.lower() == ".csv" else p.with_name(p.name + ".events.csv")


def to_csv(log_path: str | Path, out_path: str | Path, *, events: bool = True) -> int:
    """Write the cycles table of ``log_path`` as CSV (header: the column names); return the row count.

    With ``events`` (default) the events go to ``events_path_for(out_path)`` as well.
    Values are written with full (round-trip) precision, missing values as ``NaN``.
    """
    out = Path(out_path)
    with _open(log_path) as f:
        names = _column_names(f)
        dsets = [f["cycles"][n] for n in names]
        rows = min((d.shape[0] for d in dsets), default=0)
        with open(out, "w", newline="", encoding="utf-8") as fh:
            fh.write(",".join(names) + "\n")
            for a in range(0, rows, _BLOCK):
                b = min(a + _BLOCK, rows)
                block = np.column_stack([d[a:b] for d in dsets]).tolist()
                fh.write("".join(",".join(map(_fmt, r)) + "\n" for r in block))
    if events:
        events_to_csv(log_path, events_path_for(out))
    return rows


def events_to_csv(log_path: str | Path, out_path: str | Path) -> int:
    """Write the events of ``log_path`` as CSV (``t,kind,device,check,value,limit,message``); return the count."""
    with _open(log_path) as f:
        ev = _read_events(f)
    n = len(ev["t"])
    with open(out_path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(EVENT_FIELDS)
        for i in range(n):
            w.writerow([_fmt(float(ev[k][i])) if k not in EVENT_STR_FIELDS else ev[k][i] for k in EVENT_FIELDS])
    return n
