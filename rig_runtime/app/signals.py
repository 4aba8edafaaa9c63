"""Operator stops by signal: SIGINT, SIGTERM and SIGHUP request a clean stop from the
moment :class:`StopSignals` is installed — before anything is configured — until the
command ends. A signal never interrupts what is under way (a blocking configure step, a
log being closed); the run looks at the request at the next safe point: before
configuring, before the loop, and every cycle (the supervisor ramps the current down and
switches the power stages off).

A second stop signal is for an operator who does not want to wait (e.g. for a log whose
disk does not answer): :meth:`StopSignals.on_repeat` listeners hear it — ``rig run`` ends at
once if the power stages are already off, else as soon as they are."""

from __future__ import annotations

import signal
from typing import Callable

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Interrupted(Exception):
    """A requested stop before RUNNING: exit code 128 + signal number (130 SIGINT, 143
    SIGTERM, 129 SIGHUP), one line saying what happened."""

    def __init__(self, code: int, message: str):
        super().__init__(message)
        self.code = code


class StopSignals:
    """Records the first stop signal and tells the listeners (idempotent, no I/O)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.repeats = 0                    # stop signals after the first
        self._listeners: list[Callable[[], None]] = []
        self._repeat_listeners: list[Callable[[], None]] = []
        self._old: dict[int, object] = {}

    def install(self) -> "StopSignals":
        if self._old:
            return self             # already installed (the console script did it first)
        for s in SIGNALS:
            try:
                self._old[s] = signal.signal(s, self._on_signal)
            except ValueError:          # not the main thread (tests): no handlers, no stops
                pass
        return self

    def restore(self) -> None:
        for s, old in self._old.items():
            signal.signal(s, old)
        self._old.clear()

    def _on_signal(self, signum, frame) -> None:
        if self.signum is None:
            self.signum = signum
            for f in self._listeners:
                f()
        else:
            self.repeats += 1
            for f in self._repeat_listeners:
                f()

    def on_stop(self, fn: Callable[[], None]) -> None:
        """Call ``fn`` at the stop request (at once if one already came)."""
        self._listeners.append(fn)
        if self.signum is not None:
            fn()

    def on_repeat(self, fn: Callable[[], None]) -> None:
        """Call ``fn`` at each stop signal after the first (from the signal handler)."""
        self._repeat_listeners.append(fn)

    def forget(self, fn: Callable[[], None]) -> None:
        """Stop calling ``fn`` (a listener of a run that has ended)."""
        for lst in (self._listeners, self._repeat_listeners):
            while fn in lst:
                lst.remove(fn)

    @property
    def requested(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else ""

    def interrupted(self, what: str) -> Interrupted:
        return Interrupted(128 + (self.signum or 0), f"stopped by {self.name} {what}")

    def __enter__(self) -> "StopSignals":
        return self.install()

    def __exit__(self, *exc: object) -> None:
        self.restore()
