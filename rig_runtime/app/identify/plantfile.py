"""The ``plant:`` fragment written by ``rig identify --write``: the configured plant with every
identified value replaced and marked IDENTIFIED (date, logs, residual of its fit).

Per carrier (``plant_sections``): the rear carrier's identified values are the common values
(the paper's set-up identifies and controls the rear; a config without per-carrier values is
written as before), and a rear override of an identified key is dropped (it would hide it);
the front carrier's identified values are its overrides in ``plant.front``. A key the front
did not identify keeps its configured override, else the common value (the rear's, when the
rear identified it: the carriers are taken alike where the front has no value of its own).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
from pathlib import Path

from rig_runtime.config import CARRIERS, Plant as PlantParams
from rig_runtime.errors import ConfigError

_ORDER = ("v", "b", "r0", "delta0", "l0", "y_off", "c11", "J_x", "k_tau", "omega0", "K", "D_min", "D_max",
          "c_udot_max", "u_filter_hz", "psi_off")
_BW = ("a", "A", "beta", "gamma", "n")
_BW_DEFAULT = {"A": 1.0, "n": 1}


def _flat(P) -> dict:
    """Dotted name -> value of a Plant (its common values) or a CarrierPlant (its overrides)."""
    out = {}
    for k in _ORDER:
        v = getattr(P, k, None)
        if v is not None:
            out[k] = v
    bw = getattr(P, "bouc_wen", None)
    if bw is not None:
        out.update({f"bouc_wen.{k}": getattr(bw, k) for k in _BW})
    return out


def plant_sections(plant: PlantParams, identified: dict[str, dict]) -> tuple[dict, dict, dict]:
    """(common, {carrier: overrides}, {section name: {dotted name: (value, rms, step)}}) of the
    fragment: ``plant`` the configured plant, ``identified`` carrier -> {dotted name: (value,
    residual rms, step)}. Section names: "" (common), "front", "rear"."""
    common = _flat(plant)
    own = {c: _flat(getattr(plant, c)) if getattr(plant, c) is not None else {} for c in CARRIERS}
    marks: dict[str, dict] = {"": {}, "front": {}, "rear": {}}
    for c in CARRIERS:
        for name, (value, rms, step) in identified.get(c, {}).items():
            if c == "rear":
                common[name] = value
                own["rear"].pop(name, None)
                marks[""][name] = (value, rms, step)
            else:
                own["front"][name] = value
                marks["front"][name] = (value, rms, step)
    for c in CARRIERS:                         # an override's Bouc-Wen set is a whole one
        if any(k.startswith("bouc_wen.") for k in own[c]):
            for k in _BW:
                own[c].setdefault(f"bouc_wen.{k}", common.get(f"bouc_wen.{k}", _BW_DEFAULT.get(k)))
    return common, own, marks


def render(P: PlantParams, identified: dict, logs: list[str], when: str | None = None,
           carriers: dict | None = None) -> str:
    """``P`` the plant whose common values are written, ``identified``: {name: (value,
    residual_rms, step)} of them (dotted names for bouc_wen); ``carriers``: {carrier:
    (overrides {dotted name: value}, identified {name: (value, rms, step)})} written as
    ``plant.front`` / ``plant.rear`` (none: the configured ones, if any)."""
    when = when or _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"# Plant identified by `rig identify` on {when}",
             "# from: " + ", ".join(logs),
             "# Values without IDENTIFIED are the configured ones (not identifiable from these experiments).",
             "plant:"]
    if carriers is None:
        carriers = {c: (_flat(getattr(P, c)), {}) for c in CARRIERS if getattr(P, c) is not None}

    def line(key: str, value, indent: str, name: str, marks: dict, carrier: str = "") -> str:
        s = f"{indent}{key}: {value!r}"
        if name in marks:
            v, rms, step = marks[name]
            s = f"{indent}{key}: {v:.6g}"
            s += f"   # IDENTIFIED {when} ({carrier + ' carrier: ' if carrier else ''}{step}, residual RMS {rms:.3g})"
        return s
    for k in _ORDER:
        lines.append(line(k, getattr(P, k), "  ", k, identified))
    bw = P.bouc_wen
    if bw is not None or any(k.startswith("bouc_wen.") for k in identified):
        lines.append("  bouc_wen:")
        for k in _BW:
            lines.append(line(k, getattr(bw, k) if bw is not None else _BW_DEFAULT.get(k, 1.0), "    ",
                              f"bouc_wen.{k}", identified))
    lines.append(f"  front_contact: {str(P.front_contact).lower()}")
    if not getattr(P, "rear_contact", True):
        lines.append("  rear_contact: false")
    for c in CARRIERS:
        if c not in carriers or not carriers[c][0]:
            continue
        values, marks = carriers[c]
        lines.append(f"  {c}:")
        for k in _ORDER:
            if k in values:
                lines.append(line(k, values[k], "    ", k, marks, c))
        if any(k.startswith("bouc_wen.") for k in values):
            lines.append("    bouc_wen:")
            for k in _BW:
                lines.append(line(k, values[f"bouc_wen.{k}"], "      ", f"bouc_wen.{k}", marks, c))
    return "\n".join(lines) + "\n"


def render_carriers(plant: PlantParams, identified: dict[str, dict], logs: list[str], when: str | None = None) -> str:
    """The fragment for several carriers' results (``plant_sections``)."""
    common, own, marks = plant_sections(plant, identified)
    bw = None
    if "bouc_wen.beta" in common:
        from rig_runtime.config import BoucWen
        bw = BoucWen(**{k: common[f"bouc_wen.{k}"] for k in _BW})
    P = dataclasses.replace(plant, front=None, rear=None, bouc_wen=bw,
                            **{k: common[k] for k in _ORDER if k in common})
    return render(P, marks[""], logs, when, {c: (own[c], marks[c]) for c in CARRIERS})


def write(path: str | Path, text: str) -> None:
    p = Path(path)
    if p.exists():
        raise ConfigError(str(p), "", "a new file (refusing to overwrite an existing plant file)")
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text)
