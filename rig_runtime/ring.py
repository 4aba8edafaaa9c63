"""The shared memory between the loop's process and the recording sidecar.

One file mapping (on ``/dev/shm`` where there is one) holds, in this order: a header of
64-bit counters, the sidecar's error text, the loop's status snapshot, the operator
mailbox's region, the event ring and the row ring. The sidecar maps it and unlinks the
file at once, so nothing is left in ``/dev/shm`` however the run ends.

Rings (single producer = the loop, single consumer = the sidecar). Two monotonically
increasing counters per ring are the only shared state: ``W`` (items published, written
only by the loop, *after* the item's bytes are in its slot) and ``R`` (items taken,
written only by the sidecar, *after* it has copied their slots out). Slot of item ``k`` is
``k % capacity``; the ring is full when ``W - R == capacity``. Counters instead of wrapped
indices mean "full" and "empty" cannot be confused; neither side ever waits for the other
or takes a lock. Each counter is an aligned 8-byte store (a ``memoryview`` of format ``q``),
and x86-64 — the rig PC — does not reorder a store with earlier stores nor a load with
earlier loads, so a reader that sees ``W`` advanced sees the item's bytes. (On a weakly
ordered CPU this hand-off would need a checksum like the seqlock's.)

The status snapshot (a few hundred bytes of JSON, a few times a second, at most
``Layout.status_bytes``) is one seqlock slot (:mod:`rig_runtime.seqlock` has the protocol)
at the start of the status region: written by the loop, read by the sidecar.
"""

from __future__ import annotations

import mmap
import os
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import mailbox, seqlock

MAGIC = 0x52494752494E4732          # "RIGRING2" (2: the status seqlock moved into its region)
# header slots (int64 each)
_MAGIC, _NCOLS, _CAP, _EVCAP, _W, _R, _EW, _ER, _ERR_LEN, \
    _ROWS_WRITTEN, _ROWS_FLUSHED, _DROPPED, _EV_DROPPED, _STATUS_BYTES, _MAILBOX_BYTES = range(15)
HEADER_SLOTS = 32
ERROR_BYTES = 1024
KIND_B, DEVICE_B, CHECK_B, MESSAGE_B = 16, 64, 64, 512
_EVENT = struct.Struct(f"<3d4H{KIND_B}s{DEVICE_B}s{CHECK_B}s{MESSAGE_B}s")
EVENT_SLOT = (_EVENT.size + 7) // 8 * 8


def _align(n: int) -> int:
    return (n + 63) // 64 * 64


@dataclass(frozen=True)
class Layout:
    """Sizes and byte offsets of one shared block."""

    ncols: int
    capacity: int                  # rows
    event_capacity: int
    status_bytes: int = 16384     # the status snapshot's largest payload
    mailbox_bytes: int = mailbox.SIZE

    @property
    def error_at(self) -> int:
        return HEADER_SLOTS * 8

    @property
    def status_at(self) -> int:
        return _align(self.error_at + ERROR_BYTES)

    @property
    def mailbox_at(self) -> int:
        return _align(self.status_at + seqlock.HEADER_BYTES + self.status_bytes)

    @property
    def events_at(self) -> int:
        return _align(self.mailbox_at + self.mailbox_bytes)

    @property
    def rows_at(self) -> int:
        return _align(self.events_at + self.event_capacity * EVENT_SLOT)

    @property
    def size(self) -> int:
        return self.rows_at + self.capacity * self.ncols * 8


def shm_dir() -> Path:
    d = Path("/dev/shm")
    return d if d.is_dir() and os.access(d, os.W_OK) else Path(tempfile.gettempdir())


