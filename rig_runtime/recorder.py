"""Lossless cycle recorder, loop side: the loop appends a row per cycle and events; a
separate *sidecar* process (:mod:`rig_runtime.sidecar`) writes them to HDF5 and feeds the
live outputs — the same way in every mode.

``append`` never blocks, never does I/O, takes no lock and makes no system call: it packs
the row's floats with :func:`struct.Struct.pack_into` straight into a preallocated ring in
shared memory (:mod:`rig_runtime.ring`) and publishes a counter. A full ring (the sidecar
could not keep up, e.g. a stalled disk) is never waited on: the row is dropped, counted in
``rows_dropped``, and the recorder turns unhealthy with a cause naming the overflow (a
recorder fault for the supervisor) — unless the recorder was made with ``when_full="wait"``
for a lockstep run, where time does not matter and a lost row would break determinism.
Later rows are recorded again as soon as the sidecar
frees space (the ``t`` column then shows the gap). Events (state changes, faults, operator
actions) go through a second ring the same way.

Health: the sidecar reports the log's first error (a write failure, a full disk, the file
deleted while recording) through the shared header, read with one memory load per cycle;
that the sidecar process is still alive is checked every ``_ALIVE_EVERY`` reads (a
``waitpid`` without waiting).

The sidecar flushes (HDF5 flush + fsync) at least every ``min(flush_s, 1 s)``: after each
flush the file on disk is complete and readable up to that point, also if the runtime or
the machine dies afterwards. If the runtime process dies, the sidecar drains the ring,
records an event saying so and closes the log.

``writer="inline"`` (a lockstep run without live outputs, where time does not matter and a
campaign worker runs many runs): no process is started; the same :class:`~rig_runtime.sidecar.Sidecar`
writes the same ring into the same file from the loop's own process, every quarter ring (a
disk that refuses a write is the recorder's fault while the run goes on, as with the sidecar)
and at ``close`` (it flushes then, at most every ``flush_s``). No interpreter start and exit
per run; the log is the same.

File layout: see ``docs/log-format.md``.
"""

from __future__ import annotations

import atexit
import json
import math
import multiprocessing.connection
import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Mapping, Sequence

from . import ring
from .clock import as_background_process
from .errors import DeviceInitError
from .logformat import MIN_FREE_BYTES, check_attrs, check_columns     # no h5py: the sidecar writes the file
from .mailbox import Mailbox
from .sidecar import SidecarSpec, flush_period

_START_GRACE_S = 30.0       # interpreter start + imports on a loaded machine
_ALIVE_EVERY = 50           # health reads between two looks at the sidecar process


