"""The operator's mailbox between the control server (``rig ctl``, in the recording
sidecar) and the control loop: one fixed-size region of shared memory, one command slot
written only by the server, one answer slot written only by the loop.

Protocol: the server :meth:`Mailbox.submit`\\ s a command (``stop``, ``set NAME VALUE``,
``reset-fault``) and polls :meth:`Mailbox.result` for its answer; the loop calls
:meth:`Mailbox.take` once per cycle and :meth:`Mailbox.answer`\\ s what it took. One
command is in flight at a time (the server waits for each answer); a new submit replaces
a command the loop has not taken yet.

Layout (little endian, every slot 8-byte aligned)::

    0   command slot   seqlock header | kind u8, name length u8, pad, value f64, name 32 B
    64  answer slot    seqlock header | seq u64, ok u8, pad, message length u16, message 240 B

Each slot is a seqlock slot (:mod:`rig_runtime.seqlock` has the protocol) with one
writer: the server writes the command slot, the loop the answer slot.

The command slot's sequence number numbers the commands (2, 4, …; 0: no command yet), so
the loop's :meth:`take` is one unpack of that number (:func:`seqlock.seq`) compared with the
last one taken — no allocation beyond it, no system call — while nothing is pending. The
answer names the sequence number it answers; :meth:`result` returns None until the answer
for the asked number is there.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from . import seqlock

NAME_BYTES = 32
MESSAGE_BYTES = 240
KINDS = ("stop", "set", "reset-fault")          # kind codes 1, 2, 3 (0: none)

_CMD = struct.Struct(f"<BB6xd{NAME_BYTES}s")    # kind, name length, value, name (UTF-8)
_ANS = struct.Struct(f"<QB1xH4x{MESSAGE_BYTES}s")  # seq answered, ok, message length, message (UTF-8)

_CMD_OFF = 0
_CMD_END = _CMD_OFF + seqlock.HEADER_BYTES + _CMD.size
_ANS_OFF = (_CMD_END + 7) // 8 * 8
_ANS_END = _ANS_OFF + seqlock.HEADER_BYTES + _ANS.size
SIZE = (_ANS_END + 7) // 8 * 8                  # bytes the mailbox needs


@dataclass(frozen=True, slots=True)
class Command:
    """A command as the loop took it."""
    seq: int
    kind: str        # one of KINDS
    name: str = ""   # set: the gain's name
    value: float = math.nan   # set: the new value


def _cut(text: str, n: int) -> bytes:
    """``text`` as UTF-8, at most ``n`` bytes, cut at a character boundary."""
    b = text.encode("utf-8", "replace")
    return b if len(b) <= n else b[:n].decode("utf-8", "ignore").encode("utf-8")


class Mailbox:
    """One command slot and one answer slot in ``buf`` (a zero-filled region of a shared
    buffer, ``len(buf) >= SIZE``). The server side (``submit``, ``result``) and the loop
    side (``take``, ``answer``) each run in one thread of their process."""

    def __init__(self, buf: memoryview):
        if len(buf) < SIZE:
            raise ValueError(f"mailbox needs {SIZE} bytes, got {len(buf)}")
        self._buf = memoryview(buf)
        self._taken = 0                 # loop side: the last sequence number taken
        self.rejected = 0               # loop side: torn copies seen (retried next cycle)

    # ------------------------------------------------------------------ server side
    def submit(self, kind: str, name: str = "", value: float = math.nan) -> int:
        """Post a command; returns its sequence number (replaces one not taken yet)."""
        if kind not in KINDS:
            raise ValueError(f"unknown command kind {kind!r} (known: {', '.join(KINDS)})")
        nb = name.encode("utf-8")
        if len(nb) > NAME_BYTES:
            raise ValueError(f"name longer than {NAME_BYTES} bytes: {name[:40]!r}")
        return seqlock.write(self._buf, _CMD_OFF, _CMD.pack(KINDS.index(kind) + 1, len(nb), float(value), nb))

    def result(self, seq: int) -> tuple[bool, str] | None:
        """(ok, message) of command ``seq`` once the loop answered it; None while pending."""
        r = seqlock.read(self._buf, _ANS_OFF, _ANS.size)
        if r is None:
            return None
        answered, ok, n, msg = _ANS.unpack(r[1])
        if answered != seq or seq == 0:
            return None
        return bool(ok), msg[:n].decode("utf-8", "replace")

    # ------------------------------------------------------------------ loop side
    def take(self) -> Command | None:
        """The command posted since the last ``take``, or None (nothing new, or the server
        is mid-write: the next call sees it)."""
        if seqlock.seq(self._buf, _CMD_OFF) == self._taken:
            return None
        r = seqlock.read(self._buf, _CMD_OFF, _CMD.size)
        if r is None:
            self.rejected += 1
            return None
        seq, payload = r
        self._taken = seq
        code, n, value, name = _CMD.unpack(payload)
        if not 1 <= code <= len(KINDS):     # not a command this version knows
            self.answer(seq, False, f"unknown command code {code}")
            return None
        return Command(seq, KINDS[code - 1], name[:n].decode("utf-8", "replace"), value)

    def answer(self, seq: int, ok: bool, message: str) -> None:
        """Answer command ``seq`` (the message is cut to MESSAGE_BYTES of UTF-8)."""
        m = _cut(message, MESSAGE_BYTES)
        seqlock.write(self._buf, _ANS_OFF, _ANS.pack(seq, bool(ok), len(m), m))
