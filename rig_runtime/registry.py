"""Drivers by name, as configs name them (a table of strings, like python-can's
``BACKENDS``). A driver module — and the vendor library it needs — is imported only when
a config uses it, so the core never imports ``drivers`` statically."""

from __future__ import annotations

import importlib

from .errors import ConfigError

DRIVERS = {
    "laser": {"optoncdt1420": "drivers.laser:LaserDriver"},
    "can": {"cia402": "drivers.canopen402:DriveBus"},
    "ft": {"robotiq_ft300": "drivers.ft300:FTSensorSet"},
}


def driver_class(family: str, name: str, key_path: str = ""):
    """The class registered as ``name`` for a device family ("laser", "can", "ft")."""
    try:
        target = DRIVERS[family][name]
    except KeyError:
        known = ", ".join(sorted(DRIVERS.get(family, {})))
        raise ConfigError(None, key_path or f"devices.{family}.driver", f"one of {known}", name) from None
    module, cls = target.split(":")
    return getattr(importlib.import_module(module), cls)