def _child_env() -> dict:
    """The sidecar imports this package from where this process did (also a checkout on sys.path)."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


class Recorder:
    """Record one row of floats per control cycle (plus events) into an HDF5 file.

    ``columns`` names the row's values in order (SI units; see ``docs/log-format.md``);
    ``attrs`` become root attributes (strings as UTF-8). The file must not exist yet: a log
    is never overwritten. ``outputs``: live outputs the sidecar feeds, as
    ``("package.module:Class", {options})`` (see :mod:`rig_runtime.sidecar`). ``cpus``: where
    the sidecar runs (:func:`rig_runtime.clock.helper_cpus`; None: wherever this process may).
    ``writer``: "sidecar" (a process of its own; every real-time run) or "inline" (see the
    module docstring; implies ``when_full="wait"``, no live outputs).
    """

    def __init__(self, path: str | Path, columns: Sequence[str], *, attrs: Mapping[str, object],
                 buffer_cycles: int = 4096, flush_s: float = 0.5, event_capacity: int = 1024,
                 min_free_bytes: int = MIN_FREE_BYTES, outputs: Sequence[tuple[str, dict]] = (),
                 when_full: str = "drop", cpus: Sequence[int] | None = None, writer: str = "sidecar"):
        self.path = Path(path)
        self.columns: tuple[str, ...] = check_columns(columns)
        self._attrs = check_attrs(attrs)
        if int(buffer_cycles) < 2:
            raise ValueError(f"recorder: buffer_cycles >= 2, got {buffer_cycles!r}")
        if not flush_s > 0:
            raise ValueError(f"recorder: flush_s > 0, got {flush_s!r}")
        if int(event_capacity) < 1:
            raise ValueError(f"recorder: event_capacity >= 1, got {event_capacity!r}")
        self.buffer_cycles = int(buffer_cycles)
        self.flush_s = float(flush_s)
        self.flush_period = flush_period(self.flush_s)
        self.event_capacity = int(event_capacity)
        self.min_free_bytes = int(min_free_bytes)
        self.outputs = tuple((str(n), dict(o)) for n, o in outputs)
        if when_full not in ("drop", "wait"):
            raise ValueError(f"recorder: when_full is 'drop' or 'wait', got {when_full!r}")
        self.when_full = when_full
        if writer not in ("sidecar", "inline"):
            raise ValueError(f"recorder: writer is 'sidecar' or 'inline', got {writer!r}")
        if writer == "inline" and (self.outputs or when_full != "wait"):
            raise ValueError("recorder: writer 'inline' is for lockstep runs: when_full='wait', no live outputs")
        self.writer = writer
        self._inline = None                 # writer "inline": the Sidecar this process drives
        self._next_flush = 0.0
        self.cpus = tuple(cpus) if cpus else None
        self._ncols = len(self.columns)
        self._prod: ring.Producer | None = None
        self._mm = None
        self._conn: multiprocessing.connection.Connection | None = None
        self.process: subprocess.Popen | None = None
        self._error = ""
        self._refuse = True                 # nothing accepted before open / after close
        self._dropped = 0
        self._ev_dropped = 0
        self._alive_countdown = _ALIVE_EVERY
        self._final: dict | None = None
        self._opened = False
        self._closed = False
        self._mailbox = None
        self.status_refused = 0             # status snapshots too large for the slot
        self.left_running = ""              # close(timeout) left the sidecar to close the log: why

    # ------------------------------------------------------------------ status
    @property
    def healthy(self) -> bool:
        """False after a write error, a buffer overflow (rows or events were lost) or the
        sidecar's death."""
        if self._error:
            return False
        p = self._prod
        if p is None:
            return True
        if p.has_sidecar_error():
            return False
        self._alive_countdown -= 1
        if self._alive_countdown <= 0:
            self._alive_countdown = _ALIVE_EVERY
            self._check_alive()
            return not self._error
        return True

    @property
    def error(self) -> str:
        """The first cause of unhealthiness; '' while healthy."""
        if self._error:
            return self._error
        if self._prod is not None:
            return self._prod.sidecar_error()
        return self._final.get("error", "") if self._final else ""

    def _fail(self, cause: str) -> None:
        if not self._error:
            self._error = cause

    def _check_alive(self) -> None:
        proc = self.process
        if proc is not None and not self._closed and proc.poll() is not None:
            self._fail(f"recorder sidecar process ended unexpectedly (exit code {proc.returncode}); "
                       f"file valid up to row {self.rows_flushed}")
            self._refuse = True

    @property
    def rows_written(self) -> int:
        """Rows stored in the HDF5 datasets so far (all of them after ``close``)."""
        if self._final is not None:
            return self._final.get("rows_written", 0)
        return self._prod.rows_written if self._prod is not None else 0

    @property
    def rows_flushed(self) -> int:
        """Rows durable in the file (written and flushed): what a crash now would leave."""
        if self._final is not None:
            return self._final.get("rows_flushed", 0)
        return self._prod.rows_flushed if self._prod is not None else 0

    @property
    def rows_dropped(self) -> int:
        """Rows ``append`` refused because the ring was full."""
        return self._dropped

    @property
    def events_dropped(self) -> int:
        return self._ev_dropped

    @property
    def pending(self) -> int:
        """Rows in the ring not yet taken by the sidecar (fill level)."""
        return self._prod.pending if self._prod is not None else 0

    @property
    def mailbox(self):
        """The operator mailbox in the shared memory (loop side), or None before ``open``."""
        if self._mailbox is None and self._prod is not None:
            self._mailbox = Mailbox(self._prod.mailbox_view())
        return self._mailbox

    # ------------------------------------------------------------------ open
    def open(self) -> None:
        """Start the sidecar; return once it has created the log (never overwriting one),
        else raise ``DeviceInitError`` naming the cause."""
        if self._opened:
            raise RuntimeError(f"recorder {self.path}: already opened")
        self._opened = True
        layout = ring.Layout(self._ncols, self.buffer_cycles, self.event_capacity)
        if self.writer == "inline":
            self._open_inline(layout)
            return
        try:
            path, self._mm = ring.create(layout)
        except OSError as e:
            raise DeviceInitError(f"recorder {self.path}", f"no shared memory for the recording ring "
                                  f"({layout.size} bytes in {ring.shm_dir()}): {e.strerror or e}") from None
        spec = SidecarSpec(str(self.path), self.columns, self._attrs, self.flush_s, self.min_free_bytes,
                           self.outputs)
        here, there = socket.socketpair()
        proc = None
        conn = multiprocessing.connection.Connection(here.detach())
        try:
            try:
                proc = subprocess.Popen(
                    [sys.executable, "-c", "from rig_runtime.sidecar import cli; cli()", str(there.fileno()), path],
                    # stdout: nothing (it prints only to stderr), so a reader of the runtime's
                    # output (``rig run --json | …``) is not held by a sidecar left to close the log
                    pass_fds=(there.fileno(),), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                    env=_child_env())
            finally:
                there.close()               # the child has its own copy: EOF for it once we are gone
            as_background_process(proc.pid, self.cpus)    # before the spec: the child has no thread yet
            conn.send(spec)
            msg = None
            deadline = time.monotonic() + _START_GRACE_S
            while msg is None and proc.poll() is None and time.monotonic() < deadline:
                if conn.poll(0.05):
                    try:
                        msg = conn.recv()
                    except (EOFError, OSError):
                        break
            if msg is None:
                try:
                    proc.wait(0.5)
                except subprocess.TimeoutExpired:
                    pass
                what = (f"exited with code {proc.returncode}" if proc.returncode is not None
                        else f"did not report within {_START_GRACE_S:g} s")
                raise DeviceInitError(f"recorder {self.path}", f"sidecar process {what} before creating the log")
            if msg[0] == "error":
                _, device, message, cause = msg
                raise DeviceInitError(device, message) from cause
        except BaseException:
            self._stop_process(proc, conn)
            self._release()
            try:
                os.unlink(path)             # the sidecar unlinks it once attached; else we do
            except OSError:
                pass
            self._closed = True
            raise
        self.process = proc
        self._conn = conn
        self._prod = ring.Producer(self._mm, layout)
        self._refuse = False
        atexit.register(self.close)

    def _open_inline(self, layout: ring.Layout) -> None:
        from .sidecar import open_log
        self._mm = ring.create_private(layout)
        spec = SidecarSpec(str(self.path), self.columns, self._attrs, self.flush_s, self.min_free_bytes, ())
        res = open_log(ring.Consumer(self._mm, layout), spec, None)
        if isinstance(res, tuple):
            self._release()
            self._closed = True
            _, device, message, cause = res
            raise DeviceInitError(device, message) from cause
        self._inline = res
        self._inline_batch = max(1, self.buffer_cycles // 4)
        self._next_flush = time.monotonic() + self.flush_period
        self._prod = ring.Producer(self._mm, layout)
        self._refuse = False
        atexit.register(self.close)

    def _drain_inline(self) -> None:
        now = time.monotonic()
        flush = now >= self._next_flush
        if flush:
            self._next_flush = now + self.flush_period
        self._inline.drain(flush)           # type: ignore[union-attr]

    # ------------------------------------------------------------------ loop side
    def append(self, row: Sequence[float]) -> bool:
        """Record one cycle: one number per column, in column order. Never blocks.

        Returns False if the row was not recorded (ring full — the recorder turns unhealthy —
        or the recorder is closed/failed). Raises ValueError for a row of the wrong length or
        with a non-number (a programming error, caught in tests).
        """
        if self._refuse:
            return False
        try:
            if self._prod.append(row):      # type: ignore[union-attr]
                if self._inline is not None and self._prod.pending >= self._inline_batch:   # type: ignore[union-attr]
                    self._drain_inline()    # written as the sidecar would: a failing disk is seen while running
                return True
            if self._inline is not None:
                self._drain_inline()
                if self._prod.append(row):  # type: ignore[union-attr]
                    return True
            elif self.when_full == "wait" and self._wait_for_room() and self._prod.append(row):  # type: ignore[union-attr]
                return True
        except struct.error as e:
            raise ValueError(f"recorder row: expected {self._ncols} numbers in column order {self.columns} ({e})") from None
        self._dropped += 1
        self._prod.count_dropped(self._dropped, self._ev_dropped)   # type: ignore[union-attr]
        self._fail(f"recorder buffer overflow: the sidecar fell behind, ring of {self.buffer_cycles} "
                   f"cycles full; {self._dropped} rows dropped")
        return False

    def _wait_for_room(self, limit_s: float = 30.0) -> bool:
        """``when_full="wait"`` (a lockstep run, where time does not matter): wait until the
        sidecar has taken a quarter of the ring; False if it died or took longer than ``limit_s``."""
        deadline = time.monotonic() + limit_s
        prod = self._prod
        while prod.pending > 3 * self.buffer_cycles // 4:      # type: ignore[union-attr]
            if self.process is None or self.process.poll() is not None or time.monotonic() > deadline:
                return False
            time.sleep(0.001)
        return True

    def event(self, t: float, kind: str, device: str = "", check: str = "", value: float = math.nan,
              limit: float = math.nan, message: str = "") -> None:
        """Record an event (state change, fault, operator action). Non-blocking."""
        if self._refuse:
            return
        ok = self._prod.event(t, kind, device, check, value, limit, message)     # type: ignore[union-attr]
        if not ok and self._inline is not None:
            self._drain_inline()
            ok = self._prod.event(t, kind, device, check, value, limit, message)  # type: ignore[union-attr]
        if not ok:
            self._ev_dropped += 1
            self._prod.count_dropped(self._dropped, self._ev_dropped)         # type: ignore[union-attr]
            self._fail(f"recorder event buffer overflow: {self.event_capacity} events pending; events dropped")

    def publish_status(self, status: dict) -> None:
        """Hand a status snapshot (JSON-able) to the sidecar's live outputs. One that does not
        fit the status slot is counted, and the first such is recorded as an event (the live
        views then show the last snapshot that fitted)."""
        if self._prod is not None and not self._refuse:
            data = json.dumps(status, default=str).encode()
            if not self._prod.publish_status(data):
                self.status_refused += 1
                if self.status_refused == 1:
                    self.event(status.get("t", math.nan), "recorder", "recorder", "status", len(data), math.nan,
                               f"status snapshot of {len(data)} bytes does not fit its slot: live views not updated")

    # ------------------------------------------------------------------ close
    def close(self, timeout: float | None = None) -> bool:
        """Let the sidecar drain the ring, write and flush everything and close the file;
        wait for it. Idempotent. Afterwards every row ``append`` accepted is in the file,
        unless the recorder is unhealthy. Returns whether the log is closed.

        ``timeout`` bounds the wait (None: wait). A sidecar still at work past it (a disk
        that does not answer: a write or fsync that blocks) is left running, not stopped: it
        has the close request and closes the log itself as soon as the disk answers (then
        it finds its socket closed and ends); ``left_running`` names it."""
        if self._closed:
            return self.left_running == ""
        self._closed = True
        self._refuse = True
        if self._inline is not None:
            self._final = self._inline.finish({"error": self._error})
            self._inline = None
            if self._final.get("error"):
                self._fail(self._final["error"])
            self._release()
            self._unregister()
            return True
        proc, conn = self.process, self._conn
        if conn is not None and proc is not None:
            try:
                conn.send(("close", {"error": self._error}))
            except (OSError, ValueError):
                pass
            try:
                if conn.poll(timeout):
                    msg = conn.recv()
                    if msg[0] == "closed":
                        self._final = msg[1]
            except (EOFError, OSError):
                pass
            if self._final is None and timeout is not None and proc.poll() is None:
                rows = self._prod.rows_flushed if self._prod is not None else 0
                self.left_running = (f"the recording sidecar (pid {proc.pid}) did not close the log within "
                                     f"{timeout:g} s (its disk does not answer); it closes {self.path} when "
                                     f"the disk answers (now valid up to row {rows})")
                self._final = {"rows_written": self._prod.rows_written if self._prod is not None else 0,
                               "rows_flushed": rows}
                conn.close()                # the sidecar reads its close request, then this EOF
                self._release()
                self._unregister()
                return False
            if self._final is None:
                rows = self._prod.rows_flushed if self._prod is not None else 0
                self._fail(f"recorder sidecar did not close the log (exit code {proc.poll()}); "
                           f"file valid up to row {rows}")
                self._final = {"rows_written": rows, "rows_flushed": rows}
        if self._final is not None and self._final.get("error"):
            self._fail(self._final["error"])
        self._stop_process(proc, conn)
        self._release()
        self._unregister()
        return True

    def _unregister(self) -> None:
        try:
            atexit.unregister(self.close)
        except Exception:  # noqa: BLE001
            pass

    @staticmethod
    def _stop_process(proc: subprocess.Popen | None, conn) -> None:
        if conn is not None:
            conn.close()                    # EOF for a sidecar that has not finished yet
        if proc is not None:
            for stop in (None, proc.terminate, proc.kill):
                if stop is not None:
                    stop()
                try:
                    proc.wait(10.0 if stop is None else 2.0)
                    break
                except subprocess.TimeoutExpired:
                    pass

    def _release(self) -> None:
        self._mailbox = None
        if self._prod is not None:
            self._prod.release()
            self._prod = None
        if self._mm is not None:
            try:
                self._mm.close()
            except BufferError:             # a view is still exported somewhere: leave it to the GC
                pass
            self._mm = None

    def __enter__(self) -> "Recorder":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else ("open" if self._opened else "new")
        return (f"Recorder({str(self.path)!r}, {len(self.columns)} columns, {state}, "
                f"rows_written={self.rows_written}, healthy={self.healthy})")
