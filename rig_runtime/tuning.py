"""The one check of a live gain change (``rig ctl set NAME VALUE``).

A change is accepted only if all of these hold, in this order (the first that fails is
the one-line reason given to the operator):

1. the name is a gain of the control law in use (``controller.law``): the PI-PD gains
   ``K_P_y, K_I_y, K_P_psi, K_D_psi, T_f_psi`` or the P law's ``K_P``. A limit (anything in
   ``limits``: u_max, y_max, psi_max, ...) is refused as such — limits come from the frozen
   config and never change while running; any other name is refused as unknown;
2. the gain has bounds in the config (``controller.tuning``; a gain without bounds is not
   tunable) and the value is finite and within them;
3. the sampled closed loop as implemented (:func:`rig_runtime.analysis.sampled_instability`,
   the stability gate that guards every run) is stable with the new value and the other
   gains in force (which may differ from the config after earlier changes).

The result is an immutable :class:`GainChange`; the loop applies it to every controller
(``control.PIPDController.set_gain``) at a cycle boundary.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Mapping

from . import analysis, schema
from .config import P_GAINS, PIPD_GAINS, TUNABLE_GAINS, Limits, RigConfig
from .errors import ConfigError, RigError

LIMIT_NAMES = tuple(f.name for f in dataclasses.fields(Limits))


class TuningError(RigError):
    """A gain change refused; the message says why."""


@dataclasses.dataclass(frozen=True)
class GainChange:
    name: str
    old: float
    new: float


def law_gains(law: str) -> tuple[str, ...]:
    """The tunable gains of control law ``law``."""
    return P_GAINS if law == "p" else PIPD_GAINS


def gains_of(cfg: RigConfig) -> dict[str, float]:
    """The configured gains of the law in use."""
    c = cfg.controller
    if c.law == "p":
        return {"K_P": c.K_P}
    return {n: getattr(c.pipd, n) for n in PIPD_GAINS}


def with_gains(cfg: RigConfig, gains: Mapping[str, float]) -> RigConfig:
    """``cfg`` with the law's gains replaced by ``gains`` (a subset is fine)."""
    c = cfg.controller
    kp = {k: float(v) for k, v in gains.items() if k in P_GAINS}
    kpipd = {k: float(v) for k, v in gains.items() if k in PIPD_GAINS}
    c = dataclasses.replace(c, pipd=dataclasses.replace(c.pipd, **kpipd), **kp)
    return dataclasses.replace(cfg, controller=c)


def check(cfg: RigConfig, name: str, value: float, gains: Mapping[str, float] | None = None) -> GainChange:
    """Check setting gain ``name`` to ``value`` with ``gains`` in force (default: the
    configured ones); returns the change or raises :class:`TuningError` saying why not."""
    v = admissible(cfg, name, value)
    in_force = dict(gains_of(cfg))
    if gains is not None:
        in_force.update({k: float(x) for k, x in gains.items() if k in in_force})
    old = in_force[name]
    in_force[name] = v
    bad = analysis.sampled_instability(with_gains(cfg, in_force))
    if bad is not None:
        D, ev = bad
        where = "cannot be computed" if ev != ev else f"has an eigenvalue at {analysis.ev_text(ev)}"
        raise TuningError(f"{name} = {v:g} would make the sampled closed loop unstable (plant (10) with "
                          f"D = {D:g} {where}; gains then: " + ", ".join(f"{k} {x:g}" for k, x in in_force.items()) + ")")
    return GainChange(name, old, v)


def admissible(cfg: RigConfig, name: str, value: float) -> float:
    """Checks 1 and 2 (a tunable gain of the law in use, finite, within its bounds): the
    value as a float, or :class:`TuningError`. Cheap (no numpy): the loop repeats it on
    every ``set`` it takes from the mailbox, whoever wrote it there."""
    law = cfg.controller.law
    if name in LIMIT_NAMES:
        raise TuningError(f"{name} is a limit: limits cannot be changed while running "
                          "(they come from the config, which is frozen for the run)")
    if name not in TUNABLE_GAINS:
        raise TuningError(f"unknown name {name!r}: tunable gains of law {law} are "
                          + ", ".join(law_gains(law)))
    if name not in law_gains(law):
        raise TuningError(f"{name} is not a gain of the control law in use ({law}: "
                          + ", ".join(law_gains(law)) + ")")
    bounds = cfg.controller.tuning.get(name)
    if bounds is None:
        raise TuningError(f"{name} has no bounds in the config (controller.tuning): not tunable")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TuningError(f"{name}: value {value!r} is not a number") from None
    if not math.isfinite(v):
        raise TuningError(f"{name}: value {v} is not a finite number")
    lo, hi = bounds
    if not lo <= v <= hi:
        raise TuningError(f"{name} = {v:g} is outside its bounds [{lo:g}, {hi:g}] (controller.tuning)")
    return v


def config_from_json(text: str) -> RigConfig:
    """Rebuild the run's config from its JSON form (``schema.to_dict``, the log's
    ``config`` attribute): the same validation as loading it."""
    try:
        data = json.loads(text)
    except (TypeError, ValueError) as e:
        raise ConfigError("the run's config", "", f"JSON text ({e})") from None
    if not isinstance(data, dict):
        raise ConfigError("the run's config", "", "a mapping of sections", type(data).__name__)
    return schema.build(RigConfig, data, "", "the run's config")
