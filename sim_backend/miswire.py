"""Simulated miswiring (``sim: {miswire: …}``): what a rig wired wrongly sends, made where
the simulated rig turns physical values into wire values, so the runtime sees exactly what
a miswired rig would send (docs/commissioning.md, "Simulated miswiring").

- ``laser_sign``: the laser reads mirrored about the middle of its measuring range (a
  target moving away reads as coming closer);
- ``laser_swap``: two lasers' cables exchanged (each one's port carries the other's value);
- ``encoder_sign``: the wheel's drive reports its speed with the wrong sign;
- ``encoder_swap``: two wheels' encoder cables exchanged at their drives (each drive reports
  the other wheel's speed, while its power stage still drives its own wheel);
- ``current_sign``: the wheel's motor turns the drive's current the wrong way (phases swapped);
- ``node_swap``: two drives' node IDs exchanged (the runtime's command for one wheel reaches
  the other wheel's drive, and that drive's speed comes back under the first wheel's name).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Mapping, Sequence

from rig_runtime.config import LASER_ROLES, WHEELS, CanBus
from rig_runtime.errors import ConfigError


@dataclass(frozen=True, kw_only=True)
class Miswire:
    laser_sign: tuple[str, ...] = ()
    laser_swap: tuple[tuple[str, str], ...] = ()
    encoder_sign: tuple[str, ...] = ()
    encoder_swap: tuple[tuple[str, str], ...] = ()
    current_sign: tuple[str, ...] = ()
    node_swap: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        for key, names, known in (("laser_sign", self.laser_sign, LASER_ROLES),
                                  ("laser_swap", [n for p in self.laser_swap for n in p], LASER_ROLES),
                                  ("encoder_sign", self.encoder_sign, WHEELS),
                                  ("encoder_swap", [n for p in self.encoder_swap for n in p], WHEELS),
                                  ("current_sign", self.current_sign, WHEELS),
                                  ("node_swap", [n for p in self.node_swap for n in p], WHEELS)):
            for n in names:
                if n not in known:
                    raise ConfigError(None, key, f"one of {', '.join(known)}", n)
        for key, pairs in (("laser_swap", self.laser_swap), ("encoder_swap", self.encoder_swap),
                           ("node_swap", self.node_swap)):
            flat = [n for p in pairs for n in p]
            if len(set(flat)) != len(flat):
                raise ConfigError(None, key, "pairs of two different names, each name once", list(pairs))

    @property
    def any(self) -> bool:
        return bool(self.laser_sign or self.laser_swap or self.encoders or self.current_sign or self.node_swap)

    @property
    def encoders(self) -> bool:
        """Whether the wheel speeds the drives report are miswired (``wheel_speeds``)."""
        return bool(self.encoder_sign or self.encoder_swap)


NONE = Miswire()


def _partner(pairs: Sequence[tuple[str, str]]) -> dict[str, str]:
    out: dict[str, str] = {}
    for a, b in pairs:
        out[a], out[b] = b, a
    return out


def laser_values(mw: Miswire, values: Mapping[str, float], mid: Mapping[str, float]) -> dict[str, float]:
    """Role -> the distance each role's port carries (m): signs flipped about the laser's
    mid-range ``mid[role]``, then the swapped cables exchanged."""
    v = {r: (2.0 * mid[r] - d if r in mw.laser_sign else d) for r, d in values.items()}
    p = _partner(mw.laser_swap)
    return {r: v.get(p.get(r, r), v[r]) for r in v}


def wheel_speeds(mw: Miswire, omegas: Sequence[float]) -> list[float]:
    """The speeds (rad/s, ``WHEELS`` order) the wheels' drives report: signs flipped at the
    encoders, then the swapped encoder cables exchanged (a swapped node's drive still sits
    on its own wheel: that is ``drive_config``'s part)."""
    om = {w: (-o if w in mw.encoder_sign else o) for w, o in zip(WHEELS, omegas)}
    p = _partner(mw.encoder_swap)
    return [om[p.get(w, w)] for w in WHEELS]


def motor_currents(mw: Miswire, currents: Sequence[float]) -> list[float]:
    """The currents (A, ``WHEELS`` order) the motors see from their drives' output."""
    return [-c if w in mw.current_sign else c for w, c in zip(WHEELS, currents)]


def drive_config(mw: Miswire, can: CanBus) -> CanBus:
    """The drives as wired: each wheel's drive answers at the node ID the partner wheel
    has in the config (the runtime keeps the config's IDs)."""
    p = _partner(mw.node_swap)
    if not p:
        return can
    ids = {d.wheel: d.node_id for d in can.drives}
    return replace(can, drives=tuple(replace(d, node_id=ids[p[d.wheel]]) if d.wheel in p else d
                                     for d in can.drives))
