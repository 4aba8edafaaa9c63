"""Lossless cycle recorder: the loop appends a row per cycle, a writer thread stores it in HDF5
(the same way in every mode).

Loop side (``append``, ``event``) never blocks, never does file I/O (thread mode) and allocates nothing
per row beyond the call's own argument tuple: ``append`` packs the row's floats with :func:`struct.Struct.pack_into` straight into
a preallocated ``numpy`` ring of ``buffer_cycles`` rows and advances a counter. Measured
(``tests/test_recorder.py::test_append_cost``, timeit, warm cache): ≈0.4 µs for 8 columns,
≈0.5–1.2 µs for 24, ≈1.5 µs for 48 on the 2-CPU development machine; the first call after
the loop's sleep runs with cold caches and costs more (10–25 µs p50 measured there under
load, against ≈3 µs for an empty call in the same spot).

Hand-off (single producer = the loop thread, single consumer = the writer thread)
--------------------------------------------------------------------------------
Two monotonically increasing ints are the only shared state of the row ring:

* ``_w`` — rows appended; written only by the loop thread, *after* the row's bytes are in
  the ring. Slot of row ``k`` is ``k % buffer_cycles``.
* ``_r`` — rows the writer has taken; written only by the writer thread, *after* it has
  copied their slots out of the ring (into its own block, which it then writes to HDF5).

Rebinding an attribute to an int is a single atomic store under CPython's GIL, and the GIL
hand-over between threads is a full memory barrier, so a reader of ``_w`` sees every byte
written before it was published (and the loop never overwrites a slot the writer has not
released: the ring is full when ``_w - _r == buffer_cycles``). Counters instead of wrapped
indices mean "full" and "empty" cannot be confused. There is no lock on the row path.

A full ring (the writer could not keep up, e.g. a stalled disk) is never waited on:
``append`` drops the row, returns ``False``, counts it in ``rows_dropped`` and the
recorder turns unhealthy with a cause naming the overflow. Later rows are recorded again as
soon as the writer frees space (the ``t`` column then shows the gap).

Events (state changes, faults, operator actions) are rare and may come from more than one
thread, so they go through a ``collections.deque`` (whose ``append``/``popleft`` are
documented thread-safe and atomic) bounded by ``event_capacity``.

Writer side
-----------
The writer thread wakes every ``_POLL_S`` (25 ms) and moves the pending rows and events
into the file when a flush is due (every ``min(flush_s, 1 s)``: "flushed at least once a
second"), when the ring is a quarter full, or on ``close``. Writing in batches (≈100 rows per
flush at 200 Hz) keeps the number of HDF5 calls — each of which holds the interpreter lock —
small (≈3 ms of writer time per batch of 100 rows × 24 columns measured); between column
writes the writer yields the GIL (``time.sleep(0)``), so a loop thread that wakes up waits
for at most one HDF5 call (tens of µs), not for a whole batch. After every successful flush the file on disk is
complete, fsynced and readable up to that point, also if the process or the machine dies
afterwards. A log file deleted while recording is noticed at the next flush (a recorder fault).

Before each batch the writer checks the free disk space; below ``min_free_bytes`` it stops
cleanly (unhealthy, file valid up to the last flush). Any exception while writing
(``OSError`` of a failing disk, an h5py error) makes the recorder unhealthy with the cause;
the writer then stops writing, trims the datasets back to the last flushed length and
flushes that; if even this fails, the file descriptor is pointed at /dev/null so that
closing writes nothing more to the failing device.

File layout: see ``docs/log-format.md``.
"""

from __future__ import annotations

import atexit
import collections
import datetime as _dt
import json
import math
import os
import shutil
import struct
import threading
import time
from pathlib import Path
from typing import Mapping, Sequence

import h5py
import numpy as np
from h5py import h5s

from .clock import as_background_thread
from .errors import DeviceInitError

LOG_FORMAT = "rig-runtime-log"
LOG_FORMAT_VERSION = 1

EVENT_FIELDS = ("t", "kind", "device", "check", "value", "limit", "message")
EVENT_STR_FIELDS = ("kind", "device", "check", "message")
EVENT_NUM_FIELDS = ("t", "value", "limit")

#: root attributes the recorder writes itself (the caller's ``attrs`` must not use them)
RESERVED_ATTRS = frozenset({
    "columns", "log_format", "log_format_version", "recorder_opened", "recorder_closed",
    "rows_written", "rows_dropped", "events_written", "events_dropped", "recorder_error",
})

