"""Read recorder logs (``rig_runtime.recorder``) and export them as CSV.

``read_log(path)`` returns everything in plain numpy/Python objects; ``to_csv`` writes the
cycles table (header = column names with their units, ``y_r [m]``, in recording order; the
``state`` column as state names) and, by default, the events beside it as
``<out>.events.csv`` (``run.csv`` -> ``run.csv.events.csv``). Layout: ``docs/log-format.md``.
"""

from __future__ import annotations

import contextlib
import csv
import math
import re
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from ..errors import ConfigError, LogError
from ..logformat import EVENT_FIELDS, EVENT_STR_FIELDS, LAW_SIGNALS_ATTR, LOG_FORMAT, law_signals
from ..safety import State

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


@contextlib.contextmanager
def _open(path: str | Path) -> Iterator[h5py.File]:
    """The log, open for reading, once it is known to be a rig log; any failure to read it
    (not HDF5, empty, truncated, another program's HDF5, a dataset cut short) is a
    :class:`LogError` naming the file."""
    p = Path(path)
    if p.is_dir():
        raise LogError(p, "a directory")
    try:
        # locking=False: a log still being written (flushed state) can be looked at, too
        f = h5py.File(p, "r", locking=False)
    except FileNotFoundError:
        raise LogError(p, "no such file") from None
    except OSError as e:
        size = p.stat().st_size if p.exists() else 0
        raise LogError(p, "empty file" if size == 0 else f"not an HDF5 file, or truncated: {_first_line(e)}") from None
    try:
        fmt = _decode(f.attrs.get("log_format", b""))
        if fmt != LOG_FORMAT or "cycles" not in f:
            raise LogError(p, f"an HDF5 file, but no {LOG_FORMAT} (attribute log_format and group cycles missing)")
        try:
            yield f
        except (OSError, KeyError, ValueError, RuntimeError) as e:
            raise LogError(p, f"truncated or damaged: {_first_line(e)}") from None
    finally:
        f.close()


