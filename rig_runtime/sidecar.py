"""The recording sidecar: a separate process that takes every cycle row and event out of
the shared-memory ring (:mod:`rig_runtime.ring`), writes the HDF5 log
(:mod:`rig_runtime.logfile`) and feeds the live outputs (telemetry, panel, operator socket).

Why a process: HDF5 calls and every live output's Python work would hold the loop's
interpreter lock (100–180 µs per HDF5 call); in their own process they cannot. The loop's
process keeps a single thread.

Lifetime: started by :class:`rig_runtime.recorder.Recorder` as a fresh interpreter
(``python -c``: the runtime may run SCHED_FIFO and have threads, so it must not fork, and
unlike ``multiprocessing``'s spawn this does not re-run the caller's main script), SCHED_OTHER, ignoring SIGINT, SIGTERM
and SIGHUP (a Ctrl-C reaches the whole process group; the runtime stops the rig on it and
closes the log itself). It ends when the recorder says ``close`` — after draining the ring,
flushing and closing the file — or when its pipe to the runtime reports EOF: the runtime
died (SIGKILL, crash). Then it takes what the ring holds (every row the loop published),
records an event saying so, and closes the log readable up to that last row. A runtime that
stops waiting for the close (its bound, ``recorder.close_timeout_s``: a disk that does not
answer) leaves it running: it has the close request, finishes the log when the disk answers,
finds its socket closed and ends.

A lockstep run (no deadlines) without live outputs does not start this process: its
recorder drives the same :class:`Sidecar` in the loop's own process (``Recorder(writer=
"inline")``), draining the ring when it is full and at close — the same ring, the same
writer, the same file; only no interpreter to start per run.

Outputs are named by the application as ``"package.module:Class"`` strings, imported here
(lazily: the core names none) and constructed as ``Class(info, **options)``; a class whose
constructor takes ``mailbox`` also gets the operator mailbox. Each has ``rows(block)``,
``event(ev)``, ``status(dict)`` and ``close()``. An output that raises is dropped with one
line on stderr; it never stops recording.
"""

from __future__ import annotations

import importlib
import json
import math
import multiprocessing.connection
import signal
import sys
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

from . import ring
from .clock import as_background_thread
from .errors import DeviceError, RigError, picklable
from .logformat import MIN_FREE_BYTES
from .stats import Histogram

if TYPE_CHECKING:
    from .logfile import LogFile

_POLL_S = 0.025            # wake-up period with no live output
_LIVE_POLL_S = 0.005       # with live outputs: every cycle at 200 Hz
MAX_FLUSH_S = 1.0          # documented guarantee: flushed at least once a second


@dataclass(frozen=True)
class LogInfo:
    """What an output is told about the log being written."""

    path: str
    columns: tuple[str, ...]
    attrs: dict


@dataclass(frozen=True)
class SidecarSpec:
    path: str
    columns: tuple[str, ...]
    attrs: dict
    flush_s: float = 0.5
    min_free_bytes: int = MIN_FREE_BYTES
    outputs: tuple[tuple[str, dict], ...] = ()

    @property
    def flush_period(self) -> float:
        return flush_period(self.flush_s)


def flush_period(flush_s: float) -> float:
    """How often the sidecar flushes: as configured, and at least every MAX_FLUSH_S."""
    return min(flush_s, MAX_FLUSH_S)


def load_output(name: str, info: LogInfo, options: dict, mailbox: Callable[[], Any]) -> Any:
    """Import ``"module:Class"`` and construct it. Only a class that declares
    ``TAKES_MAILBOX = True`` (the ``rig ctl`` server) is handed the mailbox to the loop:
    talking back to the loop is something an output says it does, not something its
    constructor's signature happens to allow."""
    mod, _, attr = name.partition(":")
    cls = getattr(importlib.import_module(mod), attr)
    kw = dict(options)
    if getattr(cls, "TAKES_MAILBOX", False) is True:
        kw["mailbox"] = mailbox()
    return cls(info, **kw)


