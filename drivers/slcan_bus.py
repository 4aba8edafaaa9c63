"""``interface="rig_slcan"``: a python-can bus for SLCAN (Lawicel ASCII) adapters on a
serial port that reads whole buffers instead of single bytes.

python-can's own ``slcan`` interface reads one byte per ``read(1)`` (a ``select`` and a
``read`` system call per byte, ≈ 50 µs here), which at ~12 frames per 5 ms period costs
several milliseconds a cycle — too slow for the control loop. This bus speaks the same
protocol (``C``/``S<n>``/``O`` at open; frames ``tIIILDD…``, ``TIIIIIIIILDD…``, ``rIIIL``,
``RIIIIIIIIL``; ``\\r`` = OK, ``\\a`` = error; ``z``/``Z`` transmit acknowledgements are
skipped) and drains the port with one non-blocking ``read(2)`` of the bytes ``TIOCINQ``
reports per ``recv`` (see :meth:`SlcanBus._drain`). Registered as
the python-can interface ``rig_slcan`` (entry point in pyproject.toml); it works with
USB-SLCAN adapters as well as with the adapter ``rig sim`` emulates on a pty.
"""

from __future__ import annotations

import collections
import os
import select
import time
from typing import Any, Optional, Sequence

import can
import serial

from .slcan_codec import FRAME_START, encode_frame, parse_frame  # noqa: F401 - one codec for both ends
from .tty import HangUp, bytes_waiting

_os_read = os.read              # module-level so a test can watch the port's reads

_BITRATES = {10000: "S0", 20000: "S1", 50000: "S2", 100000: "S3", 125000: "S4", 250000: "S5",
             500000: "S6", 750000: "S7", 1000000: "S8", 83300: "S9"}


class SlcanBus(can.BusABC):
    def __init__(self, channel: str, bitrate: int = 1_000_000, tty_baudrate: int = 115200,
                 open_timeout_s: float = 1.0, **kwargs: Any):
        if bitrate not in _BITRATES:
            raise can.CanInitializationError(f"bitrate {bitrate} not supported by SLCAN (one of {sorted(_BITRATES)})")
        try:
            self._ser = serial.Serial(channel, baudrate=tty_baudrate, timeout=0, write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as e:
            raise can.CanInitializationError(f"cannot open SLCAN port {channel!r}: {e}") from e
        self._fd = self._ser.fd
        self._inq = bytearray(4)          # TIOCINQ's answer, reused recv after recv
        self._buf = b""
        self._rx: collections.deque = collections.deque()
        self.errors = 0                   # \a replies of the adapter
        self.channel_info = f"SLCAN on {channel}"
        super().__init__(channel=channel, **kwargs)
        self._ser.reset_input_buffer()
        for cmd in ("C", _BITRATES[bitrate], "O"):
            self._command(cmd, open_timeout_s, required=(cmd != "C"))

    def _command(self, cmd: str, timeout_s: float, required: bool) -> None:
        os.write(self._fd, (cmd + "\r").encode())
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if select.select([self._fd], [], [], max(0.0, end - time.monotonic()))[0]:
                data = os.read(self._fd, 4096)
                if b"\r" in data:
                    return
                if b"\a" in data:
                    if required:
                        raise can.CanInitializationError(f"SLCAN adapter refused {cmd!r}")
                    return
        if required:
            raise can.CanInitializationError(f"SLCAN adapter did not answer {cmd!r} within {timeout_s} s")

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        self._write(encode_frame(msg))

    def send_many(self, msgs: Sequence[can.Message]) -> None:
        """Send several frames with one ``write(2)`` (one USB transfer on a real adapter):
        the control loop's SYNC + RPDOs of a period. Not part of python-can's API; callers
        fall back to ``send`` per frame on other buses."""
        self._write(b"".join([encode_frame(m) for m in msgs]))

    def _write(self, data: bytes) -> None:
        try:
            n = os.write(self._fd, data)
        except BlockingIOError:
            n = 0
        except OSError as e:
            raise can.CanOperationError(f"SLCAN write failed: {e}") from e
        if n != len(data):
            raise can.CanOperationError("SLCAN write incomplete (port buffer full)")

    def _drain(self) -> None:
        """Read the bytes the line discipline holds (:func:`drivers.tty.bytes_waiting`),
        queue the frames they end; nothing is read while it says 0 (a real-time caller of
        ``recv(0)`` never waits for the kernel's worker)."""
        fd = self._fd
        try:
            n = bytes_waiting(fd, self._inq)
        except HangUp as e:
            raise can.CanOperationError("SLCAN adapter disconnected (hang-up on the port)") from e
        except OSError as e:
            raise can.CanOperationError(f"SLCAN read failed: {e}") from e
        if n <= 0:
            return
        try:
            chunk = _os_read(fd, n)
        except BlockingIOError:
            return
        except OSError as e:
            raise can.CanOperationError(f"SLCAN read failed: {e}") from e
        if not chunk:
            return
        buf = self._buf + chunk if self._buf else chunk
        if 7 in buf:                       # \a: the adapter refused a command; ends a reply too
            self.errors += buf.count(7)
            buf = buf.replace(b"\a", b"\r")
        lines = buf.split(b"\r")
        self._buf = lines.pop()            # an unfinished line waits for the next read
        stamp = time.time()
        starts = FRAME_START
        for line in lines:
            if line and line[0] in starts:  # skip acks (z, Z) and empty OK replies
                msg = parse_frame(line)
                if msg is not None:
                    msg.timestamp = stamp
                    self._rx.append(msg)

    def _recv_internal(self, timeout: Optional[float]):
        rx = self._rx
        if not rx:
            self._drain()
            if not rx and timeout != 0:
                end = None if timeout is None else time.monotonic() + timeout
                while not rx:
                    remaining = None if end is None else end - time.monotonic()
                    if remaining is not None and remaining <= 0:
                        break
                    select.select([self._fd], [], [], remaining)
                    self._drain()
        if rx:
            return rx.popleft(), False
        return None, False

    def shutdown(self) -> None:
        try:
            os.write(self._fd, b"C\r")
        except OSError:
            pass
        try:
            self._ser.close()
        except Exception:
            pass
        super().shutdown()