class _Out:
    """An output text file whose open, write and close failures are a ConfigError naming
    it (not mistaken for a damaged log while the log is open)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def _error(self, e: OSError) -> ConfigError:
        return ConfigError(str(self.path), "", f"a writable output file ({e.strerror or _first_line(e)})")

    def __enter__(self) -> "_Out":
        try:
            self.fh = open(self.path, "w", newline="", encoding="utf-8")
        except OSError as e:
            raise self._error(e) from None
        return self

    def write(self, text: str) -> None:
        try:
            self.fh.write(text)
        except OSError as e:
            raise self._error(e) from None

    def __exit__(self, *exc: object) -> None:
        try:
            self.fh.close()
        except OSError as e:
            if exc[0] is None:
                raise self._error(e) from None


def _first_line(e: BaseException) -> str:
    text = str(e).splitlines()[0] if str(e) else type(e).__name__
    return text[:120]


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


def _read_column(gid: h5py.h5g.GroupID, name: str) -> np.ndarray:
    """One column as float64 (HDF5 converts what the file holds), read through the
    low-level API: a third of the CPU of ``group[name][()]`` with ~100 columns a log."""
    ds = h5py.h5d.open(gid, name.encode())
    try:
        out = np.empty(ds.shape, dtype=np.float64)
        if out.size:
            ds.read(h5py.h5s.ALL, h5py.h5s.ALL, out)
        return out
    finally:
        ds.close()


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
        gid = f["cycles"].id
        cols = {n: _read_column(gid, n) for n in names}
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
    """``OUT`` -> ``OUT.events.csv`` (``run.csv`` -> ``run.csv.events.csv``), as README and
    ``--help`` say. (It used to replace a ``.csv`` suffix, so ``--csv default.csv`` wrote
    ``default.events.csv``, not the documented name.)"""
    p = Path(out_path)
    return p.with_name(p.name + ".events.csv")


# (pattern, unit) in order; the first full match names a column's unit (docs/log-format.md)
_UNITS: tuple[tuple[re.Pattern, str], ...] = tuple((re.compile(p), u) for p, u in (
    (r"t|t_run|lateness|work|.+_age", "s"),
    (r"state", ""),
    (r"(front|rear)_x_I", "m s"),
    (r"(front|rear)_de_psi|omega_\w+|dw_[fr]", "rad/s"),
    (r"psi(_\w+)?|(front|rear)_(psi_ref|e_psi)", "rad"),
    (r"y|y_ref|y_[mfr]|(front|rear)_e_y|[bs]_[fr]|s_[fr][lr]", "m"),
    (r"(front|rear)_u_(unsat|cmd|lim)|u_(cmd|lim)|i_[fr][lr]", "A"),
    (r"ft_\w+_f[xyz]", "N"),
    (r"ft_\w+_m[xyz]", "N m"),
))


def column_unit(name: str) -> str:
    """The SI unit of a log column by the naming rules of docs/log-format.md (``"m"`` for
    ``y_r``); ``""`` for ``state`` and for a name the rules do not cover (a column that is not SI
    carries its unit in its name)."""
    for pat, unit in _UNITS:
        if pat.fullmatch(name):
            return unit
    return ""


def column_header(name: str, unit: str | None = None) -> str:
    """``y_r`` -> ``y_r [m]``; a column without a unit keeps its bare name. ``unit``: the unit
    the log declares for it (a control law's signal), else the naming rules'."""
    u = column_unit(name) if unit is None else unit
    return f"{name} [{u}]" if u else name


def state_name(code: float) -> str:
    """The supervisor state of a ``state`` column value (``2.0`` -> ``RUNNING``); ``NaN`` for a
    missing value, the number itself for a code this version does not know."""
    if code != code:
        return "NaN"
    try:
        return State(int(code)).name if float(code).is_integer() else _fmt(code)
    except ValueError:
        return _fmt(code)


def to_csv(log_path: str | Path, out_path: str | Path, *, events: bool = True) -> int:
    """Write the cycles table of ``log_path`` as CSV; return the row count.

    Header: the column names with their units (``y_r [m]``, :func:`column_header`); the
    ``state`` column holds state names (``RUNNING``). With ``events`` (default) the events go to
    ``events_path_for(out_path)`` as well. Values are written with full (round-trip)
    precision, missing values as ``NaN``.
    """
    out = Path(out_path)
    with _open(log_path) as f:
        names = _column_names(f)
        dsets = [f["cycles"][n] for n in names]
        rows = min((d.shape[0] for d in dsets), default=0)
        fmts = [state_name if n == "state" else _fmt for n in names]
        law = law_signals({LAW_SIGNALS_ATTR: f.attrs[LAW_SIGNALS_ATTR]} if LAW_SIGNALS_ATTR in f.attrs else {})
        units = {f"{c}_{n}": u for c in ("front", "rear") for n, u in law.items()}   # the law's own units
        with _Out(out) as fh:
            fh.write(",".join(column_header(n, units.get(n)) for n in names) + "\n")
            for a in range(0, rows, _BLOCK):
                b = min(a + _BLOCK, rows)
                block = np.column_stack([d[a:b] for d in dsets]).tolist()
                fh.write("".join(",".join([fm(v) for fm, v in zip(fmts, r)]) + "\n" for r in block))
    if events:
        events_to_csv(log_path, events_path_for(out))
    return rows


def events_to_csv(log_path: str | Path, out_path: str | Path) -> int:
    """Write the events of ``log_path`` as CSV (``t,kind,device,check,value,limit,message``); return the count."""
    with _open(log_path) as f:
        ev = _read_events(f)
    n = len(ev["t"])
    with _Out(out_path) as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(EVENT_FIELDS)
        for i in range(n):
            w.writerow([_fmt(float(ev[k][i])) if k not in EVENT_STR_FIELDS else ev[k][i] for k in EVENT_FIELDS])
    return n
