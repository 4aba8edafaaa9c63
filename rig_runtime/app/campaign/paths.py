"""Parameter paths: a dotted name into a config's sections (``plant.delta0``,
``plant.front.delta0``, ``controller.pipd.K_P_y``, ``controller.rear.K_I_y``), its base value
and how a value is written — the one place campaigns and ``rig synthesize`` read and vary a
config, so that a study varies the plant (and the gains) it says it varies.

Carriers (docs/campaigns.md, "Parameters"):
- ``plant.front.X`` / ``plant.rear.X``: that carrier's own X (its override; the common value
  is its base when it has none).
- ``plant.X`` (a per-carrier quantity: a field of ``config.CarrierPlant``): *every* carrier.
  The common value becomes the sample; a carrier with its own X keeps its ratio to the common
  value (``X_c = X_c0 · x / X0``; the same offset ``X_c0 + x − X0`` when X0 = 0), so
  ``plant.delta0: {pct: 20}`` moves both carriers by the same 20 %, each from its own value.
- ``controller.front.G`` / ``controller.rear.G``: that carrier's gains (made from
  ``controller.pipd`` when the config has none of its own); ``controller.pipd.G``: every
  carrier's G, as ``plant.X`` above.
Other names are plain key paths (``plant.v``, ``limits.u_max``, ``sim.laser_noise_m``)."""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Optional

from rig_runtime.config import CARRIERS, CarrierPlant, PIPDGains

PLANT_CARRIER_KEYS = tuple(f.name for f in dataclasses.fields(CarrierPlant) if f.name != "bouc_wen")
GAIN_KEYS = tuple(f.name for f in dataclasses.fields(PIPDGains))


def _lookup(tree: Mapping, parts: list[str]) -> Any:
    node: Any = tree
    for p in parts:
        if not isinstance(node, Mapping) or p not in node:
            return None
        node = node[p]
    return node


def _number(v: Any) -> Optional[float]:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v)


def carrier_of(name: str) -> Optional[str]:
    """The carrier a name is about (``plant.front.delta0`` → front), None for all/none."""
    parts = name.split(".")
    if len(parts) == 3 and parts[0] in ("plant", "controller") and parts[1] in CARRIERS:
        return parts[1]
    return None


def _common(section: str) -> tuple[str, ...]:
    """Where the common value of a carrier quantity lives (plant: the section itself; the
    controller: its ``pipd`` gains)."""
    return ("plant",) if section == "plant" else ("controller", "pipd")


def _carrier_quantity(name: str) -> Optional[tuple[str, Optional[str], str]]:
    """(section, carrier or None for every carrier, key) for a name about carrier quantities."""
    parts = name.split(".")
    if parts[0] == "plant":
        if len(parts) == 3 and parts[1] in CARRIERS and parts[2] in PLANT_CARRIER_KEYS:
            return "plant", parts[1], parts[2]
        if len(parts) == 2 and parts[1] in PLANT_CARRIER_KEYS:
            return "plant", None, parts[1]
    if parts[0] == "controller" and len(parts) == 3 and parts[2] in GAIN_KEYS:
        if parts[1] in CARRIERS:
            return "controller", parts[1], parts[2]
        if parts[1] == "pipd":
            return "controller", None, parts[2]
    return None


def nominal(sections: Mapping, name: str) -> Optional[float]:
    """The base value of ``name`` in the config's sections (None: not a number there). A
    carrier's name gives that carrier's value (its own, else the common one)."""
    q = _carrier_quantity(name)
    if q is not None and q[1] is not None:
        section, carrier, key = q
        own = _lookup(sections, [section, carrier, key])
        return _number(own if own is not None else _lookup(sections, [*_common(section), key]))
    return _number(_lookup(sections, name.split(".")))


def _set(tree: dict, parts: list[str], value: float) -> None:
    node = tree
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value


def apply(sections: dict, name: str, value: float, base: Mapping) -> None:
    """Write ``name = value`` into ``sections`` (changed in place); ``base``: the base
    config's sections (the values a carrier's ratio is kept to)."""
    q = _carrier_quantity(name)
    if q is None:
        _set(sections, name.split("."), float(value))
        return
    section, carrier, key = q
    if carrier is not None:
        if section == "controller" and not isinstance(_lookup(sections, ["controller", carrier]), Mapping):
            # from the gains as varied so far (order(): the every-carrier names come first)
            sections["controller"][carrier] = dict(_lookup(sections, ["controller", "pipd"]))
        _set(sections, [section, carrier, key], float(value))
        return
    x0 = _number(_lookup(base, [*_common(section), key]))
    _set(sections, [*_common(section), key], float(value))
    for c in CARRIERS:
        own0 = _number(_lookup(base, [section, c, key]))
        if own0 is None:
            continue                        # it follows the common value
        own = own0 * float(value) / x0 if x0 else own0 + float(value) - (x0 or 0.0)
        _set(sections, [section, c, key], own)


def order(names) -> list[str]:
    """The order to apply names in: the every-carrier ones first, then a carrier's own (a
    spec that varies both ``plant.delta0`` and ``plant.front.delta0`` sets the front's last)."""
    return sorted(names, key=lambda n: carrier_of(n) is not None)
