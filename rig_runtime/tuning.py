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
   gains in force (which may differ from the config after earlier changes) — on a vehicle
   config at every speed of the schedule's range, both directions, every carrier in contact.

Checks 1 and 2 are :func:`rig_runtime.gains.admissible` (no numpy: the loop repeats them);
this module adds check 3 and so imports the analysis (numpy, scipy) — only where a change
is judged (the ``rig ctl`` server in the recording sidecar), never in the loop's module.

The result is an immutable :class:`~rig_runtime.gains.GainChange`; the loop applies it to
every controller (``control.PIPDController.set_gain``) at a cycle boundary.
"""

from __future__ import annotations

import json
from typing import Mapping

from . import analysis, schema
from .config import RigConfig
from .errors import ConfigError
from .gains import GainChange, TuningError, admissible, gains_of, with_gains


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
        ev = bad.s
        what = "cannot be computed" if ev != ev else f"has an eigenvalue at {analysis.ev_text(ev)}"
        raise TuningError(f"{name} = {v:g} would make the sampled closed loop unstable ({bad.where()} {what}; "
                          "gains then: " + ", ".join(f"{k} {x:g}" for k, x in in_force.items()) + ")")
    return GainChange(name, old, v)


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