_POLL_S = 0.025            # writer wake-up period
_MAX_FLUSH_S = 1.0         # documented guarantee: flushed at least once a second
_CHUNK_ROWS = 1024         # cycles per HDF5 chunk (8 KiB per column; 5.1 s at 200 Hz)
_EVENT_CHUNK = 64
_STR = h5py.string_dtype("utf-8")


def _utc_now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _attr_value(key: str, v: object) -> object:
    """Convert a caller attribute to something HDF5 stores portably (MATLAB-readable)."""
    if isinstance(v, str):
        return v
    if isinstance(v, (bool, np.bool_)):
        return np.int8(bool(v))                     # HDF5 has no bool; h5py's enum confuses MATLAB
    if isinstance(v, (int, np.integer)):
        return np.int64(v)
    if isinstance(v, (float, np.floating)):
        return np.float64(v)
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, (_dt.datetime, _dt.date)):
        return v.isoformat()
    if isinstance(v, (list, tuple)) and v:
        if all(isinstance(x, str) for x in v):
            return np.array(v, dtype=_STR)
        if all(isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) for x in v):
            return np.asarray(v, dtype=np.float64)
    try:
        return json.dumps(v)                        # mappings, None, mixed lists: as JSON text
    except (TypeError, ValueError) as e:
        raise TypeError(f"recorder attribute {key!r}: cannot store a {type(v).__name__} ({e})") from None


