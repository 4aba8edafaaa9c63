"""Modbus TCP framing for function 0x03 (Read Holding Registers), both ends of the wire.

Written once and used by the F/T driver's polling core (:mod:`drivers.ft_poll`, client
side) and by the simulated sensors (:mod:`sim_backend.virtual_ft`, server side), so that the
driver can keep several requests in flight on separate connections and never has to wait
in a library call (the inline poller sends and reads without blocking), and the simulator
can answer from a small selector thread or in its own thread. Both ends are checked
against pymodbus in ``tests/test_ft300.py`` (pymodbus's client reads our server, our driver
reads pymodbus's server), so a shared mistake cannot hide.

Frame (Modbus Messaging on TCP/IP Implementation Guide v1.0b; Application Protocol v1.1b3):
MBAP header = transaction id (u16), protocol id (u16, 0), length (u16, bytes that follow:
unit id + PDU), unit id (u8); then the PDU. All fields big-endian.

============================ ==========================================================
request 0x03                 ``fc=3, start (u16), quantity (u16)``
normal response              ``fc=3, byte count (u8) = 2·quantity, registers (u16 each)``
exception response           ``fc=0x83, exception code (u8)``
============================ ==========================================================
"""

from __future__ import annotations

import struct
from typing import Optional

__all__ = [
    "MBAP_LEN", "FC_READ_HOLDING", "MAX_READ_COUNT", "EXCEPTION_NAMES",
    "encode_read_request", "encode_read_response", "encode_exception",
    "frame_length", "decode_read_response", "decode_request", "exception_text",
]

MBAP_LEN = 7                    # transaction id, protocol id, length, unit id
FC_READ_HOLDING = 0x03
MAX_READ_COUNT = 125            # Application Protocol §6.3
_MAX_LENGTH_FIELD = 254         # unit id + the largest PDU (253 bytes)

# Modbus Application Protocol v1.1b3, section 7.
EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    7: "negative acknowledge",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}

_REQ = struct.Struct(">HHHBBHH")        # MBAP + fc + start + quantity (12 bytes)
_MBAP = struct.Struct(">HHHB")
_EXC = struct.Struct(">HHHBBB")
_regs_structs: dict[int, struct.Struct] = {}     # quantity -> the registers' layout (built once each)
_response_structs: dict[int, struct.Struct] = {}     # quantity -> a normal response's layout


def _regs_struct(count: int) -> struct.Struct:
    st = _regs_structs.get(count)
    if st is None:
        st = _regs_structs[count] = struct.Struct(f">{count}H")
    return st


def _response_struct(count: int) -> struct.Struct:
    st = _response_structs.get(count)
    if st is None:
        st = _response_structs[count] = struct.Struct(f">HHHBBB{count}H")
    return st


def exception_text(code: int) -> str:
    """``Modbus exception <code> (<name>)`` as health causes and errors spell it."""
    return f"Modbus exception {code} ({EXCEPTION_NAMES.get(code, 'unknown')})"


# --------------------------------------------------------------------------- client side
def encode_read_request(tid: int, unit: int, start: int, count: int) -> bytes:
    """Read Holding Registers request: 12 bytes."""
    return _REQ.pack(tid & 0xFFFF, 0, 6, unit, FC_READ_HOLDING, start, count)


def frame_length(buf: bytes | bytearray) -> Optional[int]:
    """Total length of the frame at the start of ``buf`` once its MBAP header is there
    (None before that). Raises ValueError for a length field no valid frame has."""
    if len(buf) < 6:
        return None
    n = (buf[4] << 8) | buf[5]
    if n < 2 or n > _MAX_LENGTH_FIELD:
        raise ValueError(f"MBAP length field {n} (valid: 2..{_MAX_LENGTH_FIELD})")
    return 6 + n


def decode_read_response(frame: bytes | bytearray, tid: int, unit: int, count: int
                         ) -> tuple[Optional[tuple[int, ...]], Optional[int]]:
    """One complete response frame -> ``(registers, None)`` or ``(None, exception code)``.

    Raises ValueError (with what is wrong) for anything that is not the answer to request
    ``tid`` for ``unit``: another transaction id or unit id, a protocol id other than 0, a
    byte count or length that does not match ``count`` registers, another function code.
    """
    if len(frame) < MBAP_LEN + 2:
        raise ValueError(f"response of {len(frame)} bytes is too short")
    r_tid, proto, length, r_unit = _MBAP.unpack_from(frame)
    if length != len(frame) - 6:
        raise ValueError(f"MBAP length {length} but {len(frame) - 6} bytes follow")
    if proto != 0:
        raise ValueError(f"protocol id {proto}, expected 0")
    if r_tid != tid & 0xFFFF:
        raise ValueError(f"transaction id {r_tid}, expected {tid & 0xFFFF}")
    if r_unit != unit:
        raise ValueError(f"unit id {r_unit}, expected {unit}")
    fc = frame[MBAP_LEN]
    if fc == FC_READ_HOLDING | 0x80:
        if length != 3:
            raise ValueError(f"exception response with length {length}, expected 3")
        return None, frame[MBAP_LEN + 1]
    if fc != FC_READ_HOLDING:
        raise ValueError(f"function code {fc:#04x}, expected 0x03")
    nbytes = frame[MBAP_LEN + 1]
    if nbytes != 2 * count or length != 3 + 2 * count:
        raise ValueError(f"byte count {nbytes} in a frame of length {length}, expected {2 * count} "
                         f"for {count} registers")
    return _regs_struct(count).unpack_from(frame, MBAP_LEN + 2), None


# --------------------------------------------------------------------------- server side
def decode_request(frame: bytes | bytearray) -> tuple[int, int, int, bytes]:
    """One complete request frame -> ``(transaction id, unit id, function code, PDU data)``.
    Raises ValueError for a protocol id other than 0 or a PDU without a function code."""
    tid, proto, length, unit = _MBAP.unpack_from(frame)
    if proto != 0 or length < 2 or len(frame) != 6 + length:
        raise ValueError(f"bad MBAP header (protocol {proto}, length {length}, {len(frame)} bytes)")
    return tid, unit, frame[MBAP_LEN], bytes(frame[MBAP_LEN + 1:])


def encode_read_response(tid: int, unit: int, registers: list[int] | tuple[int, ...]) -> bytes:
    """Normal response to a Read Holding Registers request (registers 0..65535)."""
    n = len(registers)
    return _response_struct(n).pack(tid & 0xFFFF, 0, 3 + 2 * n, unit, FC_READ_HOLDING, 2 * n, *registers)


def encode_exception(tid: int, unit: int, fc: int, code: int) -> bytes:
    """Exception response: function code with bit 7 set, then the exception code."""
    return _EXC.pack(tid & 0xFFFF, 0, 3, unit, (fc | 0x80) & 0xFF, code)
