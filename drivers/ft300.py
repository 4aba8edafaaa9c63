"""Robotiq FT 300-class six-axis force–torque sensors over Modbus (RTU, or TCP via a gateway):
the driver :class:`FTSensorSet`.

Modules by job (no one imports one that imports it back):

* :mod:`drivers.ft_codec` — registers 180–185 <-> :class:`Wrench` (shared with the simulator);
* :mod:`drivers.ft_modbus` — Modbus TCP framing of function 0x03 (both ends of the wire);
* :mod:`drivers.ft_poll` — links, transactions, the classification of their outcomes, the
  immutable :class:`~drivers.ft_poll.Published` per sensor and the :class:`Poller` interface;
* :mod:`drivers.ft_process` (``process``), :mod:`drivers.ft_pollers` (``thread``,
  ``inline``) — where the polling runs, chosen by ``devices.ft.poller``;
* this module — the driver: starts the poller, and turns what it published into one
  :class:`FTReading` (wrench, t, health) per sensor in ``poll(now)``, never waiting.
  It reports what the sensor and the link said; how old a sample may be is the supervisor's
  rule (``limits.ft_stale_s``), judged from ``t``.

Written against pymodbus 3.16 for RTU (``device_id=`` keyword, ``trace_packet`` hook).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple, Optional

from rig_runtime.config import FTBus

from rig_runtime.hardware import Driver, Freshness, Health, health

from .ft_codec import Wrench
from .ft_poll import Poller, Published
from .ft_pollers import InlinePoller, ThreadPoller
from .ft_process import ProcessPoller

__all__ = ["Wrench", "FTReading", "FTSensorSet", "POLLERS"]

POLLERS: dict[str, type[Poller]] = {"process": ProcessPoller, "thread": ThreadPoller, "inline": InlinePoller}
_FRESH, _INVALID = Freshness.FRESH, Freshness.INVALID


class FTReading(NamedTuple):
    """What :meth:`FTSensorSet.poll` reports for one sensor: one object per publication (the
    same object poll after poll while nothing new was published; its ``health`` likewise).
    ``health.timeouts`` and ``health.bad_frames`` count unanswered and garbled transactions,
    ``errors`` the exception responses and saturated samples, all since configure. How old
    ``t`` may be is the supervisor's rule (``limits.ft_stale_s``), judged from ``t``."""

    wrench: Optional[Wrench]    # latest sample (kept after failures; a saturated one is
                                # passed on with health INVALID); None before the first
    t: float                    # time the sample was received (nan if none; -inf: read at open by
                                # the inline poller, before any time was given)
    health: Health


class _View:
    """A sensor's latest publication, the poller's failure (``dead``) it was judged with and
    the reading built from them, kept until one of them changes."""

    __slots__ = ("name", "pub", "dead", "reading")

    def __init__(self, name: str) -> None:
        self.name = name
        self.pub: Optional[Published] = None
        self.dead = ""
        self.reading: Optional[FTReading] = None


class FTSensorSet(Driver):
    """All force–torque sensors of ``cfg`` (one connection per distinct endpoint), polled
    by the poller ``cfg.poller`` names. ``endpoints`` overrides sensors' ``host:port``;
    ``reconnect_s`` is the back-off after a failed connect; ``poller_cpus`` optionally pins
    the ``process`` poller (e.g. away from the loop's CPU; ignored by the others)."""

    name = "ft"

    def __init__(self, cfg: FTBus, endpoints: dict[str, tuple[str, int]] | None = None, *,
                 reconnect_s: float = 0.5, poller_cpus: Optional[Iterable[int]] = None) -> None:
        super().__init__()
        endpoints = dict(endpoints or {})
        if cfg.poller == "process":
            self._poller: Poller = ProcessPoller(cfg, endpoints, reconnect_s,
                                                 cpus=None if poller_cpus is None else tuple(poller_cpus))
        else:
            self._poller = POLLERS[cfg.poller](cfg, endpoints, reconnect_s)
        self._views = tuple(_View(n) for n in self._poller.names)
        self._out: dict[str, FTReading] = {}

    @property
    def names(self) -> tuple[str, ...]:
        return self._poller.names

    @property
    def poller(self) -> Poller:
        """The poller (``process``: its ``.process`` is the running child, or None)."""
        return self._poller

    # ------------------------------------------------------------------ lifecycle
    def _configure(self) -> None:
        """Connect and read every sensor once (blocking; DeviceInitError names the sensor and
        its endpoint), then poll as configured."""
        self._poller.start()

    def _close(self) -> None:
        self._poller.close()            # the last published states stay for poll() after close

    def counters(self) -> dict[str, int]:
        """Each sensor's counters as of the latest poll, as ``SENSOR.name``."""
        return {f"{v.name}.{k}": n for v in self._views if v.pub is not None for k, n in v.pub.counters}

    # ------------------------------------------------------------------ cycle side
    def poll(self, now: float) -> dict[str, FTReading]:
        """Latest sample of every sensor with its time and health; never waits (the inline
        poller does its non-blocking I/O here). The same mapping as the previous poll while
        no sensor published anything new (a returned mapping is never changed afterwards)."""
        dead = self._poller.failure()       # once per poll (a system call in process mode)
        changed = False
        for v, p in zip(self._views, self._poller.latest(now)):
            if p is not v.pub or dead != v.dead:
                v.pub, v.dead = p, dead
                state, cause = self._classify(p, dead)
                r = v.reading
                h = health(r.health if r is not None else None, state, cause, p.bad_frames, p.timeouts, p.errors)
                v.reading = FTReading(p.wrench, p.t, h)
                changed = True
        if changed:
            self._out = {v.name: v.reading for v in self._views}
        return self._out

    def _classify(self, p: Published, dead: str) -> tuple[Freshness, str]:
        """State and cause of one sensor, from what the sensor and the link said: INVALID
        while the latest reply is a Modbus exception, the poll process is dead (``dead``: why), the link is
        down (lost, or the reconnect failed) or the latest sample has an axis at an INT16
        limit (``p.saturation``: not a measurement); else FRESH, with the latest outcome as a
        note (a timeout, a garbled reply: counted, and judged by the supervisor with the time)."""
        if p.exc_code is not None:
            return _INVALID, p.cause
        if dead:
            return _INVALID, dead + (f" ({p.cause})" if p.cause else "")
        if p.link_down:
            return _INVALID, p.cause
        if p.wrench is None:
            return _FRESH, f"no sample yet ({p.cause})"
        if p.saturation:
            return _INVALID, p.saturation
        return _FRESH, p.cause
