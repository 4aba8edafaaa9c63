"""The common driver interface, in the spirit of python-can's ``BusABC``.

A driver is opened once (blocking allowed), then called every control period with
``poll()`` and, where the device takes commands, ``write()`` — both must return without
waiting on I/O. ``close()`` is idempotent; drivers are context managers.
"""

from __future__ import annotations

import abc
import enum
from dataclasses import dataclass, field
from typing import Any

from rig_runtime.errors import (  # re-exported: the driver error hierarchy
    ConfigError,
    DeviceError,
    DeviceInitError,
    DeviceIOError,
    DeviceTimeoutError,
)

__all__ = [
    "ConfigError", "DeviceError", "DeviceInitError", "DeviceIOError", "DeviceTimeoutError",
    "Freshness", "Health", "Driver",
]


class Freshness(enum.Enum):
    FRESH = "fresh"      # a valid sample arrived within the staleness bound
    STALE = "stale"      # the latest valid sample is too old, or none has arrived yet
    INVALID = "invalid"  # the device reports that its value is not a measurement (error code, fault)


@dataclass(slots=True)
class Health:
    """Health of one device channel; counters only ever increase while the driver is open."""

    state: Freshness = Freshness.STALE
    cause: str = ""                 # why it is not fresh ("no peak", "TPDO missing", …)
    bad_frames: int = 0             # frames/bytes discarded as garbled
    timeouts: int = 0
    errors: int = 0                 # device-reported errors (error codes, exceptions, EMCY)
    counters: dict[str, int] = field(default_factory=dict)  # anything device specific

    @property
    def fresh(self) -> bool:
        return self.state is Freshness.FRESH


class Driver(abc.ABC):
    """A device family on one transport."""

    name: str = "driver"

    def __init__(self) -> None:
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        """Open the transport and bring the device up. Idempotent."""
        if not self._open:
            self._do_open()
            self._open = True

    def close(self) -> None:
        """Leave the device safe and release the transport. Idempotent, never raises
        for a device that is already gone."""
        if self._open:
            self._open = False
            self._do_close()

    @abc.abstractmethod
    def _do_open(self) -> None: ...

    @abc.abstractmethod
    def _do_close(self) -> None: ...

    @abc.abstractmethod
    def poll(self, now: float) -> Any:
        """Drain what arrived without blocking; return the latest samples with health."""

    def write(self, command: Any, now: float) -> None:  # pragma: no cover - default
        """Send commands without blocking (devices that take none need not override)."""
        raise NotImplementedError(f"{self.name} takes no commands")

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
