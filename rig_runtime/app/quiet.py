"""The device libraries' own logging, quieted for a run (``rig run``, ``rig dry-run``, a
campaign's run on a Dask worker): what they would log — a timeout, a bus error — reaches
the runtime as what the driver observed, and the supervisor judges and reports it."""

from __future__ import annotations

import logging

DEVICE_LIBRARIES = ("pymodbus", "can", "canopen")


def quiet_device_libraries() -> None:
    """Only CRITICAL from pymodbus, python-can and canopen."""
    for name in DEVICE_LIBRARIES:
        logging.getLogger(name).setLevel(logging.CRITICAL)
