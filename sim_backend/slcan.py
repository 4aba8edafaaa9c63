"""An SLCAN (Lawicel ASCII) USB–CAN adapter emulated on a pty — the far side of python-can's
``slcan`` interface, bridged to a python-can bus (the virtual bus the simulated drives use).

The runtime opens the pty slave exactly as it would open a CANable/USBtin/Lawicel adapter::

    can.Bus(interface="slcan", channel=adapter.port_name, bitrate=1_000_000)

Wire protocol (what python-can's ``slcanBus`` sends and parses; every line ends in ``\\r``):

=========================== ===================================================================
host → adapter               adapter → host
=========================== ===================================================================
``O`` / ``L``                open the channel (``L``: listen only); ``\\r``. Opening discards what
                             the host left unread (a new session starts clean); opening an open
                             channel is accepted (python-can sends ``O`` twice)
``C``                        close the channel; ``\\r`` (also when already closed, as CANable does)
``S0``..``S9``, ``sxxyy``    bit rate (only while closed, else BEL); ``\\r``
``Y2``/``Y5`` (FD data rate) ``\\r`` (accepted, CAN FD frames themselves are refused)
``V`` / ``v`` / ``N``        ``V1013\\r`` (hw 10, sw 13) / ``v1013\\r`` / ``N`` + serial + ``\\r``
``F``                        ``Fxx\\r`` status flags (reading clears them): bit 3 data overrun
                             (frames dropped because the host did not read), bit 7 bus error
                             (an error frame was seen on the bus — SLCAN cannot carry it)
``Z0``/``Z1``                timestamps off/on (``Z1``: 4 hex digits, ms modulo 60000, appended to
                             each received frame, as Lawicel does); ``\\r``
``X``/``Q``/``M``/``m``/``W``/``U`` accepted, ``\\r``
``tiiildd..``  ``Tiiiiiiiildd..``  ``riiil``  ``Riiiiiiiil``
                             transmit a standard / extended data frame, standard / extended
                             RTR frame onto the bus. *No* acknowledgement by default (see below);
                             BEL if the channel is not open (or listen-only) or the line is
                             malformed
empty line                   ignored (python-can sends one when it sets no FD data rate)
anything else                BEL (``\\x07``)
=========================== ===================================================================

Frames on the bus (from the drives) reach the host as ``t``/``T``/``r``/``R`` lines while the
channel is open; while it is closed they are dropped (as a real adapter does), error frames
always are (and set status bit 7).

Why transmit commands are not acknowledged: Lawicel adapters answer ``z\\r``/``Z\\r`` and some
firmware ``\\r``, but python-can's client turns every such line into a ``None`` from
``recv(timeout=0)`` — a runtime that drains "until ``recv(0)`` returns None" would stop at
the first acknowledgement and fall a frame further behind every cycle. CANable's slcan
firmware, the common adapter, sends nothing either. ``ack_transmit=True`` restores the
Lawicel ``z``/``Z`` answers.

The host side never blocks the adapter: the pty master is non-blocking; bytes the host does
not read in time are kept up to ``backlog_bytes`` and then whole frames are dropped
(counted in ``counters["tx_dropped"]``, status bit 3). The adapter keeps the slave end open
itself, so a host that closes — or is killed — does not hang up the pty.
"""

from __future__ import annotations

import os
import select
import termios
import threading
import time
import tty
from typing import Callable, Optional

import can

from drivers.slcan_bus import encode_frame, parse_frame  # one SLCAN codec for both ends

__all__ = ["SlcanAdapter", "encode_frame", "parse_frame"]

_OK = b"\r"
_ERR = b"\x07"
_BITRATES = {"0": 10_000, "1": 20_000, "2": 50_000, "3": 100_000, "4": 125_000, "5": 250_000,
             "6": 500_000, "7": 750_000, "8": 1_000_000, "9": 83_300}
FLAG_OVERRUN = 0x08
FLAG_BUS_ERROR = 0x80


