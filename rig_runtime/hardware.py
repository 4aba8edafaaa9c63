"""The hardware seam: the interface every driver implements, with a lifecycle in the
spirit of ros2_control's hardware interface and python-can's ``BusABC`` template.

Lifecycle (public methods do the bookkeeping, ``_hooks`` do the device work)::

    configure()      open transports, configure the device (SDO, PDO mapping, the drive's
                     own safety settings) — no power. Blocking allowed.
    activate(t)      power stages on (drives: towards OPERATION ENABLED). Called only by
                     the supervisor's ARM transition. Non-blocking.
    poll(t)          drain what arrived without blocking; one immutable reading.
    write(cmd, t)    send commands without blocking (devices that take none need not).
    deactivate(t)    zero, quick stop, disable. Non-blocking; idempotent.
    resume(t)        after deactivate: communication on, power stages off (as configured),
                     so that an operator's fault reset can arm again. Non-blocking.
    close()          deactivate if active, release the transport. Idempotent, never
                     raises for a device that is already gone.

A driver is a context manager (``configure`` on enter, ``close`` on exit). Drivers live in
the ``drivers`` package and are chosen by name through :mod:`rig_runtime.registry`; this
module is the core's side of the seam and imports no driver.
"""

from __future__ import annotations

import abc
import enum
from dataclasses import dataclass
from typing import Any, Protocol

__all__ = ["Freshness", "Health", "health", "Lifecycle", "Hardware", "Driver"]


class Freshness(enum.Enum):
    """A channel's state. Drivers report FRESH or INVALID — what the device or transport
    said, never a judgement of age; STALE is the supervisor's judgement (``safety``), from
    the reading's arrival time or unanswered requests against ``limits:``."""
    FRESH = "fresh"      # driver: the device said nothing against its latest value (however old)
    STALE = "stale"      # supervisor: the latest valid value is too old, or none has arrived yet
    INVALID = "invalid"  # the device/transport says the value is not a measurement (error code,
                         # exception, fault, saturation, link gone)


@dataclass(frozen=True, slots=True)
class Health:
    """Health of one device channel as its driver observed it: an immutable value, built
    when something changes.

    ``state`` is FRESH or INVALID from a driver (see :class:`Freshness`); ``cause`` says
    why it is INVALID, or notes an observation while FRESH ("no data yet"). ``bad_frames``,
    ``timeouts`` and ``errors`` are cumulative counts that only ever increase while the
    driver is configured; judging them (corruption, a link going quiet) is the
    supervisor's. Statistics that change every poll (frames, bytes, …) are not part of
    it: :meth:`Driver.counters` returns them on demand.
    """

    state: Freshness = Freshness.STALE
    cause: str = ""                 # why it is INVALID ("no peak", "EMCY 0x…", …), or a note
    bad_frames: int = 0             # frames/bytes discarded as garbled
    timeouts: int = 0
    errors: int = 0                 # device-reported errors (error codes, exceptions, EMCY)

    @property
    def fresh(self) -> bool:
        return self.state is Freshness.FRESH


def health(prev: Health | None, state: Freshness, cause: str, bad_frames: int, timeouts: int,
           errors: int) -> Health:
    """``prev`` again if it already says this, else a new :class:`Health` (a driver hands
    out the same value poll after poll while nothing changes)."""
    if (prev is not None and prev.state is state and prev.cause == cause and prev.bad_frames == bad_frames
            and prev.timeouts == timeouts and prev.errors == errors):
        return prev
    return Health(state, cause, bad_frames, timeouts, errors)


class Lifecycle(enum.Enum):
    UNCONFIGURED = "unconfigured"
    CONFIGURED = "configured"     # transports open, device configured, no power
    ACTIVE = "active"             # power stages enabled (or being enabled)


class Hardware(Protocol):
    """The one lifecycle (module docstring): a driver implements it, the rig's device set
    (``devices.RigDevices``) implements it over its drivers, the supervisor switches the
    power stages through it and the loop polls and writes through it."""

    def configure(self) -> None: ...
    def activate(self, now: float) -> None: ...
    def poll(self, now: float) -> Any: ...
    def write(self, command: Any, now: float) -> None: ...
    def deactivate(self, now: float) -> None: ...
    def resume(self, now: float) -> None: ...
    def close(self) -> None: ...
    # a device set with drives: one drive quick-stopped and disabled while the others run
    # (the supervisor's RECONFIGURED; until the next activate)
    def isolate(self, wheel: str, now: float) -> None: ...


class Driver(abc.ABC):
    """A device family on one transport (see the module docstring for the lifecycle)."""

    name: str = "driver"

    def __init__(self) -> None:
        self._lifecycle = Lifecycle.UNCONFIGURED

    @property
    def lifecycle(self) -> Lifecycle:
        return self._lifecycle

    @property
    def is_configured(self) -> bool:
        return self._lifecycle is not Lifecycle.UNCONFIGURED

    def configure(self) -> None:
        """Open the transport and configure the device, without power. Idempotent; on
        failure nothing stays open (the hook cleans up) and the error names the device."""
        if self._lifecycle is Lifecycle.UNCONFIGURED:
            self._configure()
            self._lifecycle = Lifecycle.CONFIGURED

    def activate(self, now: float) -> None:
        """Enable the power stages (non-blocking; a drive reports when it got there)."""
        if self._lifecycle is Lifecycle.CONFIGURED:
            self._activate(now)
            self._lifecycle = Lifecycle.ACTIVE

    def deactivate(self, now: float) -> None:
        """Zero, quick stop, disable (non-blocking). Idempotent."""
        if self._lifecycle is Lifecycle.ACTIVE:
            self._lifecycle = Lifecycle.CONFIGURED
            self._deactivate(now)

    def resume(self, now: float) -> None:
        """After a deactivate: communication back on with the power stages off — the state
        ``configure()`` left — so that the device can be armed again (an operator's fault
        reset). Non-blocking; nothing to do while active or unconfigured."""
        if self._lifecycle is Lifecycle.CONFIGURED:
            self._resume(now)

    def close(self) -> None:
        """Deactivate if active, leave the device safe and release the transport.
        Idempotent; never raises for a device that is already gone."""
        if self._lifecycle is Lifecycle.UNCONFIGURED:
            return
        try:
            self.deactivate(self._close_time())
        finally:
            self._lifecycle = Lifecycle.UNCONFIGURED
            self._close()

    @abc.abstractmethod
    def _configure(self) -> None: ...

    def _activate(self, now: float) -> None:
        """Sensors have no power stage: nothing to do."""

    def _deactivate(self, now: float) -> None:
        """Sensors have no power stage: nothing to do."""

    def _resume(self, now: float) -> None:
        """Sensors keep communicating when deactivated: nothing to do."""

    @abc.abstractmethod
    def _close(self) -> None: ...

    def _close_time(self) -> float:
        """The time stamp a deactivation on close carries (the latest poll/write time)."""
        return 0.0

    @abc.abstractmethod
    def poll(self, now: float) -> Any:
        """Drain what arrived without blocking; return the latest samples with health."""

    def write(self, command: Any, now: float) -> None:  # pragma: no cover - default
        """Send commands without blocking (devices that take none need not override)."""
        raise NotImplementedError(f"{self.name} takes no commands")

    def counters(self) -> dict[str, int]:
        """Device statistics (frames, bytes, …) as a new dict; for status views and tests."""
        return {}

    def __enter__(self):
        self.configure()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