class Recorder:
    """Record one row of floats per control cycle (plus events) into an HDF5 file.

    ``columns`` names the row's values in order (SI units; see ``docs/log-format.md``);
    ``attrs`` become root attributes (strings as UTF-8). The file must not exist yet:
    a log is never overwritten. A background writer thread does all file I/O; ``append``
    never does.
    """

    def __init__(self, path: str | Path, columns: Sequence[str], *, attrs: Mapping[str, object],
                 buffer_cycles: int = 4096, flush_s: float = 0.5, event_capacity: int = 1024,
                 min_free_bytes: int = 32 * 2**20):
        self.path = Path(path)
        cols = tuple(columns)
        if not cols:
            raise ValueError("recorder: at least one column")
        for c in cols:
            if not isinstance(c, str) or not c or "/" in c or c in (".", "..") or c != c.strip():
                raise ValueError(f"recorder: invalid column name {c!r} (non-empty, no '/', no surrounding blanks)")
        dup = sorted({c for c in cols if cols.count(c) > 1})
        if dup:
            raise ValueError(f"recorder: duplicate column names {dup}")
        if int(buffer_cycles) < 2:
            raise ValueError(f"recorder: buffer_cycles >= 2, got {buffer_cycles!r}")
        if not flush_s > 0:
            raise ValueError(f"recorder: flush_s > 0, got {flush_s!r}")
        if int(event_capacity) < 1:
            raise ValueError(f"recorder: event_capacity >= 1, got {event_capacity!r}")
        self.columns: tuple[str, ...] = cols
        self._attrs: dict[str, object] = {}
        for k, v in attrs.items():
            if not isinstance(k, str) or not k or "/" in k:
                raise ValueError(f"recorder: invalid attribute name {k!r}")
            if k in RESERVED_ATTRS:
                raise ValueError(f"recorder: attribute name {k!r} is reserved for the recorder")
            self._attrs[k] = _attr_value(k, v)
        self.buffer_cycles = int(buffer_cycles)
        self.flush_s = float(flush_s)
        self.flush_period = min(self.flush_s, _MAX_FLUSH_S)
        self.event_capacity = int(event_capacity)
        self.min_free_bytes = int(min_free_bytes)

        n = len(cols)
        self._ncols = n
        # ring and the loop-side constants, all preallocated
        self._buf = np.full((self.buffer_cycles, n), np.nan)
        self._cap = self.buffer_cycles
        self._room = self.buffer_cycles     # set to 0 once no more rows are accepted (closed / writer dead)
        self._rowbytes = 8 * n
        self._pack = struct.Struct(f"={n}d").pack_into
        self._w = 0                         # rows appended (loop thread only)
        self._r = 0                         # rows stored (writer thread only)
        self._dropped = 0
        self._ev: collections.deque = collections.deque()
        self._ev_dropped = 0

        self._error = ""
        self._refuse = False                # loop side: accept no more rows/events (closed or writer dead)
        self._dead = False                  # writer side: a write failed, nothing more is written
        self._rows_written = 0
        self._rows_flushed = 0
        self._frozen = False
        self._events_written = 0
        self._events_flushed = 0
        self.flushes = 0                    # successful flushes (diagnostics, tests)

        self._file: h5py.File | None = None
        self._cyc: list[h5py.Dataset] = []
        self._evds: dict[str, h5py.Dataset] = {}
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._opened = False
        self._closed = False
        self._close_lock = threading.Lock()

    # ------------------------------------------------------------------ status
    @property
    def healthy(self) -> bool:
        """False after a write error or a buffer overflow (rows or events were lost)."""
        return not self._error

    @property
    def error(self) -> str:
        """The first cause of unhealthiness; '' while healthy."""
        return self._error

    @property
    def rows_written(self) -> int:
        """Rows stored in the HDF5 datasets so far (all of them after ``close``)."""
        return self._rows_written

    @property
    def rows_flushed(self) -> int:
        """Rows durable in the file (written and flushed): what a crash now would leave."""
        return self._rows_flushed

    @property
    def rows_dropped(self) -> int:
        """Rows ``append`` refused because the ring was full."""
        return self._dropped

    @property
    def events_dropped(self) -> int:
        return self._ev_dropped

    @property
    def pending(self) -> int:
        """Rows in the ring not yet stored (fill level)."""
        return self._w - self._r

    def _fail(self, cause: str) -> None:
        if not self._error:
            self._error = cause

    # ------------------------------------------------------------------ open
    def open(self) -> None:
        """Create the file (never overwriting one), write the attributes, start the writer."""
        if self._opened:
            raise RuntimeError(f"recorder {self.path}: already opened")
        dev = f"recorder {self.path}"
        try:
            free = shutil.disk_usage(self.path.parent).free
        except OSError:
            free = None                             # missing directory: reported by the create below
        if free is not None and free < self.min_free_bytes:
            raise DeviceInitError(dev, f"disk almost full ({free / 2**20:.1f} MiB free, "
                                       f"need {self.min_free_bytes / 2**20:.0f} MiB)")
        try:
            # 'x': fail if it exists; default libver -> HDF5 1.8 readable. The chunk cache is
            # per dataset and 1 MiB by default: with ~90 columns it grew the process by ~90 MB
            # over the first ten minutes of a run. Writing is append-only, so two chunks do.
            f = h5py.File(self.path, "x", rdcc_nbytes=2 * _CHUNK_ROWS * 8, rdcc_nslots=7)
        except FileExistsError as e:
            raise DeviceInitError(dev, "log file exists already (logs are never overwritten)") from e
        except (OSError, ValueError) as e:
            raise DeviceInitError(dev, f"cannot create log file: {e}") from e
        try:
            for k, v in self._attrs.items():
                f.attrs[k] = v
            f.attrs["columns"] = np.array(self.columns, dtype=_STR)
            f.attrs["log_format"] = LOG_FORMAT
            f.attrs["log_format_version"] = np.int64(LOG_FORMAT_VERSION)
            f.attrs["recorder_opened"] = _utc_now_iso()
            g = f.create_group("cycles")
            g.attrs["columns"] = np.array(self.columns, dtype=_STR)
            self._cyc = []
            for i, c in enumerate(self.columns):
                d = g.create_dataset(c, shape=(0,), maxshape=(None,), chunks=(_CHUNK_ROWS,),
                                     dtype="f8", fillvalue=np.nan)
                d.attrs["index"] = np.int64(i)
                self._cyc.append(d)
            e = f.create_group("events")
            self._evds = {}
            for name in EVENT_FIELDS:
                if name in EVENT_STR_FIELDS:
                    self._evds[name] = e.create_dataset(name, shape=(0,), maxshape=(None,),
                                                        chunks=(_EVENT_CHUNK,), dtype=_STR)
                else:
                    self._evds[name] = e.create_dataset(name, shape=(0,), maxshape=(None,),
                                                        chunks=(_EVENT_CHUNK,), dtype="f8", fillvalue=np.nan)
            f.flush()
        except Exception as exc:  # noqa: BLE001 - any failure here is an init failure of the log
            try:
                f.close()
            finally:
                try:
                    os.unlink(self.path)            # we created it (mode 'x'); it is empty
                except OSError:
                    pass
            raise DeviceInitError(dev, f"cannot initialise log file: {exc}") from exc
        self._file = f
        self._opened = True
        self._thread = threading.Thread(target=self._run, name=f"recorder:{self.path.name}", daemon=True)
        self._thread.start()
        atexit.register(self.close)

    # ------------------------------------------------------------------ loop side
    def append(self, row: Sequence[float]) -> bool:
        """Record one cycle: one number per column, in column order. Never blocks.

        Returns False if the row was not recorded (ring full — the recorder turns unhealthy —
        or the recorder is closed/failed). Raises ValueError for a row of the wrong length or
        with a non-number (a programming error, caught in tests).
        """
        w = self._w
        if w - self._r >= self._room:
            return self._reject()
        try:
            self._pack(self._buf, (w % self._cap) * self._rowbytes, *row)
        except struct.error as e:
            raise ValueError(f"recorder row: expected {self._ncols} numbers in column order {self.columns} ({e})") from None
        self._w = w + 1                   # publish: the writer may now read slot w
        return True

    def _reject(self) -> bool:
        if self._refuse:
            return False
        self._dropped += 1
        if not self._error:
            self._error = (f"recorder buffer overflow: the writer fell behind, ring of {self._cap} "
                           f"cycles full at row {self._w + self._dropped - 1}; rows dropped")
        return False

    def event(self, t: float, kind: str, device: str = "", check: str = "", value: float = math.nan,
              limit: float = math.nan, message: str = "") -> None:
        """Record an event (state change, fault, operator action). Non-blocking, thread-safe."""
        if self._refuse:
            return
        ev = self._ev
        if len(ev) >= self.event_capacity:
            self._ev_dropped += 1
            if not self._error:
                self._error = f"recorder event buffer overflow: {self.event_capacity} events pending; events dropped"
            return
        ev.append((t, kind, device, check, value, limit, message))

    # ------------------------------------------------------------------ writer side
    def _run(self) -> None:
        as_background_thread()          # the loop (SCHED_FIFO) must preempt the writer
        next_flush = time.monotonic() + self.flush_period
        while True:
            closing = self._stop.wait(_POLL_S)
            now = time.monotonic()
            flush_due = now >= next_flush
            if flush_due:
                next_flush = now + self.flush_period
            if not self._dead and (closing or flush_due or self._w - self._r >= self._cap // 4
                                   or len(self._ev) >= self.event_capacity // 4):
                self._service(flush=closing or flush_due)
            if closing:
                break
        self._finish()

    def _service(self, flush: bool) -> None:
        try:
            if self._disk_low():
                return
            self._write_pending()
            if flush:
                self._flush()
        except Exception as e:  # noqa: BLE001 - every write failure is reported the same way
            self._on_write_error(e)

    def _write_pending(self) -> None:
        # events first: cheap, and a fault event should not wait behind rows
        ev = self._ev
        m = len(ev)
        if m:
            items = [ev.popleft() for _ in range(m)]
            self._write_events(items)
        w = self._w                       # snapshot; rows beyond it are left for the next pass
        r = self._r
        n = w - r
        if n <= 0:
            return
        cap = self._cap
        i0 = r % cap
        if i0 + n <= cap:
            block = self._buf[i0:i0 + n].T.copy()
        else:
            block = np.concatenate((self._buf[i0:], self._buf[:i0 + n - cap])).T.copy()
        self._r = w                       # slots copied: release them to the loop
        start = self._rows_written
        end = start + n
        for j, d in enumerate(self._cyc):
            self._store_column(d, start, block[j])
            time.sleep(0)                 # offer the GIL to the loop between HDF5 calls
        self._rows_written = end

    @staticmethod
    def _store_column(d: h5py.Dataset, start: int, data: np.ndarray) -> None:
        """Extend a 1-D float64 dataset by ``data`` (contiguous) at ``start``.

        Low-level h5py calls: about 3x cheaper than ``d.resize(); d[a:b] = data`` (≈30 µs
        instead of ≈100 µs per column and batch), and the writer holds the GIL for less time.
        """
        n = data.shape[0]
        d.id.set_extent((start + n,))
        fspace = d.id.get_space()
        fspace.select_hyperslab((start,), (n,))
        d.id.write(h5s.create_simple((n,)), fspace, data)

    def _write_events(self, items: list[tuple]) -> None:
        cols: dict[str, list] = {k: [] for k in EVENT_FIELDS}
        for it in items:
            for k, v in zip(EVENT_FIELDS, it):
                if k in EVENT_STR_FIELDS:
                    cols[k].append(v if isinstance(v, str) else str(v))
                else:
                    try:
                        cols[k].append(float(v))
                    except (TypeError, ValueError):
                        cols[k].append(math.nan)
        start = self._events_written
        end = start + len(items)
        for k, d in self._evds.items():
            d.resize((end,))
            if k in EVENT_STR_FIELDS:
                d[start:end] = np.array(cols[k], dtype=object)
            else:
                d[start:end] = np.array(cols[k], dtype=np.float64)
        self._events_written = end

    def _flush(self) -> None:
        if self._rows_written == self._rows_flushed and self._events_written == self._events_flushed:
            return                        # nothing new: the file on disk is already current
        assert self._file is not None
        self._file.flush()
        fd = self._file.id.get_vfd_handle()
        os.fsync(fd)                      # durable: survives a crash of the machine, not just of the process
        if os.fstat(fd).st_nlink == 0:
            raise FileNotFoundError(f"the log file {self.path} was deleted while recording")
        self._rows_flushed = self._rows_written
        self._events_flushed = self._events_written
        self.flushes += 1

    def _on_write_error(self, e: BaseException) -> None:
        self._fail(f"recorder write failed ({type(e).__name__}: {e}); recording stopped, "
                   f"file valid up to row {self._rows_flushed}")
        self._stop_writing()

    def _stop_writing(self) -> None:
        """After a failure: accept nothing more and bring the file back to the last flush.

        The extents are trimmed to what the last successful flush made durable and flushed
        once more, so that closing publishes no half-written rows. If even that fails (the
        device itself is failing), the file's descriptor is pointed at /dev/null so that
        closing cannot write anything more to the device ("freeze").
        """
        self._dead = True
        self._refuse = True
        self._room = 0
        try:
            for d in self._cyc:
                if d.shape[0] != self._rows_flushed:
                    d.id.set_extent((self._rows_flushed,))
            for d in self._evds.values():
                if d.shape[0] != self._events_flushed:
                    d.id.set_extent((self._events_flushed,))
            assert self._file is not None
            self._file.flush()
        except Exception:  # noqa: BLE001 - the device is failing: stop touching it
            self._freeze()
        self._rows_written = self._rows_flushed
        self._events_written = self._events_flushed

    def _freeze(self) -> None:
        try:
            assert self._file is not None
            fd = self._file.id.get_vfd_handle()
            nul = os.open(os.devnull, os.O_RDWR)
            try:
                os.dup2(nul, fd)
            finally:
                os.close(nul)
            self._frozen = True
        except Exception:  # noqa: BLE001
            pass

    def _disk_low(self) -> bool:
        """True (and unhealthy, writer stopped cleanly) when free space fell below the margin."""
        try:
            free = shutil.disk_usage(self.path.parent).free
        except OSError:
            return False
        if free >= self.min_free_bytes:
            return False
        self._fail(f"recorder stopped: disk almost full ({free / 2**20:.1f} MiB free on {self.path.parent}, "
                   f"margin {self.min_free_bytes / 2**20:.0f} MiB); file valid up to row {self._rows_flushed}")
        self._stop_writing()
        return True

    def _finish(self) -> None:
        """Writer thread, last: final attributes, close the file."""
        f = self._file
        if f is None:
            return
        if not self._dead:
            try:
                f.attrs["recorder_closed"] = _utc_now_iso()
                f.attrs["rows_written"] = np.int64(self._rows_written)
                f.attrs["rows_dropped"] = np.int64(self._dropped)
                f.attrs["events_written"] = np.int64(self._events_written)
                f.attrs["events_dropped"] = np.int64(self._ev_dropped)
                f.attrs["recorder_error"] = self._error
            except Exception as e:  # noqa: BLE001
                self._on_write_error(e)
        self._cyc = []                    # drop our dataset handles before the file goes
        self._evds = {}
        try:
            f.close()
        except Exception as e:  # noqa: BLE001
            if not self._frozen:
                self._fail(f"recorder close failed ({type(e).__name__}: {e}); "
                           f"file valid up to row {self._rows_flushed}")
        self._file = None

    # ------------------------------------------------------------------ close
    def close(self, timeout: float | None = None) -> None:
        """Drain the ring, write and flush everything, close the file. Idempotent.

        Call it after the loop has stopped appending (an ``append`` racing with ``close``
        may be lost). Afterwards every row ``append`` accepted is in the file, unless the
        recorder is unhealthy. ``timeout`` bounds the wait for the writer (None: wait).
        """
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        self._refuse = True               # refuse rows/events from now on (without marking unhealthy)
        self._room = 0
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout)
            if self._thread.is_alive():
                self._fail(f"recorder close timed out after {timeout} s; file valid up to row {self._rows_flushed}")
        try:
            atexit.unregister(self.close)
        except Exception:  # noqa: BLE001
            pass

    def __enter__(self) -> "Recorder":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else ("open" if self._opened else "new")
        return (f"Recorder({str(self.path)!r}, {len(self.columns)} columns, {state}, "
                f"rows_written={self._rows_written}, healthy={self.healthy})")
