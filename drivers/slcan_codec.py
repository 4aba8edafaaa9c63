"""The SLCAN (Lawicel ASCII) frame codec: one line per classic CAN frame, shared by the
``rig_slcan`` python-can interface (:mod:`drivers.slcan_bus`) and the adapter ``rig sim``
emulates (:mod:`sim_backend.slcan`). No I/O."""

from __future__ import annotations

import re
from binascii import unhexlify
from typing import Optional

import can

__all__ = ["FRAME_START", "encode_frame", "parse_frame"]

_HEX = frozenset(b"0123456789abcdefABCDEF")
# a data frame with an 11-bit id, the usual line: t III L DD… (the length is checked after)
_STD_DATA = re.compile(rb"t([0-9A-Fa-f]{3})([0-8])((?:[0-9A-Fa-f][0-9A-Fa-f]){0,8})")
FRAME_START = frozenset(b"tTrR")


def encode_frame(msg: can.Message, timestamp_ms: Optional[int] = None) -> bytes:
    """One SLCAN line for a classic CAN frame (``None``-free; error/FD frames are not encodable)."""
    dlc = msg.dlc
    if msg.is_extended_id:
        head = f"{'R' if msg.is_remote_frame else 'T'}{msg.arbitration_id:08X}{dlc:d}"
    else:
        head = f"{'r' if msg.is_remote_frame else 't'}{msg.arbitration_id:03X}{dlc:d}"
    body = "" if msg.is_remote_frame else bytes(msg.data[:dlc]).hex().upper()
    tail = f"{timestamp_ms:04X}" if timestamp_ms is not None else ""
    return (head + body + tail + "\r").encode("ascii")


def parse_frame(line: bytes) -> Optional[can.Message]:
    """A ``t``/``T``/``r``/``R`` command line (without ``\\r``) -> Message, None if malformed."""
    m = _STD_DATA.fullmatch(line)
    if m is not None:                                # fast path: standard-id data frame
        id_txt, dlc_txt, data_txt = m.groups()
        dlc = dlc_txt[0] - 48
        can_id = int(id_txt, 16)
        if len(data_txt) != 2 * dlc or can_id > 0x7FF:
            return None
        return can.Message(arbitration_id=can_id, is_extended_id=False, data=unhexlify(data_txt), dlc=dlc)
    kind = line[:1]
    if kind not in (b"t", b"T", b"r", b"R"):
        return None                                  # acks (z, Z), status or version replies
    ext = kind in (b"T", b"R")
    remote = kind in (b"r", b"R")
    n_id = 8 if ext else 3
    if len(line) < 1 + n_id + 1:
        return None
    id_txt, dlc_txt = line[1:1 + n_id], line[1 + n_id:2 + n_id]
    if not all(c in _HEX for c in id_txt) or not dlc_txt.isdigit():
        return None
    can_id, dlc = int(id_txt, 16), int(dlc_txt)
    if dlc > 8 or can_id > (0x1FFFFFFF if ext else 0x7FF):
        return None
    rest = line[2 + n_id:]
    if remote:
        if rest:
            return None
        return can.Message(arbitration_id=can_id, is_extended_id=ext, is_remote_frame=True, dlc=dlc)
    if len(rest) != 2 * dlc or not all(c in _HEX for c in rest):
        return None
    return can.Message(arbitration_id=can_id, is_extended_id=ext, data=unhexlify(rest), dlc=dlc)
