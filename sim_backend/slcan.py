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

Two ways to connect the CAN side:

* **bridge** — ``SlcanAdapter(bus)``: frames go to and come from any python-can bus (e.g.
  python-can's ``virtual`` bus), on two threads (pty → bus, bus → pty).
* **direct** — ``SlcanAdapter(None, service=fn)``: the devices use ``adapter.device_bus``
  (a python-can bus with no thread of its own) and are served by the adapter's one thread:
  it waits in ``epoll`` on the pty, hands every frame of what it read to the devices, calls
  ``service(t)`` at once (and every ``service_period_s`` for their timers), and writes what
  the devices sent meanwhile in ONE ``write`` — a SYNC is answered by the thread that read
  it, with no hand-over between threads (``rig sim``: its SYNC → TPDO path).
"""

from __future__ import annotations

import collections
import math
import os
import select
import termios
import threading
import time
import tty
from typing import Callable, Optional

import can

from drivers.slcan_codec import encode_frame, parse_frame  # one SLCAN codec for both ends

__all__ = ["SlcanAdapter", "DeviceSideBus", "encode_frame", "parse_frame"]

_OK = b"\r"
_ERR = b"\x07"
_BITRATES = {"0": 10_000, "1": 20_000, "2": 50_000, "3": 100_000, "4": 125_000, "5": 250_000,
             "6": 500_000, "7": 750_000, "8": 1_000_000, "9": 83_300}
FLAG_OVERRUN = 0x08
FLAG_BUS_ERROR = 0x80


class DeviceSideBus(can.BusABC):
    """The CAN side of a direct-mode :class:`SlcanAdapter` as a python-can bus, for the
    devices behind it: ``send`` goes to the host (within the adapter's thread: collected and
    written once the devices are served), ``recv`` returns the host's frames."""

    def __init__(self, adapter: "SlcanAdapter") -> None:
        self._adapter = adapter
        self._rx: collections.deque[can.Message] = collections.deque()
        self._cond = threading.Condition()
        self.channel_info = f"SLCAN adapter on {adapter.port_name} (device side)"
        super().__init__(channel=adapter.port_name)

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        self._adapter._from_device(msg)

    def _push(self, msg: can.Message) -> None:
        self._rx.append(msg)
        if self._adapter.service is None:           # a device thread may be waiting in recv
            with self._cond:
                self._cond.notify()

    def _recv_internal(self, timeout: Optional[float]):
        rx = self._rx
        if not rx and timeout != 0:
            with self._cond:
                self._cond.wait_for(lambda: rx, timeout)
        try:
            return rx.popleft(), False
        except IndexError:
            return None, False


class SlcanAdapter:
    """An SLCAN adapter on a pty, bridged to ``bus`` — or, with ``bus=None``, serving the
    devices on :attr:`device_bus` from its own thread (see the module docstring).

    ``on_frame(msg, t_monotonic)`` is called (from the adapter's reader thread, keep it short)
    for every frame the host transmits, before the devices get it (``t``: when it was read);
    ``on_host_frames(msgs, t_monotonic)`` for the frames just written to the host, ``t`` taken
    after the write. Direct mode: ``service(t)`` (adapter thread) after every read that
    brought frames and every ``service_period_s``; ``on_thread_start()`` runs first in the
    adapter's thread(s) (e.g. to give only that thread a real-time priority).
    """

    def __init__(self, bus: Optional[can.BusABC] = None, *,
                 on_frame: Optional[Callable[[can.Message, float], None]] = None,
                 on_host_frames: Optional[Callable[[list, float], None]] = None,
                 service: Optional[Callable[[float], None]] = None, service_period_s: float = 0.001,
                 on_thread_start: Optional[Callable[[], None]] = None,
                 ack_transmit: bool = False, serial_number: str = "RIG0", version: str = "1013",
                 backlog_bytes: int = 65536) -> None:
        if bus is not None and service is not None:
            raise ValueError("service() is for the direct mode (bus=None)")
        self.on_frame = on_frame
        self.on_host_frames = on_host_frames
        self.service = service
        self.service_period_s = service_period_s
        self.on_thread_start = on_thread_start
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
        self._out = bytearray()                 # direct mode: lines for the host, written after service
        self._out_msgs: list[can.Message] = []
        self._frames_in = 0                     # direct mode: host frames since the last service
        self._loop_ident: Optional[int] = None
        self._watches: dict[int, Callable[[float], None]] = {}
        # direct mode: after_write(t, served_host_frames) ends every turn of the loop, after the
        # devices' answers were written (the place for work that must not delay them)
        self.after_write: Optional[Callable[[float, bool], None]] = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._closed = False
        self.bus: can.BusABC = bus if bus is not None else DeviceSideBus(self)
        self.device_bus: Optional[DeviceSideBus] = None if bus is not None else self.bus

    # ------------------------------------------------------------------ lifetime
    def start(self) -> "SlcanAdapter":
        """Start the thread(s): direct mode one, bridge mode two (pty → bus, bus → pty)."""
        if self._threads:
            return self
        loops = [(self._pty_loop, "slcan pty->bus" if self.device_bus is None else "slcan adapter")]
        if self.device_bus is None:
            loops.append((self._bus_loop, "slcan bus->pty"))
        for target, name in loops:
            th = threading.Thread(target=self._thread_main, args=(target,), name=name, daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def run(self) -> None:
        """Direct mode: serve in the calling thread until :meth:`stop` (then :meth:`close`)."""
        if self.device_bus is None:
            raise RuntimeError("run() is for the direct mode (bus=None); start() bridges")
        self._thread_main(self._pty_loop)

    def stop(self) -> None:
        """Ask the loop(s) to end (safe from a callback inside the loop)."""
        self._stop.set()
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass

    def watch(self, fd: int, callback: Callable[[float], None]) -> None:
        """Direct mode: also wait for ``fd``; ``callback(t)`` runs in the adapter's thread
        when it is readable (after the host's bytes of the same wake-up). Before start/run."""
        self._watches[fd] = callback

    def _thread_main(self, target: Callable[[], None]) -> None:
        if self.on_thread_start is not None:
            try:
                self.on_thread_start()
            except Exception:  # noqa: BLE001 - a refused priority must not stop the adapter
                pass
        target()

    def close(self) -> None:
        """Stop the threads and close the pty (a bridged bus stays open: it is the caller's;
        the direct mode's device bus is shut down). Idempotent."""
        if self._closed:
            return
        self._closed = True
        self.stop()
        for th in self._threads:
            th.join(2.0)
        self._threads.clear()
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        if self.device_bus is not None:
            self.device_bus.shutdown()

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
        """Bridge mode: frames from the bus to the host, up to 64 lines per write."""
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
            if out:
                self._to_host(bytes(out), sent)

    def _from_device(self, msg: can.Message) -> None:
        """Direct mode: a device sent ``msg``. In the adapter's thread it waits for the write
        after ``service``; from any other thread it is written at once."""
        line = self._encode(msg)
        if not line:
            return
        if threading.get_ident() == self._loop_ident:
            self._out += line
            self._out_msgs.append(msg)
        else:
            self._to_host(line, [msg])

    def _flush_out(self) -> None:
        """Direct mode: write what the devices sent during the last service, in one write."""
        if self._out:
            data, msgs = bytes(self._out), self._out_msgs
            self._out.clear()
            self._out_msgs = []
            self._to_host(data, msgs)
        elif self._backlog:
            with self._wlock:
                self._flush_backlog()

    def _to_host(self, data: bytes, msgs: list) -> None:
        if self._write_frames(data) and self.on_host_frames is not None:
            try:
                self.on_host_frames(msgs, time.monotonic())
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
        """Wait for the host's bytes (epoll), execute every complete line; in direct mode
        serve the devices right after (and on their timer period) and write their answers."""
        self._loop_ident = threading.get_ident()
        buf = bytearray()
        master, mono = self._master, time.monotonic
        ep = select.epoll()
        ep.register(master, select.EPOLLIN)
        ep.register(self._wake_r, select.EPOLLIN)
        watches = self._watches
        for fd in watches:
            ep.register(fd, select.EPOLLIN)
        service, period = self.service, self.service_period_s
        next_service = mono() + period if service is not None else math.inf
        try:
            while not self._stop.is_set():
                if service is not None:
                    timeout = next_service - mono()
                else:
                    timeout = 0.1 if self._backlog else 1.0
                events = ep.poll(timeout) if timeout > 0 else ()
                if self._stop.is_set():
                    return
                t = mono()
                ready = [fd for fd, _ in events]
                if master in ready:
                    try:
                        chunk = os.read(master, 65536)
                    except BlockingIOError:
                        chunk = b""
                    except OSError:
                        # EIO: no slave open anywhere (cannot happen while we hold it) — back off
                        time.sleep(0.01)
                        continue
                    if chunk:
                        buf += chunk
                        while True:
                            i = _line_end(buf)
                            if i < 0:
                                break
                            line = bytes(buf[:i])
                            del buf[:i + 1]
                            self._command(line, t)
                        if len(buf) > 1024:          # no terminator in sight: garbage, resynchronise
                            buf.clear()
                            self.counters["bad_commands"] += 1
                for fd in ready:
                    cb = watches.get(fd)
                    if cb is not None:
                        cb(t)
                if service is None:
                    continue
                served = self._frames_in
                if served or t >= next_service:
                    self._frames_in = 0
                    if t >= next_service:
                        next_service += period
                        if next_service <= t:
                            next_service = t + period
                    try:
                        service(t)
                    except Exception:  # noqa: BLE001 - a device error must not stop the adapter
                        pass
                self._flush_out()
                if self.after_write is not None:
                    self.after_write(t, bool(served))
        finally:
            ep.close()

    def _command(self, line: bytes, t: float) -> None:
        line = line.strip(b"\n ")
        if not line:
            return
        c = line[:1]
        if c in (b"t", b"T", b"r", b"R"):
            return self._transmit(line, t)
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

    def _transmit(self, line: bytes, t: float) -> None:
        msg = parse_frame(line)
        if msg is None or not self.is_open or self.listen_only:
            return self._error()
        msg.timestamp = t
        self.counters["host_frames"] += 1
        cb = self.on_frame
        if cb is not None:
            try:
                cb(msg, t)
            except Exception:  # noqa: BLE001 - an observer must not break the adapter
                pass
        if self.device_bus is not None:
            self.device_bus._push(msg)
            self._frames_in += 1
        else:
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
