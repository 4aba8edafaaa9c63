"""Micro-Epsilon optoNCDT 1420-class laser triangulation sensors on RS-422.

Wire format (optoNCDT 1420 manual, Chap. 8.2 and 7.5.2.1; see docs/protocols.md, section 1):
every output value is three bytes sent L, M, H. The two top bits of each byte are a
flag (``00`` L, ``01`` M, ``10`` H), the low six bits are data, so a value carries 18
bits ``x = L6 | M6 << 6 | H6 << 12``. Distances are 16-bit values 0..65520 with

    d_mm = (102/65520 · x − 1) · MR/100        (MR = measuring range in mm)

and values above 65520 are the device's 18-bit error codes (262076 "no peak", …).
There is no checksum: a damaged byte is only detected if its flag breaks the L, M, H
pattern; a byte replaced by one with the *same* flag is undetectable by any decoder.

The codec (module-level functions and :class:`FrameDecoder`) does no I/O; the virtual
device in ``sim_backend.virtual_laser`` reuses it. :class:`drivers.laser.LaserDriver` reads a
serial port without blocking and turns the values into SI metres with health.
"""

from __future__ import annotations

import math
import re
from typing import Iterable, Sequence

__all__ = [
    "MAX_DISTANCE_X", "MAX_X", "ERROR_CODES", "X_PER_PERCENT",
    "encode_value", "encode_values", "x_from_distance_mm", "xs_from_distance_mm",
    "distance_mm_from_x", "error_reason", "FrameDecoder",
]

MAX_DISTANCE_X = 65520          # largest 16-bit distance value (d = 1.01·MR)
MAX_X = (1 << 18) - 1           # 18 data bits per value: 262143
X_PER_PERCENT = 65520 / 102    # d_mm = (x/X_PER_PERCENT − 1)·MR/100

ERROR_CODES: dict[int, str] = {
    262075: "too much data for the baud rate",
    262076: "no peak",
    262077: "peak before range",
    262078: "peak after range",
    262080: "cannot calculate",
    262081: "peak too large",
    262082: "laser off",
}

_FLAG_L, _FLAG_M, _FLAG_H = 0x00, 0x40, 0x80
# x = L + (M << 6) + (H << 12) − _FLAG_SUM when M and H carry their flags 01 and 10.
_FLAG_SUM = (_FLAG_M << 6) + (_FLAG_H << 12)
# An H byte whose six data bits are at most 14 makes x <= 14·4096 + 4095 = 61439 < 65520: a
# distance, whatever L and M hold.
_H_SAFE = _FLAG_H | 14
# Each byte -> one letter, so frame search runs on bytes in C: L, M, H by the flag bits, h for
# an H byte above _H_SAFE (a value that may be an error code), X for flag 11 (never valid).
_FLAG_TABLE = bytes(b"LMHX"[b >> 6] if not _H_SAFE < b < 0xC0 else ord("h") for b in range(256))
_FRAME_RUN = re.compile(rb"(?:LM[Hh])+")
_CLEAN = b"LMH" * 1024          # letters of a gap-free stream of up to 1024 distance frames


def encode_value(x: int) -> bytes:
    """The three wire bytes (L, M, H) of one 18-bit value."""
    if not 0 <= x <= MAX_X:
        raise ValueError(f"laser value {x} outside 0..{MAX_X}")
    return bytes((x & 0x3F, _FLAG_M | (x >> 6) & 0x3F, _FLAG_H | (x >> 12) & 0x3F))


def encode_values(xs: Sequence[int]) -> bytes:
    """Wire bytes of many values, frame after frame. The frames of distance values are made
    by :func:`encode_value` a block at a time, when a value of the block is first asked
    for, and kept (a device sends values near each other: a value then costs one look-up);
    an error code's frame is made each time."""
    try:
        return b"".join(map(_frame_of, xs))
    except KeyError:
        pass
    for x in xs:                            # make the blocks of the distance values missing
        if x not in _FRAMES and 0 <= x <= MAX_DISTANCE_X:
            lo = x - x % _BLOCK
            block = range(lo, min(lo + _BLOCK, MAX_DISTANCE_X + 1))
            _FRAMES.update(zip(block, map(encode_value, block)))
    return b"".join([_FRAMES[x] if x in _FRAMES else encode_value(x) for x in xs])   # error codes


_BLOCK = 512
_FRAMES: dict[int, bytes] = {}      # distance value -> its frame, made a block at a time
_frame_of = _FRAMES.__getitem__


def distance_mm_from_x(x: int, mr_mm: float) -> float:
    """Distance from the start of the measuring range, mm, of a valid value x (0..65520)."""
    return (x / X_PER_PERCENT - 1.0) * mr_mm / 100.0


def x_from_distance_mm(d_mm: float, mr_mm: float) -> int:
    """Inverse of :func:`distance_mm_from_x`: rounded to the nearest value, clipped to 0..65520."""
    if math.isnan(d_mm):
        raise ValueError("distance is NaN")
    return xs_from_distance_mm([d_mm], mr_mm)[0]