class SlcanAdapter:
    """An SLCAN adapter on a pty, bridged to ``bus`` (see the module docstring).

    ``on_frame(msg, t_monotonic)`` is called (from the adapter's reader thread, keep it short)
    for every frame the host transmits, before it goes onto the bus; ``on_host_frames(msgs,
    t_monotonic)`` (from the bus thread) for the frames just written to the host, ``t`` taken
    after the write.
    """

    def __init__(self, bus: can.BusABC, *, on_frame: Optional[Callable[[can.Message, float], None]] = None,
                 on_host_frames: Optional[Callable[[list, float], None]] = None,
                 ack_transmit: bool = False, serial_number: str = "RIG0", version: str = "1013",
                 backlog_bytes: int = 65536) -> None:
        self.bus = bus
        self.on_frame = on_frame
        self.on_host_frames = on_host_frames
        self.ack_transmit = ack_transmit
        self.serial_number = serial_number
        self.version = version
        self.backlog_bytes = backlog_bytes
        self.is_open = False          # channel opened by the host (O or L)
        self.listen_only = False
        self.bitrate: Optional[int] = None
        self.timestamps = False
        self.flags = 0
        self.counters = {"host_frames": 0, "bus_frames": 0, "tx_dropped": 0, "closed_dropped": 0,
                         "error_frames": 0, "bad_commands": 0, "opens": 0, "closes": 0}
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        attrs = termios.tcgetattr(self._slave)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        os.set_blocking(self._master, False)
        self.port_name = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._wlock = threading.Lock()
        self._backlog = bytearray()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._closed = False

    # ------------------------------------------------------------------ lifetime
    def start(self) -> "SlcanAdapter":
        """Start the two bridge threads (pty → bus, bus → pty); returns self."""
        if self._threads:
            return self
        for target, name in ((self._pty_loop, "slcan pty->bus"), (self._bus_loop, "slcan bus->pty")):
            th = threading.Thread(target=target, name=name, daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def close(self) -> None:
        """Stop the threads and close the pty (the bus stays open: it is the caller's). Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass
        for th in self._threads:
            th.join(2.0)
        self._threads.clear()
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> "SlcanAdapter":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ adapter -> host
    def _write(self, data: bytes) -> bool:
        """Write to the master without blocking. What the kernel does not take now waits in
        a backlog (lines stay whole); False (nothing written) once the backlog is full."""
        with self._wlock:
            if self._backlog:
                self._flush_backlog()
            if self._backlog:
                if len(self._backlog) + len(data) > self.backlog_bytes:
                    return False
                self._backlog += data
                return True
            try:
                n = os.write(self._master, data)
            except BlockingIOError:
                n = 0
            except OSError:
                return False
            if n < len(data):
                self._backlog += data[n:]
            return True

    def _flush_backlog(self) -> None:
        try:
            n = os.write(self._master, self._backlog)
        except (BlockingIOError, OSError):
            return
        del self._backlog[:n]

    def _bus_loop(self) -> None:
        recv = self.bus.recv
        while not self._stop.is_set():
            try:
                msg = recv(0.1)
            except Exception:  # noqa: BLE001 - a bus shut down under us ends the thread
                if self._stop.is_set():
                    return
                time.sleep(0.01)
                continue
            if msg is None:
                if self._backlog:
                    with self._wlock:
                        self._flush_backlog()
                continue
            out = bytearray()
            sent: list[can.Message] = []
            n = 0
            while msg is not None and n < 64:
                line = self._encode(msg)
                if line:
                    out += line
                    sent.append(msg)
                n += 1
                try:
                    msg = recv(0.0)
                except Exception:  # noqa: BLE001
                    msg = None
            if msg is not None:
                line = self._encode(msg)
                if line:
                    out += line
                    sent.append(msg)
            if out and self._write_frames(bytes(out)) and self.on_host_frames is not None:
                try:
                    self.on_host_frames(sent, time.monotonic())
                except Exception:  # noqa: BLE001 - an observer must not break the adapter
                    pass

    def _encode(self, msg: can.Message) -> bytes:
        if msg.is_error_frame:
            self.counters["error_frames"] += 1
            self.flags |= FLAG_BUS_ERROR
            return b""
        if msg.is_fd:
            return b""
        if not self.is_open:
            self.counters["closed_dropped"] += 1
            return b""
        ts = int(time.monotonic() * 1000) % 60000 if self.timestamps else None
        self.counters["bus_frames"] += 1
        return encode_frame(msg, ts)

    def _write_frames(self, data: bytes) -> bool:
        if self._write(data):
            return True
        n = data.count(b"\r")
        self.counters["bus_frames"] -= n
        self.counters["tx_dropped"] += n
        self.flags |= FLAG_OVERRUN
        return False

    # ------------------------------------------------------------------ host -> adapter
    def _pty_loop(self) -> None:
        buf = bytearray()
        poller = select.poll()
        poller.register(self._master, select.POLLIN)
        poller.register(self._wake_r, select.POLLIN)
        while not self._stop.is_set():
            try:
                events = poller.poll(1000)
            except InterruptedError:
                continue
            if self._stop.is_set():
                return
            if not events:
                continue
            try:
                chunk = os.read(self._master, 4096)
            except BlockingIOError:
                continue
            except OSError:
                # EIO: no slave open anywhere (cannot happen while we hold it) — back off
                time.sleep(0.01)
                continue
            buf += chunk
            while True:
                i = _line_end(buf)
                if i < 0:
                    break
                line = bytes(buf[:i])
                del buf[:i + 1]
                self._command(line)
            if len(buf) > 1024:          # no terminator in sight: garbage, resynchronise
                buf.clear()
                self.counters["bad_commands"] += 1

    def _command(self, line: bytes) -> None:
        line = line.strip(b"\n ")
        if not line:
            return
        c = line[:1]
        if c in (b"t", b"T", b"r", b"R"):
            return self._transmit(line)
        arg = line[1:].decode("ascii", "replace")
        if c == b"O" or c == b"L":
            if self.is_open:            # python-can opens twice (set_bitrate, then __init__)
                self.listen_only = c == b"L"
                return self._ok()
            try:                        # what the last host left unread must not reach this one
                termios.tcflush(self._slave, termios.TCIFLUSH)
            except termios.error:
                pass
            with self._wlock:
                self._backlog.clear()
            self.listen_only = c == b"L"
            self.is_open = True
            self.counters["opens"] += 1
            return self._ok()
        if c == b"C":
            if self.is_open:
                self.counters["closes"] += 1
            self.is_open = False
            return self._ok()
        if c == b"S":
            if self.is_open or arg not in _BITRATES:
                return self._error()
            self.bitrate = _BITRATES[arg]
            return self._ok()
        if c == b"s":
            if self.is_open or len(arg) != 4 or not all(ch in "0123456789abcdefABCDEF" for ch in arg):
                return self._error()
            self.bitrate = None
            return self._ok()
        if c == b"Y":
            return self._ok() if not self.is_open else self._error()
        if c == b"V":
            return self._reply(f"V{self.version}\r")
        if c == b"v":
            return self._reply(f"v{self.version}\r")
        if c == b"N":
            return self._reply(f"N{self.serial_number}\r")
        if c == b"F":
            flags, self.flags = self.flags, 0
            return self._reply(f"F{flags:02X}\r")
        if c == b"Z":
            if arg not in ("0", "1"):
                return self._error()
            self.timestamps = arg == "1"
            return self._ok()
        if c in (b"X", b"Q", b"M", b"m", b"W", b"U"):
            return self._ok()
        return self._error()

    def _transmit(self, line: bytes) -> None:
        msg = parse_frame(line)
        if msg is None or not self.is_open or self.listen_only:
            return self._error()
        t = time.monotonic()
        msg.timestamp = t
        self.counters["host_frames"] += 1
        cb = self.on_frame
        if cb is not None:
            try:
                cb(msg, t)
            except Exception:  # noqa: BLE001 - an observer must not break the adapter
                pass
        try:
            self.bus.send(msg)
        except can.CanError:
            self.flags |= FLAG_BUS_ERROR
        if self.ack_transmit:
            self._reply("Z\r" if msg.is_extended_id else "z\r")

    def _ok(self) -> None:
        self._write(_OK)

    def _error(self) -> None:
        self.counters["bad_commands"] += 1
        self._write(_ERR)

    def _reply(self, text: str) -> None:
        self._write(text.encode("ascii"))


def _line_end(buf: bytearray) -> int:
    """Index of the first line terminator (\\r; a lone \\n is accepted too), -1 if none."""
    i = buf.find(b"\r")
    j = buf.find(b"\n")
    if i < 0:
        return j
    if j < 0:
        return i
    return min(i, j)
