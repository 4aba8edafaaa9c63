"""What a log holds, by name, without the HDF5 library: the format's name and version, the
event fields, the attributes the recorder reserves, and the checks of a run's columns and
attributes (made in the runtime's process, before anything is written).

Its own module so that the recorder's loop side (:mod:`rig_runtime.recorder`) and the
sidecar's spec do not import h5py: only the sidecar, which writes the file
(:mod:`rig_runtime.logfile`), and the log readers load it. Layout: ``docs/log-format.md``.
"""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

LOG_FORMAT = "rig-runtime-log"
LOG_FORMAT_VERSION = 1

EVENT_FIELDS = ("t", "kind", "device", "check", "value", "limit", "message")
TRUTH_GROUP = "sim_truth"       # a dry run's simulated truth (the plant's y, ψ per carrier), marked as simulation
EVENT_STR_FIELDS = ("kind", "device", "check", "message")
EVENT_NUM_FIELDS = ("t", "value", "limit")

#: root attributes the recorder writes itself (the caller's ``attrs`` must not use them)
RESERVED_ATTRS = frozenset({
    "columns", "log_format", "log_format_version", "recorder_opened", "recorder_closed",
    "rows_written", "rows_dropped", "events_written", "events_dropped", "recorder_error",
})

MIN_FREE_BYTES = 32 * 2**20      # below this much free disk space the writer stops cleanly

#: root attribute written with the columns: the control law's signals ``{name: SI unit}`` (JSON
#: text, in column order); each controlled carrier's columns ``{carrier}_{name}`` hold them
LAW_SIGNALS_ATTR = "law_signals"


#: how people read a signal of an SI unit (the panel, the figures): unit -> (display unit, scale)
DISPLAY_UNITS = {"m": ("mm", 1e3), "rad": ("mrad", 1e3), "m s": ("mm s", 1e3), "rad s": ("mrad s", 1e3),
                 "rad/s": ("mrad/s", 1e3), "A": ("A", 1.0)}


def display_unit(unit: str) -> tuple[str, float]:
    """(display unit, scale) of a value in SI ``unit`` (mm for m, mrad for rad; else as it is)."""
    return DISPLAY_UNITS.get(unit, (unit, 1.0))


def law_signals(attrs: Mapping[str, object]) -> dict[str, str]:
    """The law's signals a log's root attributes declare (``LAW_SIGNALS_ATTR``), name -> unit, in
    column order; ``{}`` for a log without them (written before they were declared) or with a
    value that is not such a mapping."""
    v = attrs.get(LAW_SIGNALS_ATTR) if isinstance(attrs, Mapping) else None
    if isinstance(v, bytes):
        v = v.decode("utf-8", "replace")
    try:
        d = json.loads(v) if isinstance(v, str) else None
    except ValueError:
        return {}
    if not isinstance(d, dict):
        return {}
    return {str(k): str(u) for k, u in d.items() if isinstance(k, str) and k}


def check_columns(columns: Sequence[str]) -> tuple[str, ...]:
    """The row's column names, validated (non-empty, unique, usable as dataset names)."""
    cols = tuple(columns)
    if not cols:
        raise ValueError("recorder: at least one column")
    for c in cols:
        if not isinstance(c, str) or not c or "/" in c or c in (".", "..") or c != c.strip():
            raise ValueError(f"recorder: invalid column name {c!r} (non-empty, no '/', no surrounding blanks)")
    dup = sorted({c for c in cols if cols.count(c) > 1})
    if dup:
        raise ValueError(f"recorder: duplicate column names {dup}")
    return cols


def attr_value(key: str, v: object) -> object:
    """Convert a caller attribute to something HDF5 stores portably (MATLAB-readable)."""
    if isinstance(v, str):
        return v
    if isinstance(v, (bool, np.bool_)):
        return np.int8(bool(v))                     # HDF5 has no bool; h5py's enum confuses MATLAB
    if isinstance(v, (int, np.integer)):
        return np.int64(v)
    if isinstance(v, (float, np.floating)):
        return np.float64(v)
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, (_dt.datetime, _dt.date)):
        return v.isoformat()
    if isinstance(v, (list, tuple)) and v:
        if all(isinstance(x, str) for x in v):
            return list(v)
        if all(isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) for x in v):
            return [float(x) for x in v]
    try:
        return json.dumps(v)                        # mappings, None, mixed lists: as JSON text
    except (TypeError, ValueError) as e:
        raise TypeError(f"recorder attribute {key!r}: cannot store a {type(v).__name__} ({e})") from None


def check_attrs(attrs: Mapping[str, object]) -> dict[str, object]:
    """The caller's root attributes, converted (picklable: they cross to the sidecar)."""
    out: dict[str, object] = {}
    for k, v in attrs.items():
        if not isinstance(k, str) or not k or "/" in k:
            raise ValueError(f"recorder: invalid attribute name {k!r}")
        if k in RESERVED_ATTRS:
            raise ValueError(f"recorder: attribute name {k!r} is reserved for the recorder")
        out[k] = attr_value(k, v)
    return out