def _ignore_stop_signals() -> None:
    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        try:
            signal.signal(s, signal.SIG_IGN)
        except (OSError, ValueError):
            pass


def cli() -> None:
    """``python -c "from rig_runtime.sidecar import cli; cli()" FD RING``: FD is this end of
    the recorder's socket pair; the recorder sends the :class:`SidecarSpec` first."""
    _ignore_stop_signals()
    conn = multiprocessing.connection.Connection(int(sys.argv[1]))
    try:
        spec = conn.recv()
    except (EOFError, OSError):
        return                              # the recorder is gone already
    main(sys.argv[2], spec, conn)


def main(ring_path: str, spec: SidecarSpec, conn: multiprocessing.connection.Connection) -> None:
    """The sidecar process's work (after :func:`cli`, which ignores the stop signals first)."""
    as_background_thread()
    layout, mm = ring.attach(ring_path)
    sidecar = open_log(ring.Consumer(mm, layout), spec, conn)
    if isinstance(sidecar, tuple):
        conn.send(sidecar)
        return
    conn.send(("ready",))
    sidecar.run()


def open_log(cons: ring.Consumer, spec: SidecarSpec, conn) -> "Sidecar | tuple":
    """Start the outputs and create the log: the :class:`Sidecar` that writes it, or the
    ``("error", device, message, cause)`` that says why not."""
    info = LogInfo(spec.path, tuple(spec.columns), dict(spec.attrs))
    outputs: list[tuple[str, Any]] = []
    from .logfile import LogFile        # h5py: in the sidecar's process only, never the loop's
    log = LogFile(spec.path, spec.columns, spec.attrs, spec.min_free_bytes)
    try:
        def mailbox():
            from .mailbox import Mailbox
            return Mailbox(cons.mailbox_view())
        for name, opts in spec.outputs:
            outputs.append((name, load_output(name, info, opts, mailbox)))
        log.create()
    except DeviceError as e:
        _close_outputs(outputs)
        return ("error", e.device, str(e)[len(e.device) + 2:], picklable(e.__cause__))
    except RigError as e:           # an output's option the operator got wrong (a port in use, ...)
        _close_outputs(outputs)
        return ("error", "recorder", f"live output: {e}", None)
    except Exception as e:  # noqa: BLE001 - an output that cannot start: its cause, one line
        _close_outputs(outputs)
        return ("error", "recorder", f"live output failed to start ({type(e).__name__}: {e})", None)
    return Sidecar(cons, log, outputs, spec, conn)


def _us(h: Histogram) -> dict:
    p50, p99 = h.percentiles((50.0, 99.0)) if h.n else (math.nan, math.nan)
    return {"last": h.last * 1e6, "p50": p50 * 1e6, "p99": p99 * 1e6, "max": h.max * 1e6}


def _close_outputs(outputs) -> None:
    for _, o in outputs:
        try:
            o.close()
        except Exception:  # noqa: BLE001
            pass


