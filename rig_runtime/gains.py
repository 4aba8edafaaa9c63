"""The gains of the control laws, and the cheap part of the check of a live gain change
(``rig ctl set NAME VALUE``): checks 1 and 2 of :mod:`rig_runtime.tuning` — the name is a
tunable gain of the law in use, the value is finite and within its bounds.

Its own module so that the loop, which repeats this part on every ``set`` it takes from
the mailbox, does not import the stability gate (:func:`rig_runtime.tuning.check`, numpy
and scipy): no numpy, no scipy here.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Mapping

from .config import DECOUPLED_GAINS, P_GAINS, PIPD_GAINS, TUNABLE_GAINS, Limits, RigConfig
from .errors import RigError

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
    return P_GAINS if law == "p" else DECOUPLED_GAINS if law == "decoupled" else PIPD_GAINS


def gains_of(cfg: RigConfig) -> dict[str, float]:
    """The configured gains of the law in use."""
    c = cfg.controller
    if c.law == "p":
        return {"K_P": c.K_P}
    if c.law == "decoupled":
        return {n: getattr(c.decoupled, n) for n in DECOUPLED_GAINS}
    return {n: getattr(c.pipd, n) for n in PIPD_GAINS}


def with_gains(cfg: RigConfig, gains: Mapping[str, float]) -> RigConfig:
    """``cfg`` with the law's gains replaced by ``gains`` (a subset is fine). A live change
    acts on every carrier's controller: carriers with gains of their own (``controller.front``
    / ``rear``) get the new value too, their other gains stay."""
    c = cfg.controller
    kp = {k: float(v) for k, v in gains.items() if k in P_GAINS}
    kpipd = {k: float(v) for k, v in gains.items() if k in PIPD_GAINS}
    own = {k: dataclasses.replace(getattr(c, k), **kpipd) for k in ("front", "rear") if getattr(c, k) is not None}
    if c.decoupled is not None:
        own["decoupled"] = dataclasses.replace(c.decoupled, **{k: float(v) for k, v in gains.items()
                                                               if k in DECOUPLED_GAINS})
    c = dataclasses.replace(c, pipd=dataclasses.replace(c.pipd, **kpipd), **own, **kp)
    return dataclasses.replace(cfg, controller=c)


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
