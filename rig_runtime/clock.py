"""Clocks: the loop owns time through one interface with two implementations.

- ``RealtimeClock``: monotonic clock, absolute deadlines; sleeps until ``spin_s`` before
  the deadline, then spins, so the wake-up does not depend on the sleep's granularity.
- ``LockstepClock``: simulated time; ``wait_until(t)`` lets the simulated plant and its
  virtual devices advance to ``t`` (a callback) and returns at once — deterministic, as
  fast as the machine allows.
"""

from __future__ import annotations

import abc
import os
import time
from typing import Callable

from .config import Realtime


class Clock(abc.ABC):
    #: whether releases are wall-clock deadlines (a lockstep clock's are not: nothing is late)
    deadlines = True

    @abc.abstractmethod
    def now(self) -> float:
        """Current time, s."""

    @abc.abstractmethod
    def wait_until(self, t: float) -> float:
        """Return at (or as soon as possible after) ``t``; returns the release time."""


class RealtimeClock(Clock):
    def __init__(self, spin_s: float = 200e-6):
        self.spin_s = spin_s
        self._mono = time.monotonic
        self._sleep = time.sleep

    def now(self) -> float:
        return self._mono()

    def wait_until(self, t: float) -> float:
        mono = self._mono
        remaining = t - mono() - self.spin_s
        if remaining > 0:
            self._sleep(remaining)
        now = mono()
        while now < t:
            now = mono()
        return now


class LockstepClock(Clock):
    """Simulated time; ``advance(t)`` is called before each release and may return a later
    release time (a simulated stall: the runtime wakes up late, as on a starved machine)."""

    deadlines = False

    def __init__(self, advance: Callable[[float], float | None] | None = None, t0: float = 0.0):
        self._t = t0
        self._advance = advance

    def now(self) -> float:
        return self._t

    def wait_until(self, t: float) -> float:
        """``advance(t)`` may return a later release time (a simulated stall); None is ``t``."""
        if t > self._t:
            r = self._advance(t) if self._advance is not None else None
            self._t = t if r is None else max(t, r)
        return self._t


def apply_realtime(rt: Realtime) -> list[str]:
    """Apply SCHED_FIFO, CPU affinity and mlockall as configured; return one line per
    setting saying whether it took effect (each is used when the OS permits)."""
    report = []
    if rt.switch_interval_us is not None:
        import sys
        sys.setswitchinterval(rt.switch_interval_us * 1e-6)
        report.append(f"interpreter switch interval {rt.switch_interval_us:g} us: applied")
    if rt.cpu_affinity:
        err = set_cpu_affinity(rt.cpu_affinity)
        report.append(f"cpu affinity {sorted(rt.cpu_affinity)}: " + (f"not applied ({err})" if err else "applied"))
    if rt.sched_fifo_priority is not None:
        err = set_sched_fifo(rt.sched_fifo_priority)
        report.append(f"SCHED_FIFO priority {rt.sched_fifo_priority}: " + (f"not applied ({err})" if err else "applied"))
    if rt.mlockall:
        try:
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            MCL_CURRENT, MCL_FUTURE = 1, 2
            if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
                err = ctypes.get_errno()
                raise OSError(err, os.strerror(err))
            report.append("mlockall: applied")
        except OSError as e:
            report.append(f"mlockall: not applied ({e})")
    return report


def set_cpu_affinity(cpus) -> str | None:
    """Run this process on ``cpus`` (threads and processes started later inherit it);
    None if applied, else why not."""
    try:
        os.sched_setaffinity(0, set(cpus))
        return None
    except (OSError, AttributeError, ValueError) as e:
        return str(e)


def set_sched_fifo(priority: int) -> str | None:
    """Run the calling thread SCHED_FIFO at ``priority`` (threads and processes it starts
    later inherit it); None if applied, else why not."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return None
    except (OSError, AttributeError) as e:
        return str(e)


def helper_cpus(rt: Realtime) -> tuple[int, ...] | None:
    """The CPUs for the runtime's helper processes (recording sidecar, F/T poller): those the
    loop is not pinned to by ``realtime.cpu_affinity``; None when it is not pinned or no
    CPU is left (the helpers then share the loop's)."""
    if not rt.cpu_affinity:
        return None
    others = sorted(set(range(os.cpu_count() or 1)) - set(rt.cpu_affinity))
    return tuple(others) or None


def as_background_process(pid: int, cpus=None) -> None:
    """Move process ``pid`` (a helper process this one started) to SCHED_OTHER: a child
    inherits the runtime's SCHED_FIFO and must not compete with the loop; given ``cpus``
    (:func:`helper_cpus`), also off the loop's CPU. Best effort."""
    try:
        os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass
    if cpus:
        try:
            os.sched_setaffinity(pid, set(cpus))
        except (OSError, AttributeError, ValueError):
            pass


def as_background_thread() -> bool:
    """Called first in a helper thread (recorder writer, pollers): run it SCHED_OTHER.

    Threads inherit the policy of the thread that creates them; once the process runs
    SCHED_FIFO, a helper at the loop's priority would not be preempted by the loop on a
    shared CPU. Linux applies ``sched_setscheduler(0, …)`` to the calling thread only.
    Returns whether the thread now runs SCHED_OTHER (False where the OS does not tell)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        return os.sched_getscheduler(0) == os.SCHED_OTHER
    except (OSError, AttributeError):
        return False


def next_release(t0: float, k: int, h: float, t_done: float) -> tuple[bool, int]:
    """For a cycle released at ``t0 + k·h`` and done at ``t_done``: whether it ran past its
    period, and the index of the next release still ahead — missed periods are skipped,
    not caught up (the control loop and the bare loop of ``rig latency``)."""
    missed = t_done > t0 + (k + 1) * h
    return missed, (int((t_done - t0) / h) + 1 if missed else k + 1)

