"""Experiments for the identification: read from a run log (HDF5) or a CSV file.

An ``Experiment`` holds, per control cycle k (period h), the rear carrier's applied input
``u[k]`` (A, held over [t_k, t_k+1)) and the measurements ``psi[k]``, ``y[k]``, ``dw[k]``
taken at t_k (after the plant moved with u[0..k-1]). From a log the input is the commanded
wheel current as the drives resolve it (CiA 402 target torque in per mille of the rated
current, ``drivers.cia402.amps_to_permille``), so a sine is the staircase the rig applied.

CSV (logs recorded elsewhere): a first line ``# experiment: KIND`` and the columns
``t`` (s), ``u`` (A, the differential current applied over the next period), ``psi`` (rad),
``y`` (m), ``dw`` (rad/s); missing values as NaN.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.cia402 import amps_to_permille, permille_to_amps
from rig_runtime.errors import ConfigError

KINDS = ("free-response", "steps", "sine", "open-loop-steps")
_BY_SCENARIO = {"ident-free-response": "free-response", "ident-steps": "steps", "ident-sine": "sine",
                "open-loop-steps": "open-loop-steps", "sine-hysteresis": "sine"}
CSV_COLUMNS = ("t", "u", "psi", "y", "dw")


@dataclass(frozen=True)
class Experiment:
    kind: str
    source: str
    h: float
    t: np.ndarray     # s, from the first row
    u: np.ndarray     # A, applied over [t_k, t_k + h)
    psi: np.ndarray   # rad, rear carrier yaw angle psi_ar
    y: np.ndarray     # m, rear lateral displacement y_r
    dw: np.ndarray    # rad/s, rear wheel-speed difference

    @property
    def name(self) -> str:
        return Path(self.source).name


def _applied(i: np.ndarray, rated: float) -> np.ndarray:
    return np.array([permille_to_amps(amps_to_permille(v, rated), rated) if np.isfinite(v) else 0.0 for v in i])


def _from_log(path: Path) -> Experiment:
    from rig_runtime.app.export import read_log
    try:
        d = read_log(path)
    except OSError as e:
        raise ConfigError(str(path), "", f"a readable run log (HDF5): {e}") from None
    a, c = d["attrs"], d["columns"]
    kind = a.get("experiment") or _BY_SCENARIO.get(a.get("scenario", ""), "")
    if kind not in KINDS:
        raise ConfigError(str(path), "experiment", f"a log of an identification experiment ({', '.join(KINDS)})",
                          a.get("scenario", ""))
    for n in ("t", "psi_ar", "y_r", "dw_r"):
        if n not in c:
            raise ConfigError(str(path), n, "a logged column (rear carrier measurements)")
    rated = {}
    try:
        for dr in json.loads(a.get("config", "{}"))["devices"]["can"]["drives"]:
            rated[dr["wheel"]] = float(dr["rated_current_A"])
    except (KeyError, TypeError, ValueError):
        pass
    if "i_rl" in c and "i_rr" in c and "rl" in rated and "rr" in rated:
        u = _applied(c["i_rl"], rated["rl"]) - _applied(c["i_rr"], rated["rr"])
    elif "rear_u_lim" in c:
        u = np.nan_to_num(c["rear_u_lim"])
    else:
        raise ConfigError(str(path), "rear_u_lim", "a logged rear input (i_rl/i_rr or rear_u_lim)")
    h = float(a.get("h", np.median(np.diff(c["t"]))))
    t = c["t"] - c["t"][0]
    return Experiment(kind, str(path), h, t, u, c["psi_ar"], c["y_r"], c["dw_r"])


def _from_csv(path: Path) -> Experiment:
    with open(path, newline="", encoding="utf-8") as fh:
        first = fh.readline()
        if not first.startswith("#") or "experiment:" not in first:
            raise ConfigError(str(path), "line 1", "'# experiment: KIND' with KIND one of " + ", ".join(KINDS))
        kind = first.split("experiment:", 1)[1].strip()
        if kind not in KINDS:
            raise ConfigError(str(path), "experiment", "one of " + ", ".join(KINDS), kind)
        rows = list(csv.DictReader(fh))
    if not rows or any(k not in rows[0] for k in CSV_COLUMNS):
        raise ConfigError(str(path), "header", "the columns " + ",".join(CSV_COLUMNS))
    try:
        col = {k: np.array([float(r[k]) for r in rows]) for k in CSV_COLUMNS}
    except ValueError as e:
        raise ConfigError(str(path), "values", f"numbers ({e})") from None
    t = col["t"] - col["t"][0]
    return Experiment(kind, str(path), float(np.median(np.diff(t))), t, np.nan_to_num(col["u"]),
                      col["psi"], col["y"], col["dw"])


def load_experiment(path: str | Path) -> Experiment:
    """One experiment from a run log (``.h5``) or a CSV file (see the module docstring)."""
    p = Path(path)
    if not p.exists():
        raise ConfigError(str(p), "", "an existing log or CSV file")
    return _from_csv(p) if p.suffix.lower() == ".csv" else _from_log(p)


def segments(u: np.ndarray) -> list[tuple[int, int]]:
    """[k0, k1) index ranges of constant input."""
    ch = np.flatnonzero(np.diff(u) != 0.0) + 1
    b = np.concatenate(([0], ch, [len(u)]))
    return [(int(a), int(c)) for a, c in zip(b[:-1], b[1:])]