def create(layout: Layout) -> tuple[str, mmap.mmap]:
    """A new zero-filled shared block; returns its file path (the sidecar unlinks it) and map.

    The file's pages are allocated here (``posix_fallocate``), not on first touch: a full
    /dev/shm then fails now with an OSError instead of a SIGBUS in the loop minutes later."""
    fd, path = tempfile.mkstemp(prefix="rig-ring-", dir=shm_dir())
    try:
        os.posix_fallocate(fd, 0, layout.size)
        mm = mmap.mmap(fd, layout.size)
    except BaseException:
        os.unlink(path)
        raise
    finally:
        os.close(fd)
    _init_header(mm, layout)
    return path, mm


def create_private(layout: Layout) -> mmap.mmap:
    """A zero-filled block in this process's memory only (no file): for a recorder whose
    writer runs in the loop's own process (a lockstep run, :mod:`rig_runtime.recorder`)."""
    mm = mmap.mmap(-1, layout.size)
    _init_header(mm, layout)
    return mm


def _init_header(mm: mmap.mmap, layout: Layout) -> None:
    h = memoryview(mm).cast("q")
    h[_NCOLS], h[_CAP], h[_EVCAP] = layout.ncols, layout.capacity, layout.event_capacity
    h[_STATUS_BYTES], h[_MAILBOX_BYTES] = layout.status_bytes, layout.mailbox_bytes
    h[_MAGIC] = MAGIC
    h.release()


def attach(path: str) -> tuple[Layout, mmap.mmap]:
    """Map an existing block (the sidecar) and unlink its file."""
    fd = os.open(path, os.O_RDWR)
    try:
        mm = mmap.mmap(fd, os.fstat(fd).st_size)
    finally:
        os.close(fd)
    os.unlink(path)
    h = memoryview(mm).cast("q")
    try:
        if h[_MAGIC] != MAGIC:
            raise ValueError(f"{path}: not a rig ring")
        return Layout(h[_NCOLS], h[_CAP], h[_EVCAP], h[_STATUS_BYTES], h[_MAILBOX_BYTES]), mm
    finally:
        h.release()


def _enc(s: str, n: int) -> bytes:
    return s.encode("utf-8", "replace")[:n]


def _dec(b: bytes, n: int) -> str:
    return b[:n].decode("utf-8", "ignore")          # a truncated multi-byte character is dropped


class Producer:
    """The loop's side: append rows and events, publish status; never waits."""

    def __init__(self, mm: mmap.mmap, layout: Layout):
        self.layout = layout
        self._mm = mm
        self._h = memoryview(mm).cast("q")
        self._pack = struct.Struct(f"={layout.ncols}d").pack_into
        self._rows_at = layout.rows_at
        self._rowbytes = 8 * layout.ncols
        self._cap = layout.capacity
        self._w = 0
        self._ew = 0

    def mailbox_view(self) -> memoryview:
        lo = self.layout.mailbox_at
        return memoryview(self._mm)[lo:lo + self.layout.mailbox_bytes]

    @property
    def pending(self) -> int:
        return self._w - self._h[_R]

    def append(self, row) -> bool:
        """Put one row in the ring; False (nothing written) if the ring is full.
        ``struct.error`` for a row of the wrong length or with a non-number."""
        w = self._w
        if w - self._h[_R] >= self._cap:
            return False
        self._pack(self._mm, self._rows_at + (w % self._cap) * self._rowbytes, *row)
        self._w = w + 1
        self._h[_W] = w + 1                 # publish: the sidecar may now read slot w
        return True

    def event(self, t: float, kind: str, device: str, check: str, value: float, limit: float,
              message: str) -> bool:
        ew = self._ew
        lay = self.layout
        if ew - self._h[_ER] >= lay.event_capacity:
            return False
        k, d, c, m = _enc(kind, KIND_B), _enc(device, DEVICE_B), _enc(check, CHECK_B), _enc(message, MESSAGE_B)
        _EVENT.pack_into(self._mm, lay.events_at + (ew % lay.event_capacity) * EVENT_SLOT,
                         float(t), float(value), float(limit), len(k), len(d), len(c), len(m), k, d, c, m)
        self._ew = ew + 1
        self._h[_EW] = ew + 1
        return True

    def publish_status(self, data: bytes) -> bool:
        """Publish a status snapshot (a seqlock write); False if it does not fit."""
        if len(data) > self.layout.status_bytes:
            return False
        seqlock.write(self._mm, self.layout.status_at, data)
        return True

    def count_dropped(self, rows: int, events: int) -> None:
        self._h[_DROPPED] = rows
        self._h[_EV_DROPPED] = events

    # what the sidecar reports back
    def sidecar_error(self) -> str:
        n = self._h[_ERR_LEN]
        if not n:
            return ""
        lo = self.layout.error_at
        return _dec(bytes(self._mm[lo:lo + n]), n)

    def has_sidecar_error(self) -> bool:
        return self._h[_ERR_LEN] != 0

    @property
    def rows_written(self) -> int:
        return self._h[_ROWS_WRITTEN]

    @property
    def rows_flushed(self) -> int:
        return self._h[_ROWS_FLUSHED]

    def release(self) -> None:
        self._h.release()


