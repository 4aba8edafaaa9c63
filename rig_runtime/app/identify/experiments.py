"""Experiments for the identification: read from a run log (HDF5) or a CSV file.

An ``Experiment`` holds, per control cycle k (period h), one carrier's applied input
``u[k]`` (A, held over [t_k, t_k+1)) and its measurements ``psi[k]``, ``y[k]``, ``dw[k]``
taken at t_k (after the plant moved with u[0..k-1]), the carrier (``front`` / ``rear``) and
the roller speed ``v`` of the experiment. The paper's set-up identifies the rear carrier at
v > 0 with the front lifted; the mirrored one the front carrier at v < 0 with the rear out
of contact (the carrier in contact is then the trailing one, its lateral dynamics stable).

From a log: the carrier is the log's ``open_loop_carrier`` attribute (the scenario's
``open_loop.carrier``); in a log without it, the one carrier that had an input, and for a
free response (no input) the one whose yaw angle moved (``carrier_of``). The input is the
commanded wheel current as the drives resolve it (CiA 402 target torque in per mille of the
rated current, ``drivers.cia402.amps_to_permille``), so a sine is the staircase the rig
applied. ``v`` is the measured one: the mean wheel speed of the carrier's wheels × r0
(median over the record), which must be steady; the config's ``plant.v`` for a lifted carrier
(no rolling contact, and its free response does not depend on v).

CSV (logs recorded elsewhere): a first line ``# experiment: KIND``, optional lines
``# carrier: front|rear`` (default rear) and ``# v: SPEED`` (m/s; default the config's
plant.v), then the columns ``t`` (s), ``u`` (A, the differential current applied over the
next period), ``psi`` (rad), ``y`` (m), ``dw`` (rad/s); missing values as NaN.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.cia402 import amps_to_permille, permille_to_amps
from rig_runtime.app.runlog import CARRIER_COLUMNS
from rig_runtime.config import CARRIERS
from rig_runtime.errors import ConfigError

KINDS = ("free-response", "steps", "sine", "open-loop-steps")
_BY_SCENARIO = {"ident-free-response": "free-response", "ident-steps": "steps", "ident-sine": "sine",
                "open-loop-steps": "open-loop-steps", "sine-hysteresis": "sine"}
CSV_COLUMNS = ("t", "u", "psi", "y", "dw")
#: per carrier: its wheels (left, right), its measurement columns (runlog's), its lane's input
COLUMNS = {c: {**cols, "u": f"{c}_u_lim"} for c, cols in CARRIER_COLUMNS.items()}
SPEED_STEADY = 0.02     # the measured speed may vary by 2 % of its median over an experiment
V_MIN = 0.05            # m/s: below, the wheels do not roll enough for (2)/(4) (the lateral input c̄_y v -> 0)


@dataclass(frozen=True)
class Experiment:
    kind: str
    source: str
    h: float
    t: np.ndarray     # s, from the first row
    u: np.ndarray     # A, applied over [t_k, t_k + h)
    psi: np.ndarray   # rad, the carrier's yaw angle (psi_ar / psi_af)
    y: np.ndarray     # m, its lateral displacement (y_r / y_f)
    dw: np.ndarray    # rad/s, its wheel-speed difference left − right
    carrier: str = "rear"
    v: float | None = None   # m/s, roller speed (sign = direction); None: the config's plant.v
    other_rolling: bool = False   # the other carrier was on the rollers too (the log's config)

    @property
    def name(self) -> str:
        return Path(self.source).name


def _applied(i: np.ndarray, rated: float) -> np.ndarray:
    return np.array([permille_to_amps(amps_to_permille(v, rated), rated) if np.isfinite(v) else 0.0 for v in i])


def carrier_of(attrs: dict, cols: dict, path: str = "") -> str:
    """The carrier a log's experiment is about: the ``open_loop_carrier`` attribute; else the
    one carrier that had an input; else (a free response) the one whose yaw angle moved most."""
    c = attrs.get("open_loop_carrier", "")
    if c in CARRIERS:
        return c
    driven = [x for x in CARRIERS if np.nanmax(np.abs(_input(cols, x, {}, path, need=False)), initial=0.0) > 0]
    if len(driven) == 1:
        return driven[0]
    if driven:
        raise ConfigError(path, "carrier", "a log with an input on one carrier only (or give --carrier)")
    spread = {x: float(np.nanpercentile(cols[COLUMNS[x]["psi"]], 99) - np.nanpercentile(cols[COLUMNS[x]["psi"]], 1))
              for x in CARRIERS if COLUMNS[x]["psi"] in cols and np.isfinite(cols[COLUMNS[x]["psi"]]).any()}
    if not spread:
        raise ConfigError(path, "psi_ar", "a logged yaw angle (psi_af or psi_ar)")
    return max(spread, key=spread.get)


def _input(cols: dict, carrier: str, rated: dict, path: str, need: bool = True) -> np.ndarray:
    a, b = COLUMNS[carrier]["wheels"]
    wires = f"i_{a}" in cols and f"i_{b}" in cols
    if wires and a in rated and b in rated:
        return _applied(cols[f"i_{a}"], rated[a]) - _applied(cols[f"i_{b}"], rated[b])
    if COLUMNS[carrier]["u"] in cols:
        return np.nan_to_num(cols[COLUMNS[carrier]["u"]])
    if wires:
        return np.nan_to_num(cols[f"i_{a}"] - cols[f"i_{b}"])
    if need:
        raise ConfigError(path, COLUMNS[carrier]["u"], f"a logged {carrier} input (i_{a}/i_{b} or {COLUMNS[carrier]['u']})")
    return np.zeros(len(cols["t"]))


def measured_speed(cols: dict, carrier: str, r0: float, path: str = "") -> float | None:
    """The roller speed seen by ``carrier``'s wheels: median of r0 (ω_l + ω_r)/2 (None when the
    log has no wheel speeds). It must be steady (``SPEED_STEADY``) and not near standstill."""
    a, b = COLUMNS[carrier]["wheels"]
    if f"omega_{a}" not in cols or f"omega_{b}" not in cols:
        return None
    v = r0 * 0.5 * (cols[f"omega_{a}"] + cols[f"omega_{b}"])
    v = v[np.isfinite(v)]
    if not len(v):
        return None
    vm = float(np.median(v))
    if abs(vm) < V_MIN:
        raise ConfigError(path, "speed", f"an experiment with the rollers running (|v| >= {V_MIN} m/s)",
                          f"{vm:.3g} m/s")
    lo, hi = np.percentile(v, [1, 99])
    if max(hi - vm, vm - lo) > SPEED_STEADY * abs(vm):
        raise ConfigError(path, "speed", f"a steady roller speed (within {SPEED_STEADY:.0%})",
                          f"{lo:.3g}..{hi:.3g} m/s")
    return vm


def _from_log(path: Path, carrier: str | None = None) -> Experiment:
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
    logged = a.get("open_loop_carrier", "")
    if carrier is not None and logged in CARRIERS and logged != carrier:
        raise ConfigError(str(path), "--carrier", f"the log's own carrier ({logged})", carrier)
    carrier = carrier or carrier_of(a, c, str(path))
    col = COLUMNS[carrier]
    for n in ("t", col["psi"], col["y"], col["dw"]):
        if n not in c:
            raise ConfigError(str(path), n, f"a logged column ({carrier} carrier measurements)")
    try:
        conf = json.loads(a.get("config", "{}"))
    except ValueError:
        conf = {}
    rated = {}
    try:
        for dr in conf["devices"]["can"]["drives"]:
            rated[dr["wheel"]] = float(dr["rated_current_A"])
    except (KeyError, TypeError, ValueError):
        pass
    u = _input(c, carrier, rated, str(path))
    v = None
    if a.get("lifted_carrier", "") != carrier and kind != "free-response":
        r0 = _r0(conf, carrier)
        v = measured_speed(c, carrier, r0, str(path)) if r0 else None
    other = "front" if carrier == "rear" else "rear"
    pl = conf.get("plant") or {}
    rolling = bool(pl.get(f"{other}_contact", other == "rear")) and a.get("lifted_carrier", "") != other
    h = float(a.get("h", np.median(np.diff(c["t"]))))
    t = c["t"] - c["t"][0]
    return Experiment(kind, str(path), h, t, u, c[col["psi"]], c[col["y"]], c[col["dw"]], carrier=carrier, v=v,
                      other_rolling=rolling)


def _r0(conf: dict, carrier: str) -> float | None:
    """The carrier's wheel radius in the log's config (its own override, else the common one)."""
    pl = conf.get("plant") or {}
    own = pl.get(carrier) or {}
    r0 = own.get("r0") if own.get("r0") is not None else pl.get("r0")
    return float(r0) if isinstance(r0, (int, float)) and r0 > 0 else None


def _from_csv(path: Path, carrier: str | None = None) -> Experiment:
    with open(path, newline="", encoding="utf-8") as fh:
        first = fh.readline()
        if not first.startswith("#") or "experiment:" not in first:
            raise ConfigError(str(path), "line 1", "'# experiment: KIND' with KIND one of " + ", ".join(KINDS))
        kind = first.split("experiment:", 1)[1].strip()
        if kind not in KINDS:
            raise ConfigError(str(path), "experiment", "one of " + ", ".join(KINDS), kind)
        meta = {}
        pos = fh.tell()
        line = fh.readline()
        while line.startswith("#"):
            k, _, val = line[1:].partition(":")
            meta[k.strip()] = val.strip()
            pos = fh.tell()
            line = fh.readline()
        fh.seek(pos)
        rows = list(csv.DictReader(fh))
    own = meta.get("carrier")
    if own is not None and own not in CARRIERS:
        raise ConfigError(str(path), "carrier", "front or rear", own)
    if carrier is not None and own is not None and own != carrier:
        raise ConfigError(str(path), "--carrier", f"the file's own carrier ({own})", carrier)
    try:
        v = float(meta["v"]) if "v" in meta else None
    except ValueError:
        raise ConfigError(str(path), "v", "a speed in m/s", meta["v"]) from None
    if not rows or any(k not in rows[0] for k in CSV_COLUMNS):
        raise ConfigError(str(path), "header", "the columns " + ",".join(CSV_COLUMNS))
    try:
        col = {k: np.array([float(r[k]) for r in rows]) for k in CSV_COLUMNS}
    except ValueError as e:
        raise ConfigError(str(path), "values", f"numbers ({e})") from None
    t = col["t"] - col["t"][0]
    return Experiment(kind, str(path), float(np.median(np.diff(t))), t, np.nan_to_num(col["u"]),
                      col["psi"], col["y"], col["dw"], carrier=own or carrier or "rear", v=v)


def load_experiment(path: str | Path, carrier: str | None = None) -> Experiment:
    """One experiment from a run log (``.h5``) or a CSV file (see the module docstring);
    ``carrier``: take it as that carrier's (refused if the log names another one)."""
    p = Path(path)
    if not p.exists():
        raise ConfigError(str(p), "", "an existing log or CSV file")
    return _from_csv(p, carrier) if p.suffix.lower() == ".csv" else _from_log(p, carrier)


def segments(u: np.ndarray) -> list[tuple[int, int]]:
    """[k0, k1) index ranges of constant input."""
    ch = np.flatnonzero(np.diff(u) != 0.0) + 1
    b = np.concatenate(([0], ch, [len(u)]))
    return [(int(a), int(c)) for a, c in zip(b[:-1], b[1:])]