def xs_from_distance_mm(d: Iterable[float], mr_mm: float, base: float = 0.0, scale: float = 1.0,
                        offset_mm: float = 0.0, below: int = 0, above: int = MAX_DISTANCE_X) -> list[int]:
    """Wire values of distances r = (base + d)·scale − offset_mm from the start of the
    measuring range (mm; a device that sees ``base`` metres from its mounting, sampled with
    deviations ``d``, passes scale 1000 and its offset), each rounded to the nearest value
    (half to even). A distance before the span (r < −1 % of MR) gives ``below``, one beyond
    it (> 101 %) ``above``: by default the ends 0 and 65520 (clipped); a device passes the
    error codes it sends there. A NaN raises ValueError."""
    lo, hi, xpp = -0.01 * mr_mm, 1.01 * mr_mm, X_PER_PERCENT
    out: list[int] = []
    add = out.append
    for e in d:         # a loop: its names are fast locals (a comprehension's are cells here)
        r = (base + e) * scale - offset_mm
        add(below if r < lo else above if r > hi else round((r * 100.0 / mr_mm + 1.0) * xpp))
    return out


def error_reason(x: int) -> str | None:
    """None for a distance value (0..65520), else why the value is not a measurement."""
    if 0 <= x <= MAX_DISTANCE_X:
        return None
    text = ERROR_CODES.get(x)
    return f"{text} ({x})" if text else f"unknown code {x}"


class FrameDecoder:
    """Incremental decoder: bytes in, 18-bit values out.

    A frame is three consecutive bytes flagged L, M, H. Partial frames at the end of a
    chunk are kept for the next :meth:`decode`; every other byte that is not part of such
    a triple (garbage, a frame with a lost or damaged byte) is dropped and counted in
    ``discarded``, and decoding resynchronises on the next L, M, H. One pass of
    ``bytes.translate`` (in C) gives each byte's letter; a chunk of whole clean frames none
    of which can be an error code (the usual case) is then kept as bytes: its last value
    is decoded at once, the others only if asked (:meth:`values`).

    After :meth:`decode`, the latest chunk: ``count`` values, the last one ``last`` (-1 if
    none), ``distances_only`` (no error code or value beyond the range end among them).
    """

    __slots__ = ("discarded", "frames", "count", "last", "distances_only", "_pending", "_buf", "_list")

    def __init__(self) -> None:
        self.discarded = 0      # bytes thrown away as not part of a frame
        self.frames = 0         # values decoded
        self._pending = b""     # an L or L, M waiting for the rest of its frame
        self._buf = b""         # the latest chunk's clean frames, not decoded yet (_list None)
        self.clear()

    @property
    def pending(self) -> int:
        """Bytes of an incomplete frame held for the next call."""
        return len(self._pending)

    def reset(self) -> None:
        """Forget a partial frame (after a read error); its bytes count as discarded."""
        self.discarded += len(self._pending)
        self._pending = b""
        self.clear()

    def clear(self) -> None:
        """The latest chunk is empty (nothing was read)."""
        self.count = 0
        self.last = -1
        self.distances_only = True
        self._list: list[int] | None = []

    def feed(self, data: bytes) -> list[int]:
        """Decode what ``data`` (plus the held partial frame) completes, in order."""
        self.decode(data)
        return self.values()

    def decode(self, data: bytes) -> int:
        """Decode what ``data`` (plus the held partial frame) completes, as the latest chunk;
        how many values it holds."""
        pending = self._pending
        buf = pending + data if pending else data if type(data) is bytes else bytes(data)
        n = len(buf)
        letters = buf.translate(_FLAG_TABLE)
        if n % 3 == 0 and _CLEAN.startswith(letters):   # whole clean distance frames
            if pending:
                self._pending = b""
            if not n:
                self.clear()
                return 0
            self._buf, self._list = buf, None
            count = self.count = n // 3
            self.frames += count
            self.last = buf[-3] + (buf[-2] << 6) + (buf[-1] << 12) - _FLAG_SUM
            self.distances_only = True
            return count
        out: list[int] = []
        pos = 0
        for m in _FRAME_RUN.finditer(letters):
            start, end = m.span()
            self.discarded += start - pos
            out += _values(buf, start, end)
            pos = end
        keep = 2 if letters.endswith(b"LM") else 1 if letters.endswith(b"L") else 0
        self.discarded += n - keep - pos
        self._pending = buf[n - keep:] if keep else b""
        self._list = out
        self.count = len(out)
        self.frames += self.count
        self.last = out[-1] if out else -1
        self.distances_only = not out or max(out) <= MAX_DISTANCE_X
        return self.count

    def values(self) -> list[int]:
        """The latest chunk's values."""
        if self._list is None:
            self._list = _values(self._buf, 0, len(self._buf))
        return self._list


def _values(buf: bytes, start: int, end: int) -> list[int]:
    """Values of the clean frames buf[start:end] (flags known to be L, M, H)."""
    return [lo + (mid << 6) + (hi << 12) - _FLAG_SUM
            for lo, mid, hi in zip(buf[start:end:3], buf[start + 1:end:3], buf[start + 2:end:3])]


