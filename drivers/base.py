"""The common driver interface, in the spirit of python-can's ``BusABC``.

A driver is opened once (blocking allowed), then called every control period with
``poll()`` and, where the device takes commands, ``write()`` — both must return without
waiting on I/O. ``close()`` is idempotent; drivers are context managers.
"""

from __future__ import annotations

import abc
import enum
from dataclasses import dataclass, field
from typing import Any, Mapping

from rig_runtime.errors import (  # re-exported: the driver error hierarchy
    ConfigError,
    DeviceError,
    DeviceInitError,
    DeviceIOError,
    DeviceTimeoutError,
)

__all__ = [
    "ConfigError", "DeviceError", "DeviceInitError", "DeviceIOError", "DeviceTimeoutError",
    "Freshness", "Health", "CounterView", "snapshot", "Driver",
]


class Freshness(enum.Enum):
    FRESH = "fresh"      # a valid sample arrived within the staleness bound
    STALE = "stale"      # the latest valid sample is too old, or none has arrived yet
    INVALID = "invalid"  # the device reports that its value is not a measurement (error code, fault)


@dataclass(slots=True)
class Health:
    """Health of one device channel; counters only ever increase while the driver is open.

    A driver keeps one live ``Health`` per channel and hands out snapshots with its
    readings (:func:`snapshot`): state, cause and the three counts as they were at the poll;
    ``counters`` of a snapshot is a read-only *live* view of the driver's counters
    (:class:`CounterView`), so a snapshot can be handed out again while only counters
    changed (the usual poll).
    """

    state: Freshness = Freshness.STALE
    cause: str = ""                 # why it is not fresh ("no peak", "TPDO missing", …)
    bad_frames: int = 0             # frames/bytes discarded as garbled
    timeouts: int = 0
    errors: int = 0                 # device-reported errors (error codes, exceptions, EMCY)
    counters: Mapping[str, int] = field(default_factory=dict)  # anything device specific (live: a dict;
                                                               # snapshot: a CounterView of it)

    @property
    def fresh(self) -> bool:
        return self.state is Freshness.FRESH


class CounterView(Mapping[str, int]):
    """Read-only live view of a driver's counters, as a health snapshot holds them. Copies,
    pickles and deep-copies as a plain dict of the counts at that moment (``dict(view)``
    too, e.g. for JSON)."""

    __slots__ = ("_d",)

    def __init__(self, counters: dict[str, int]) -> None:
        self._d = counters

    def __getitem__(self, key: str) -> int:
        return self._d[key]

    def __iter__(self):
        return iter(self._d)

    def __len__(self) -> int:
        return len(self._d)

    def __repr__(self) -> str:
        return repr(self._d)

    def copy(self) -> dict[str, int]:
        return dict(self._d)

    def __reduce__(self):
        return dict, (dict(self._d),)

    def __deepcopy__(self, memo) -> dict[str, int]:
        return dict(self._d)


def snapshot(live: Health, counters: CounterView, prev: Health | None) -> Health:
    """The snapshot of ``live`` for a reading: ``prev`` again if ``live`` still matches it
    (state, cause and counts), else a new one. ``counters``: the view of ``live.counters``
    that the snapshots share."""
    if (prev is not None and prev.state is live.state and prev.bad_frames == live.bad_frames
            and prev.timeouts == live.timeouts and prev.errors == live.errors and prev.cause == live.cause):
        return prev
    return Health(live.state, live.cause, live.bad_frames, live.timeouts, live.errors, counters)


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