class Sidecar:
    """The sidecar's loop (one thread): drain, write, feed, until close or the runtime's death.
    Inline (``conn`` None): the recorder calls :meth:`drain` and :meth:`finish` instead of
    :meth:`run`."""

    def __init__(self, cons: ring.Consumer, log: LogFile, outputs: list, spec: SidecarSpec, conn):
        self.cons = cons
        self.log = log
        self.outputs = outputs
        self.spec = spec
        self.conn = conn
        self.poll_s = _LIVE_POLL_S if outputs else _POLL_S
        self._pending_rows: list = []
        self._pending_n = 0
        self._events: list[tuple] = []
        self._last_t = math.nan
        self._batch = max(1, cons.layout.capacity // 4)
        cols = list(spec.columns)
        # the timing monitor's distributions, from every row (the loop sends only counts)
        self._timing = (cols.index("lateness"), cols.index("work"), Histogram(), Histogram()) \
            if outputs and "lateness" in cols and "work" in cols else None

    def run(self) -> None:
        closing: dict | None = None
        parent_gone = False
        next_flush = time.monotonic() + self.spec.flush_period
        while True:
            try:
                if self.conn.poll(self.poll_s):
                    msg = self.conn.recv()
                    if msg[0] == "close":
                        closing = msg[1]
            except (EOFError, OSError):
                parent_gone = True
            now = time.monotonic()
            flush = now >= next_flush
            if flush:
                next_flush = now + self.spec.flush_period
            self._service(flush=flush)
            if closing is not None or parent_gone:
                break
        self._service(flush=False)            # what arrived meanwhile
        if parent_gone:
            t = self._last_t
            self._event((t, "recorder", "runtime", "died", math.nan, math.nan,
                         "the runtime process ended without closing the log (killed or crashed); "
                         "the log holds every cycle it published"))
        self._finish(closing or {}, parent_gone)

    def drain(self, flush: bool) -> None:
        """Inline: take what the ring holds and write it (and flush, if ``flush``)."""
        self._service(flush=flush)

    def finish(self, closing: dict) -> dict:
        """Inline: take the rest, close the log; what the process would answer to ``close``."""
        self._service(flush=False)
        return self._finish(closing, False)

    def _event(self, ev: tuple) -> None:
        self._events.append(ev)
        self._feed("event", ev)

    def _service(self, flush: bool) -> None:
        cons = self.cons
        for ev in cons.take_events():
            self._event(ev)
        block = cons.take_rows()
        if len(block):
            self._last_t = float(block[-1, 0])
            self._pending_rows.append(block)
            self._pending_n += len(block)
            if self._timing is not None:
                il, iw, hl, hw = self._timing
                for lat, work in block[:, (il, iw)].tolist():
                    hl.add(lat)
                    hw.add(work)
            self._feed("rows", block)
        st = cons.status()
        if st is not None:
            try:
                status = json.loads(st)
            except ValueError:
                status = None
            if status is not None:
                if self._timing is not None and isinstance(status.get("timing"), dict):
                    _, _, hl, hw = self._timing
                    status["timing"].update(lateness_us=_us(hl), work_us=_us(hw))
                self._feed("status", status)
        if flush or self._pending_n >= self._batch or self._events:
            self._write(flush or bool(self._events))

    def _write(self, flush: bool) -> None:
        import numpy as np
        block = np.concatenate(self._pending_rows) if self._pending_rows else None
        self._pending_rows, self._pending_n = [], 0
        events, self._events = self._events, []
        self.log.write(block, events, flush)
        self.cons.report(self.log.rows_written, self.log.rows_flushed)
        if self.log.error:
            self.cons.set_error(self.log.error)

    def _feed(self, what: str, arg: Any) -> None:
        for item in list(self.outputs):
            name, out = item
            try:
                getattr(out, what)(arg)
            except Exception as e:  # noqa: BLE001 - a live view must never stop recording
                self.outputs.remove(item)
                print(f"rig: live output {name} stopped ({type(e).__name__}: {e}); recording goes on",
                      file=sys.stderr, flush=True)
                try:
                    out.close()
                except Exception:  # noqa: BLE001
                    pass

    def _finish(self, closing: dict, parent_gone: bool) -> dict:
        import numpy as np
        rows_dropped, events_dropped = self.cons.dropped()
        loop_error = closing.get("error", "")
        if loop_error:
            self.log.fail(loop_error)
        self._write(flush=True)
        self.log.close({"rows_dropped": np.int64(rows_dropped), "events_dropped": np.int64(events_dropped)})
        self.cons.report(self.log.rows_written, self.log.rows_flushed)
        if self.log.error:
            self.cons.set_error(self.log.error)
        _close_outputs(self.outputs)
        closed = {"rows_written": self.log.rows_written, "rows_flushed": self.log.rows_flushed,
                  "events_written": self.log.events_written, "error": self.log.error, "flushes": self.log.flushes}
        if not parent_gone and self.conn is not None:
            try:
                self.conn.send(("closed", closed))
            except (OSError, ValueError):
                pass
        self.cons.release()
        return closed
