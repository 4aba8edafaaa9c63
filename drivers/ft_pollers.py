"""Two of the F/T pollers (the third, ``process``, is :mod:`drivers.ft_process`):

* :class:`ThreadPoller` (``devices.ft.poller: thread``) — one thread per connection in the
  runtime process, blocking rounds at ``poll_hz``; timestamps ``time.monotonic()``;
* :class:`InlinePoller` (``devices.ft.poller: inline``) — no helper at all: the driver's
  ``poll(now)`` does the I/O itself, never waiting. It first collects what has arrived on
  its sockets (non-blocking ``recv``) and publishes it, stamped ``now``; then, when a round
  is due at ``poll_hz``, it sends the next requests. A request sent in one ``poll`` is
  answered by the next ``poll`` that finds the reply — a pipelined request/response on the
  caller's thread, driven only by the times it is given (the same times and replies give
  the same readings). TCP only: the serial client blocks per request, so ``inline`` with an RTU sensor
  is refused by the configuration (``devices.ft.poller``).
"""

from __future__ import annotations

import math

from rig_runtime.config import FTBus

from .ft_poll import Poller, Sensor, TcpLink

__all__ = ["ThreadPoller", "InlinePoller"]

_EPS = 1e-9                     # float residue of sums of periods must not delay a round


class ThreadPoller(Poller):
    """One daemon thread per connection in this process (:meth:`PollCore.run`)."""

    def start(self) -> None:
        self.core.open()
        self.core.start_threads()

    def close(self) -> None:
        self.core.close()


class InlinePoller(Poller):
    """The polling done by ``latest(now)`` itself (see the module docstring).

    ``start()`` is the same blocking open as the other pollers (connect, read every sensor
    once: DeviceInitError if one does not answer); those reads have no time on the caller's
    clock yet, so they are stamped ``-inf`` (infinitely old until the first reply that ``latest``
    collects). Per connection one request is in flight; a reply not complete
    ``timeout_s`` after its request (by the ``now`` values given) is a timeout, and the
    connection is reopened with a non-blocking connect to the address resolved at open.
    """

    def __init__(self, cfg: FTBus, endpoints: dict[str, tuple[str, int]], reconnect_s: float) -> None:
        self._now = -math.inf
        super().__init__(cfg, endpoints, reconnect_s, clock=self._clock)
        assert not any(link.rtu for link in self.core.links), "FTBus refuses inline with RTU"
        self._period = 1.0 / cfg.poll_hz
        self._timeout_s = cfg.timeout_s
        self._due = -math.inf
        self._queues: list[list[Sensor]] = [[] for _ in self.core.links]
        self._busy = False              # a link has a request or connect in flight or sensors queued

    def _clock(self) -> float:
        return self._now

    def start(self) -> None:
        self.core.open()

    def close(self) -> None:
        self.core.close_links()

    def latest(self, now: float):
        self._now = now
        new_round = now >= self._due - _EPS
        if new_round:                   # no catch-up burst after a gap
            nxt = self._due + self._period
            self._due = nxt if now < nxt - _EPS else now + self._period
        elif not self._busy:            # nothing in flight, nothing to send: nothing can be new
            return super().latest(now)
        busy = False
        for link, queue in zip(self.core.links, self._queues):
            if new_round:               # unfinished sensors of the last round go first
                for s in link.sensors:
                    if s not in queue:
                        queue.append(s)
            self._step(link, queue, now)        # type: ignore[arg-type]
            if queue or link.pending is not None or link.connecting:    # type: ignore[attr-defined]
                busy = True
        self._busy = busy
        return super().latest(now)

    def _step(self, link: TcpLink, queue: list[Sensor], now: float) -> None:
        """Collect, then send: one connection's share of ``latest(now)``."""
        core = self.core
        if link.connecting:
            try:
                done = link.connect_done()
            except OSError as exc:
                return core.connect_failed(link, exc)
            if not done:
                if now - link.since >= self._timeout_s:
                    core.connect_failed(link, TimeoutError("timed out"))
                return
            core.connected(link)
        if link.pending is not None and not core.on_readable(link):
            if now - link.since < self._timeout_s:
                return                  # the reply may still come
            core.give_up(link)          # timeout or truncated reply; the connection is closed
        if link.pending is not None or not queue:
            return
        if link.sock is None:
            if now < link.retry_at:
                return
            try:
                done = link.connect_nowait()
            except OSError as exc:
                return core.connect_failed(link, exc)
            link.since = now
            if not done:
                return
            core.connected(link)
        core.send(link, queue.pop(0))
