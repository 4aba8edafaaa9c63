"""The HDF5 log file: create it, append cycle rows and events, flush durably, close.

Synchronous and single-threaded: the recording sidecar (:mod:`rig_runtime.sidecar`) is its
only user while a run records. Layout: ``docs/log-format.md``.

Durability: after every successful :meth:`LogFile.flush` the file on disk is complete,
fsynced and readable up to that point, also if the process or the machine dies afterwards.
A log file deleted while recording is noticed at the next flush. Before each batch the free
disk space is checked; below ``min_free_bytes`` the writer stops cleanly. Any exception while
writing makes the log *dead*: the datasets are trimmed back to the last flushed length and
flushed; if even that fails, the file's descriptor is pointed at /dev/null so that closing
writes nothing more to the failing device. ``error`` then names the first cause.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import shutil
from pathlib import Path
from typing import Mapping, Sequence

import h5py
import numpy as np
from h5py import h5s

from .errors import DeviceInitError
from .logformat import (EVENT_FIELDS, EVENT_STR_FIELDS, LOG_FORMAT, LOG_FORMAT_VERSION, MIN_FREE_BYTES,
                        check_columns)

_CHUNK_ROWS = 1024         # cycles per HDF5 chunk (8 KiB per column; 5.1 s at 200 Hz)
_EVENT_CHUNK = 64
_STR = h5py.string_dtype("utf-8")


def utc_now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _h5_attr(v: object) -> object:
    if isinstance(v, list):
        return np.array(v, dtype=_STR) if v and isinstance(v[0], str) else np.asarray(v, dtype=np.float64)
    return v


class LogFile:
    """One HDF5 log being written (never overwriting an existing file)."""

    def __init__(self, path: str | Path, columns: Sequence[str], attrs: Mapping[str, object],
                 min_free_bytes: int = MIN_FREE_BYTES):
        self.path = Path(path)
        self.columns = check_columns(columns)
        self.attrs = dict(attrs)
        self.min_free_bytes = int(min_free_bytes)
        self.error = ""
        self.dead = False
        self.rows_written = 0
        self.rows_flushed = 0
        self.events_written = 0
        self.events_flushed = 0
        self.flushes = 0
        self._frozen = False
        self._file: h5py.File | None = None
        self._cyc: list[h5py.Dataset] = []
        self._evds: dict[str, h5py.Dataset] = {}

    def fail(self, cause: str) -> None:
        """Record ``cause`` as the log's error unless one is recorded already."""
        if not self.error:
            self.error = cause

    # ------------------------------------------------------------------ create
    def create(self) -> None:
        """Create the file with its attributes and empty datasets; ``DeviceInitError`` naming
        the log on any failure (no file is left behind)."""
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
            for k, v in self.attrs.items():
                f.attrs[k] = _h5_attr(v)
            f.attrs["columns"] = np.array(self.columns, dtype=_STR)
            f.attrs["log_format"] = LOG_FORMAT
            f.attrs["log_format_version"] = np.int64(LOG_FORMAT_VERSION)
            f.attrs["recorder_opened"] = utc_now_iso()
            g = f.create_group("cycles")
            g.attrs["columns"] = np.array(self.columns, dtype=_STR)
            for i, c in enumerate(self.columns):
                d = g.create_dataset(c, shape=(0,), maxshape=(None,), chunks=(_CHUNK_ROWS,),
                                     dtype="f8", fillvalue=np.nan)
                d.attrs["index"] = np.int64(i)
                self._cyc.append(d)
            e = f.create_group("events")
            for name in EVENT_FIELDS:
                if name in EVENT_STR_FIELDS:
                    self._evds[name] = e.create_dataset(name, shape=(0,), maxshape=(None,),
                                                        chunks=(_EVENT_CHUNK,), dtype=_STR)
                else:
                    self._evds[name] = e.create_dataset(name, shape=(0,), maxshape=(None,),
                                                        chunks=(_EVENT_CHUNK,), dtype="f8", fillvalue=np.nan)
            f.flush()
        except Exception as exc:  # noqa: BLE001 - any failure here is an init failure of the log
            self._cyc, self._evds = [], {}
            try:
                f.close()
            finally:
                try:
                    os.unlink(self.path)            # we created it (mode 'x'); it is empty
                except OSError:
                    pass
            raise DeviceInitError(dev, f"cannot initialise log file: {exc}") from exc
        self._file = f

    # ------------------------------------------------------------------ write
    def write(self, block: np.ndarray | None, events: Sequence[tuple], flush: bool) -> None:
        """Append ``block`` (rows × columns) and ``events``; flush if asked. Failures make
        the log dead (see the module docstring); nothing raises."""
        if self.dead:
            return
        try:
            if self._disk_low():
                return
            if events:
                self._write_events(events)  # events first: cheap, and a fault event should not wait behind rows
            if block is not None and len(block):
                self._write_rows(block)
            if flush:
                self.flush()
        except Exception as e:  # noqa: BLE001 - every write failure is reported the same way
            self.fail(f"recorder write failed ({type(e).__name__}: {e}); recording stopped, "
                       f"file valid up to row {self.rows_flushed}")
            self._stop_writing()

    def _write_rows(self, block: np.ndarray) -> None:
        cols = np.ascontiguousarray(block.T)
        start = self.rows_written
        for j, d in enumerate(self._cyc):
            self.store_column(d, start, cols[j])
        self.rows_written = start + block.shape[0]

    @staticmethod
    def store_column(d: h5py.Dataset, start: int, data: np.ndarray) -> None:
        """Extend a 1-D float64 dataset by ``data`` (contiguous) at ``start``.

        Low-level h5py calls: about 3x cheaper than ``d.resize(); d[a:b] = data``."""
        n = data.shape[0]
        d.id.set_extent((start + n,))
        fspace = d.id.get_space()
        fspace.select_hyperslab((start,), (n,))
        d.id.write(h5s.create_simple((n,)), fspace, data)

    def _write_events(self, items: Sequence[tuple]) -> None:
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
        start = self.events_written
        end = start + len(items)
        for k, d in self._evds.items():
            d.resize((end,))
            if k in EVENT_STR_FIELDS:
                d[start:end] = np.array(cols[k], dtype=object)
            else:
                d[start:end] = np.array(cols[k], dtype=np.float64)
        self.events_written = end

    def flush(self) -> None:
        """Make everything written durable (HDF5 flush + fsync); raises on failure."""
        if self.rows_written == self.rows_flushed and self.events_written == self.events_flushed:
            return                        # nothing new: the file on disk is already current
        assert self._file is not None
        self._file.flush()
        fd = self._file.id.get_vfd_handle()
        os.fsync(fd)                      # durable: survives a crash of the machine, not just of the process
        if os.fstat(fd).st_nlink == 0:
            raise FileNotFoundError(f"the log file {self.path} was deleted while recording")
        self.rows_flushed = self.rows_written
        self.events_flushed = self.events_written
        self.flushes += 1

    def _stop_writing(self) -> None:
        """After a failure: write nothing more and bring the file back to the last flush."""
        self.dead = True
        try:
            for d in self._cyc:
                if d.shape[0] != self.rows_flushed:
                    d.id.set_extent((self.rows_flushed,))
            for d in self._evds.values():
                if d.shape[0] != self.events_flushed:
                    d.id.set_extent((self.events_flushed,))
            assert self._file is not None
            self._file.flush()
        except Exception:  # noqa: BLE001 - the device is failing: stop touching it
            self._freeze()
        self.rows_written = self.rows_flushed
        self.events_written = self.events_flushed

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
        try:
            free = shutil.disk_usage(self.path.parent).free
        except OSError:
            return False
        if free >= self.min_free_bytes:
            return False
        self.fail(f"recorder stopped: disk almost full ({free / 2**20:.1f} MiB free on {self.path.parent}, "
                   f"margin {self.min_free_bytes / 2**20:.0f} MiB); file valid up to row {self.rows_flushed}")
        self._stop_writing()
        return True

    # ------------------------------------------------------------------ close
    def close(self, final_attrs: Mapping[str, object]) -> None:
        """Write the closing attributes (unless dead) and close the file. Never raises."""
        f = self._file
        if f is None:
            return
        if not self.dead:
            try:
                f.attrs["recorder_closed"] = utc_now_iso()
                f.attrs["rows_written"] = np.int64(self.rows_written)
                f.attrs["events_written"] = np.int64(self.events_written)
                for k, v in final_attrs.items():
                    f.attrs[k] = v
                f.attrs["recorder_error"] = self.error
            except Exception as e:  # noqa: BLE001
                self.fail(f"recorder close failed ({type(e).__name__}: {e}); file valid up to row {self.rows_flushed}")
                self._stop_writing()
        self._cyc = []                    # drop our dataset handles before the file goes
        self._evds = {}
        try:
            f.close()
        except Exception as e:  # noqa: BLE001
            if not self._frozen:
                self.fail(f"recorder close failed ({type(e).__name__}: {e}); "
                           f"file valid up to row {self.rows_flushed}")
        self._file = None
