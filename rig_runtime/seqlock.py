"""One slot of shared memory with one writer and lock-free readers: a seqlock with a CRC.

The mailbox (:mod:`rig_runtime.mailbox`), the F/T poll process's sensor slots
(``drivers/ft_process.py``) and the loop's status snapshot (:mod:`rig_runtime.ring`) all
publish through these functions; this is the one place the protocol lives.

Slot layout at ``off`` (little endian; ``off`` should be 8-byte aligned so that ``lock``
is one aligned 8-byte store)::

    off + 0    lock     u64   even: complete (the slot's sequence number), odd: being written
    off + 8    crc32    u32   CRC-32 of the length field's four bytes followed by the payload
    off + 12   length   u32   payload bytes
    off + 16   payload        up to the slot's capacity (the caller's ``size``)

Writer (exactly one per slot): make ``lock`` odd, write the payload, then CRC and length,
make ``lock`` even again — each write advances the sequence number by 2 (0: never written).

Reader: read ``lock``, copy the payload, read ``lock`` again; accept the copy only if both
reads are equal and even and the CRC matches. A torn copy (the writer was mid-write) fails
one of the three; the CRC also catches stores seen out of order on a weakly ordered CPU,
which Python code cannot fence. The CRC covers the length too, so a zero-filled or stale
header over a new sequence number is no valid empty payload. A rejected read changes
nothing: the reader tries again on its next call and never waits.

:func:`seq` is the cheap check a reader makes every cycle: one 8-byte unpack, compared with
the sequence number it last took; only when that moved does it pay for :func:`read`.
"""

from __future__ import annotations

import struct
import zlib

HEADER_BYTES = 16                       # lock, CRC-32, length: the payload starts here

_LOCK = struct.Struct("<Q")
_CRC_LEN = struct.Struct("<II")         # at off + 8
_LEN = struct.Struct("<I")


def _crc(n: int, payload: bytes) -> int:
    return zlib.crc32(payload, zlib.crc32(_LEN.pack(n)))


def seq(buf, off: int) -> int:
    """The slot's ``lock`` (its sequence number when even): one 8-byte unpack, nothing else."""
    return _LOCK.unpack_from(buf, off)[0]


def write(buf, off: int, payload: bytes) -> int:
    """Publish ``payload`` in the slot at ``off`` of ``buf`` (a writable buffer: memoryview,
    bytearray, mmap); returns the new (even) sequence number. ValueError, with the slot
    untouched, if the payload does not fit in ``buf``."""
    n = len(payload)
    start = off + HEADER_BYTES
    if off < 0 or start + n > len(buf):
        raise ValueError(f"seqlock slot at {off}: {n} payload bytes do not fit in {len(buf)}")
    lock = _LOCK.unpack_from(buf, off)[0] | 1
    _LOCK.pack_into(buf, off, lock)                         # odd: being written
    buf[start:start + n] = payload
    _CRC_LEN.pack_into(buf, off + 8, _crc(n, payload), n)
    _LOCK.pack_into(buf, off, lock + 1)                     # even: complete
    return lock + 1


def read(buf, off: int, size: int) -> tuple[int, bytes] | None:
    """(sequence number, payload) of the slot at ``off`` whose payload holds at most ``size``
    bytes; None if it was never written, is being written, or the copy is torn or corrupt
    (a length over ``size`` included). Nothing changes on None: just read again later."""
    lock = _LOCK.unpack_from(buf, off)[0]
    if lock & 1 or lock == 0:
        return None
    crc, n = _CRC_LEN.unpack_from(buf, off + 8)
    if n > size:
        return None
    start = off + HEADER_BYTES
    payload = bytes(buf[start:start + n])
    if _LOCK.unpack_from(buf, off)[0] != lock or _crc(n, payload) != crc:
        return None
    return lock, payload