class Consumer:
    """The sidecar's side: take rows and events, read the status, report back."""

    def __init__(self, mm: mmap.mmap, layout: Layout):
        self.layout = layout
        self._mm = mm
        self._h = memoryview(mm).cast("q")
        self._rows = np.ndarray((layout.capacity, layout.ncols), dtype=np.float64, buffer=mm,
                                offset=layout.rows_at)
        self._st_seen = 0

    def mailbox_view(self) -> memoryview:
        lo = self.layout.mailbox_at
        return memoryview(self._mm)[lo:lo + self.layout.mailbox_bytes]

    def rows_pending(self) -> int:
        return self._h[_W] - self._h[_R]

    def take_rows(self, limit: int | None = None) -> np.ndarray:
        """Copy out the published rows not taken yet (at most ``limit``) and release their slots."""
        h = self._h
        r, w = h[_R], h[_W]
        n = w - r if limit is None else min(w - r, limit)
        cap = self.layout.capacity
        i0 = r % cap
        if n <= 0:
            return self._rows[:0].copy()
        if i0 + n <= cap:
            block = self._rows[i0:i0 + n].copy()
        else:
            block = np.concatenate((self._rows[i0:], self._rows[:i0 + n - cap]))
        h[_R] = r + n                       # slots copied: the loop may reuse them
        return block

    def take_events(self) -> list[tuple]:
        h = self._h
        lay = self.layout
        r, w = h[_ER], h[_EW]
        out = []
        for k in range(r, w):
            t, v, lim, nk, nd, nc, nm, kb, db, cb, mb = _EVENT.unpack_from(
                self._mm, lay.events_at + (k % lay.event_capacity) * EVENT_SLOT)
            out.append((t, _dec(kb, nk), _dec(db, nd), _dec(cb, nc), v, lim, _dec(mb, nm)))
        h[_ER] = w
        return out

    def status(self) -> bytes | None:
        """The newest status snapshot not seen before, or None (none new, or torn: retry later)."""
        lay = self.layout
        if seqlock.seq(self._mm, lay.status_at) == self._st_seen:
            return None
        r = seqlock.read(self._mm, lay.status_at, lay.status_bytes)
        if r is None:
            return None
        self._st_seen, data = r
        return data

    def dropped(self) -> tuple[int, int]:
        return self._h[_DROPPED], self._h[_EV_DROPPED]

    def report(self, rows_written: int, rows_flushed: int) -> None:
        self._h[_ROWS_WRITTEN] = rows_written
        self._h[_ROWS_FLUSHED] = rows_flushed

    def set_error(self, text: str) -> None:
        """Once: the log's first error (the loop's recorder turns unhealthy on it)."""
        if self._h[_ERR_LEN]:
            return
        b = _enc(text, ERROR_BYTES) or b"?"
        lo = self.layout.error_at
        self._mm[lo:lo + len(b)] = b
        self._h[_ERR_LEN] = len(b)

    def release(self) -> None:
        self._rows = None
        self._h.release()
