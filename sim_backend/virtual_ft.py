"""Simulated force–torque sensors: the other end of the FT 300 wire.

Modbus TCP (127.0.0.1, a free port unless given): every TCP sensor is served with the
driver's own framing (:mod:`drivers.ft_modbus`), either by one small selector thread (after
:meth:`VirtualFTServer.start`: ``rig sim``, tests) or — lockstep — by
:meth:`VirtualFTServer.answer_pending`, which the simulator calls in its ``advance(t)``:
it answers every request that has arrived, in the caller's thread, without waiting for
more (the first call retires the thread). With ``stream="memory"`` the same Modbus TCP
frames travel over in-process wires instead of loopback sockets (:mod:`rig_runtime.wires`,
endpoints ``("mem://NAME", 0)``): until the first ``answer_pending`` a request is answered
as it arrives (in the sender's thread, where the selector thread would answer it), from
then on only in ``answer_pending`` — the same replies at the same points of a lockstep
cycle as over TCP, without a socket, a selector or a thread. Modbus RTU (a pseudo-terminal pair per sensor):
pymodbus's serial server on an asyncio loop thread, started only if an RTU sensor exists.
Holding registers 180..185 are filled from the latest :class:`Wrench` with the register
codec the driver decodes with (:mod:`drivers.ft_codec`), so there is one register map for
both ends; ``tests/test_ft300.py`` reads the TCP server with pymodbus's client. Faults are
injected per sensor and act on the wire:

=============== ==========================================================================
``dropout``     the request is processed but no answer is sent (the client times out)
``corrupt``     ``mode="garble"`` (default): TCP — byte count of the answer set to 0xFF,
                undecodable; RTU — CRC inverted. ``mode="truncate"``: only the first half
                of the answer frame is sent
``stuck``       registers frozen at their value when the fault was injected
``offset``      ``fx=…, …, mz=…`` (SI) added to the wrench before encoding
``out_of_range`` answer with a Modbus exception response, ``code=4`` (device failure) unless given
=============== ==========================================================================

The TCP server answers function 0x03 for registers within 180..185; other registers →
exception 2, writes (0x05, 0x06, 0x0F, 0x10, 0x17) → 2 (read-only), other functions → 1,
quantity 0 or > 125 → 3, another unit id → 11 (as a gateway whose target does not answer).
"""

from __future__ import annotations

import asyncio
import fcntl
import os
import select
import selectors
import socket
import struct
import threading
import time
import tty
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, Optional

from rig_runtime import wires

if TYPE_CHECKING:                   # pymodbus: imported where a serial (RTU) sensor or a fault needs it
    from pymodbus.constants import ExcCodes
    from pymodbus.server import ModbusSerialServer

from drivers.ft_codec import DEFAULT_UNIT_ID, REG_COUNT, REG_START, Wrench, registers_from_wrench
from drivers.ft_modbus import (
    FC_READ_HOLDING,
    MAX_READ_COUNT,
    decode_request,
    encode_exception,
    encode_read_response,
    frame_length,
)

__all__ = ["VirtualFTServer", "FAULT_KINDS"]

FAULT_KINDS = ("dropout", "corrupt", "stuck", "offset", "out_of_range")
_WRENCH_FIELDS = Wrench._fields
_START_TIMEOUT_S = 5.0
_WRITE_FCS = (0x05, 0x06, 0x0F, 0x10, 0x17)
_GATEWAY_NO_RESPONSE = 11


class VirtualFTServer:
    """Simulated FT sensors; ``endpoints`` (TCP) and ``serial_ports`` (RTU) say where to connect."""

    def __init__(self, names: Sequence[str], unit_id: int = DEFAULT_UNIT_ID, host: str = "127.0.0.1",
                 ports: Optional[Mapping[str, int]] = None, rtu: Sequence[str] = (),
                 baudrate: int = 19200, stream: str = "tcp") -> None:
        if len(set(names)) != len(names):
            raise ValueError(f"sensor names must be distinct: {list(names)}")
        if stream not in ("tcp", "memory"):
            raise ValueError(f"stream must be 'tcp' or 'memory', got {stream!r}")
        self.stream = stream
        if not set(rtu) <= set(names):
            raise ValueError(f"rtu names {sorted(set(rtu) - set(names))} are not sensors")
        self.names = tuple(names)
        self.unit_id = unit_id
        self.host = host
        self.baudrate = baudrate
        self._ports = dict(ports or {})
        self._rtu = frozenset(rtu)
        self.endpoints: dict[str, tuple[str, int]] = {}
        self.serial_ports: dict[str, str] = {}
        self._lock = threading.Lock()
        self._wrenches = {n: Wrench() for n in self.names}
        self._faults: dict[str, dict[str, dict[str, Any]]] = {n: {} for n in self.names}
        self._served = {n: 0 for n in self.names}
        self._regs: dict[str, Optional[list[int]]] = dict.fromkeys(self.names)   # encoded once per change
        self._servers: list[ModbusSerialServer] = []
        self._bridges: list[_PtyBridge] = []
        self._tcp: Optional[_TcpServer | _MemServer] = None
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._thread: Optional[threading.Thread] = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "VirtualFTServer":
        """Start the servers; returns once all are listening."""
        if self._tcp is not None or self._thread is not None:
            return self
        try:
            tcp = [n for n in self.names if n not in self._rtu]
            if tcp:
                self._tcp = (_MemServer if self.stream == "memory" else _TcpServer)(self, tcp)
                self.endpoints.update(self._tcp.endpoints)
                self._tcp.start()
            if self._rtu:
                self._loop = asyncio.new_event_loop()
                self._thread = threading.Thread(target=self._run_loop, name="virtual-ft-rtu", daemon=True)
                self._thread.start()
                asyncio.run_coroutine_threadsafe(self._start_servers(), self._loop).result(_START_TIMEOUT_S)
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Stop every server, the threads and the pty bridges. Idempotent."""
        if self._tcp is not None:
            self._tcp.close()
            self._tcp = None
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return
        if loop.is_running():
            fut = asyncio.run_coroutine_threadsafe(self._stop_servers(), loop)
            try:
                fut.result(_START_TIMEOUT_S)
            finally:
                loop.call_soon_threadsafe(loop.stop)
        thread.join(_START_TIMEOUT_S)
        for bridge in self._bridges:
            bridge.close()
        self._bridges.clear()
        self._loop = self._thread = None

    def __enter__(self) -> "VirtualFTServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def answer_pending(self) -> int:
        """Lockstep: answer every request that has arrived on the TCP sensors' sockets (new
        connections accepted too) in the caller's thread, never waiting for more; returns
        once every reply has left its socket's send queue. Loopback TCP delivers within the
        ``send`` call (the receive path runs in the sender's softirq), so a client's
        non-blocking read right after this finds the replies; likewise the requests a
        client sent before this call are here to be read. Returns the number of requests
        read (each answered, unless a ``dropout`` fault swallows it).

        The first call retires the selector thread (its sockets stay open): from then on,
        requests are answered only here. 0 if there is no TCP sensor."""
        if self._tcp is None:
            return 0
        return self._tcp.answer_pending()

    @property
    def running(self) -> bool:
        return ((self._tcp is not None and self._tcp.running)
                or (self._thread is not None and self._thread.is_alive()))

    # ------------------------------------------------------------------ plant side
    def set_wrench(self, name: str, w: Wrench) -> None:
        """New physical value for one sensor (any thread)."""
        self._check_name(name)
        with self._lock:
            self._wrenches[name] = w
            self._regs[name] = None

    def served(self, name: str) -> int:
        """Number of register reads this sensor has answered with data."""
        with self._lock:
            return self._served[name]

    def inject(self, name: str, kind: str, **params: Any) -> None:
        """Start a fault (see the module docstring); replaces one of the same kind."""
        self._check_name(name)
        params = _check_fault(kind, params)
        with self._lock:
            if kind == "stuck":
                params["registers"] = self._registers_locked(name)
            faults = dict(self._faults[name])
            faults[kind] = params
            self._faults[name] = faults
            self._regs[name] = None

    def clear(self, name: str, kind: Optional[str] = None) -> None:
        """End one fault, or all faults of the sensor when ``kind`` is None."""
        self._check_name(name)
        if kind is not None and kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {kind!r} (known: {', '.join(FAULT_KINDS)})")
        with self._lock:
            self._faults[name] = {} if kind is None else {k: v for k, v in self._faults[name].items() if k != kind}
            self._regs[name] = None

    def _check_name(self, name: str) -> None:
        if name not in self._wrenches:
            raise KeyError(f"no simulated FT sensor {name!r} (have: {', '.join(self.names)})")

    def _registers_locked(self, name: str) -> list[int]:
        """Registers the sensor would answer with now (caller holds the lock; read-only list,
        cached until the wrench or the faults change)."""
        regs = self._regs[name]
        if regs is not None:
            return regs
        faults = self._faults[name]
        if "stuck" in faults:
            regs = list(faults["stuck"]["registers"])
        else:
            w = self._wrenches[name]
            if "offset" in faults:
                off = faults["offset"]
                w = w._replace(**{k: getattr(w, k) + off.get(k, 0.0) for k in _WRENCH_FIELDS})
            regs = registers_from_wrench(w)
        self._regs[name] = regs
        return regs

    # ------------------------------------------------------------------ TCP server side
    def _answer(self, name: str, frame: bytes | bytearray) -> Optional[bytes]:
        """The bytes the sensor sends for one request frame (None: nothing, ``dropout``)."""
        tid, unit, fc, data = decode_request(frame)
        with self._lock:
            faults = self._faults[name]
            reply = None
            if unit != self.unit_id:
                code = _GATEWAY_NO_RESPONSE
            elif fc != FC_READ_HOLDING:
                code = 2 if fc in _WRITE_FCS else 1
            elif len(data) != 4:
                code = 3
            else:
                start, count = (data[0] << 8) | data[1], (data[2] << 8) | data[3]
                if not 1 <= count <= MAX_READ_COUNT:
                    code = 3
                elif start < REG_START or start + count > REG_START + REG_COUNT:
                    code = 2
                elif "out_of_range" in faults:
                    code = faults["out_of_range"]["code"]
                else:
                    code = 0
                    regs = self._registers_locked(name)[start - REG_START:start - REG_START + count]
                    reply = encode_read_response(tid, unit, regs)
                    self._served[name] += 1
            if reply is None:
                reply = encode_exception(tid, unit, fc, code)
            if "dropout" in faults:
                return None
            if "corrupt" in faults:
                return _mangle(reply, faults["corrupt"]["mode"], rtu=False)
        return reply

    # ------------------------------------------------------------------ RTU server side
    def _run_loop(self) -> None:
        loop = self._loop
        assert loop is not None
        asyncio.set_event_loop(loop)
        try:
            loop.run_forever()
        finally:
            for task in asyncio.all_tasks(loop):
                task.cancel()
            loop.run_until_complete(asyncio.sleep(0))
            loop.close()

    async def _start_servers(self) -> None:
        for name in self.names:
            if name not in self._rtu:
                continue
            from pymodbus.server import ModbusSerialServer
            from pymodbus.simulator import DataType, SimData, SimDevice
            device = SimDevice(id=self.unit_id, action=self._make_action(name),
                               simdata=[SimData(REG_START, values=[0] * REG_COUNT,
                                                datatype=DataType.REGISTERS, readonly=True)])
            bridge = _PtyBridge()
            self._bridges.append(bridge)
            server = ModbusSerialServer(device, port=bridge.server_path, baudrate=self.baudrate,
                                        trace_packet=self._make_tracer(name))
            self._servers.append(server)
            await server.serve_forever(background=True)
            self.serial_ports[name] = bridge.client_path

    async def _stop_servers(self) -> None:
        for server in self._servers:
            await server.shutdown()
        self._servers.clear()
        await asyncio.sleep(0.01)       # let transports finish closing

    def _make_action(self, name: str):
        """SimDevice action: refresh registers 180..185 from the plant, or answer an exception."""
        async def action(function_code: int, start_address: int, address: int, count: int,
                         registers: list[int], set_values: Any) -> Optional[ExcCodes]:
            with self._lock:
                fault = self._faults[name].get("out_of_range")
                if fault is not None:
                    from pymodbus.constants import ExcCodes
                    return ExcCodes(fault["code"])
                registers[0:REG_COUNT] = self._registers_locked(name)
                self._served[name] += 1
            return None
        return action

    def _make_tracer(self, name: str):
        """trace_packet hook (RTU): drop or mangle outgoing frames while a wire fault is active."""
        def trace(sending: bool, data: bytes) -> bytes:
            if not sending:
                return data
            faults = self._faults[name]
            if "dropout" in faults:
                return b""
            if "corrupt" in faults:
                return _mangle(data, faults["corrupt"]["mode"], rtu=True)
            return data
        return trace


def _check_fault(kind: str, params: dict[str, Any]) -> dict[str, Any]:
    """Validate fault parameters; returns them with defaults filled in."""
    from pymodbus.constants import ExcCodes
    allowed: dict[str, dict[str, Any]] = {
        "dropout": {}, "stuck": {},
        "corrupt": {"mode": "garble"},
        "offset": {k: 0.0 for k in _WRENCH_FIELDS},
        "out_of_range": {"code": int(ExcCodes.DEVICE_FAILURE)},
    }
    if kind not in allowed:
        raise ValueError(f"unknown fault kind {kind!r} (known: {', '.join(FAULT_KINDS)})")
    extra = set(params) - set(allowed[kind])
    if extra:
        raise TypeError(f"fault {kind!r} takes no parameter(s) {sorted(extra)}")
    out = {**allowed[kind], **params}
    if kind == "corrupt" and out["mode"] not in ("garble", "truncate"):
        raise ValueError(f"corrupt mode must be 'garble' or 'truncate', got {out['mode']!r}")
    if kind == "out_of_range":
        out["code"] = int(ExcCodes(out["code"]))    # ValueError for a code Modbus does not define
    return out


def _mangle(frame: bytes, mode: str, rtu: bool) -> bytes:
    """Garble an outgoing frame so that the client must reject it."""
    if mode == "truncate":
        return frame[: len(frame) // 2]
    b = bytearray(frame)
    if rtu:
        b[-1] ^= 0xFF                   # CRC no longer matches
    elif len(b) > 8:
        b[8] = 0xFF                     # MBAP(7) + function code; byte count beyond the frame
    return bytes(b)


class _Conn:
    """One client connection of the TCP server: request bytes not yet framed, reply bytes
    not yet sent."""

    __slots__ = ("sock", "name", "rx", "tx", "want_write")

    def __init__(self, sock: socket.socket, name: str) -> None:
        self.sock = sock
        self.name = name
        self.rx = bytearray()
        self.tx = bytearray()
        self.want_write = False


class _MemConn:
    """One client connection of the in-process server: the server's end of the wire and
    request bytes not yet framed."""

    __slots__ = ("end", "name", "rx")

    def __init__(self, end: wires.WireEnd, name: str) -> None:
        self.end = end
        self.name = name
        self.rx = bytearray()


class _MemServer:
    """Every Modbus TCP sensor of a :class:`VirtualFTServer` on in-process wires (one
    listening name per sensor): requests framed and answered as :class:`_TcpServer` does,
    at arrival until :meth:`answer_pending` is first called, then only there."""

    def __init__(self, owner: VirtualFTServer, names: Sequence[str]) -> None:
        self._owner = owner
        self._listeners: list[wires.Listener] = []
        self._conns: list[_MemConn] = []
        self._inline = False
        self._open = True
        self.endpoints: dict[str, tuple[str, int]] = {}
        for name in names:
            ls = wires.listen(wires.unique_name(f"ft-{name}"))
            ls.on_connect = self._acceptor(name)
            self._listeners.append(ls)
            self.endpoints[name] = (ls.url, 0)

    @property
    def running(self) -> bool:
        return self._open and not self._inline

    def start(self) -> None:
        pass

    def _acceptor(self, name: str):
        def accept(end: wires.WireEnd) -> None:
            conn = _MemConn(end, name)
            self._conns.append(conn)
            if not self._inline:
                end.rx.on_data = lambda: self._serve(conn)
        return accept

    def answer_pending(self) -> int:
        if not self._inline:
            self._inline = True
            for conn in self._conns:
                conn.end.rx.on_data = None
        n = 0
        for conn in list(self._conns):          # a copy: _serve drops hung-up connections from the list
            if conn.end.rx.buf or conn.end.hung_up:
                n += self._serve(conn)
        return n

    def _serve(self, conn: _MemConn) -> int:
        """Frame and answer what arrived on ``conn``; the number of requests read."""
        end = conn.end
        rx = conn.rx
        rx += end.read()
        if not rx:
            if end.hung_up:
                self._drop(conn)
            return 0
        answer, name = self._owner._answer, conn.name
        n_req = 0
        while True:
            try:
                n = frame_length(rx)
                if n is None or len(rx) < n:
                    break
                reply = answer(name, rx[:n])
            except ValueError:                          # not Modbus TCP: hang up, like a device would
                self._drop(conn)
                return n_req
            del rx[:n]
            n_req += 1
            if reply and not end.hung_up:
                end.write(reply)
        return n_req

    def _drop(self, conn: _MemConn) -> None:
        conn.end.close()
        if conn in self._conns:
            self._conns.remove(conn)

    def close(self) -> None:
        """Hang up every connection and stop listening (clients see EOF)."""
        self._open = False
        for ls in self._listeners:
            ls.close()
        for conn in list(self._conns):
            self._drop(conn)


class _TcpServer:
    """Every TCP sensor of a :class:`VirtualFTServer` on one selector thread: one listening
    socket per sensor, non-blocking connections, requests answered in arrival order
    (pipelined requests on one connection too)."""

    def __init__(self, owner: VirtualFTServer, names: Sequence[str]) -> None:
        self._owner = owner
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._listeners: list[socket.socket] = []
        self._conns: dict[int, _Conn] = {}
        self._stopping = False
        self._inline = False            # answer_pending() took over from the thread
        self._requests = 0              # request frames read (answer_pending's count)
        self._replied: set[_Conn] = set()   # connections written to in this answer_pending()
        self.endpoints: dict[str, tuple[str, int]] = {}
        try:
            for name in names:
                ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                self._listeners.append(ls)
                ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)   # rebind over TIME_WAIT
                ls.bind((owner.host, owner._ports.get(name, 0)))
                ls.listen(8)
                ls.setblocking(False)
                self._sel.register(ls, selectors.EVENT_READ, name)
                self.endpoints[name] = (owner.host, ls.getsockname()[1])
        except BaseException:
            self._close_sockets()
            raise
        self._thread = threading.Thread(target=self._run, name="virtual-ft-tcp", daemon=True)

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def start(self) -> None:
        self._thread.start()

    def answer_pending(self) -> int:
        """Retire the thread on first use; then passes over everything ready (accepts,
        requests, replies) until nothing is, without waiting; then wait until every reply
        sent here has left its send queue (see :meth:`VirtualFTServer.answer_pending`)."""
        if not self._inline:
            self._inline = True
            self._wake()
            if self._thread.is_alive():
                self._thread.join(_START_TIMEOUT_S)
        self._requests = 0
        self._replied.clear()
        for _ in range(8):              # a new connection's request is read in the next pass
            if not self._serve_ready(0.0):
                break
        deadline = time.monotonic() + _START_TIMEOUT_S
        for conn in self._replied:
            while conn.sock.fileno() >= 0 and (conn.tx or _unsent(conn.sock)):
                if time.monotonic() > deadline:     # a peer that stopped reading: not ours to wait for
                    break
                if conn.tx:
                    self._send(conn)
                time.sleep(0)
        self._replied.clear()
        return self._requests

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass

    def close(self) -> None:
        """Stop the thread; every socket is closed (clients see EOF, ports are free)."""
        self._stopping = True
        self._wake()
        if self._thread.is_alive():
            self._thread.join(_START_TIMEOUT_S)
        else:
            self._close_sockets()

    def _run(self) -> None:
        """Serve until closed (or retired by :meth:`answer_pending`; the sockets then stay)."""
        try:
            while not self._stopping and not self._inline:
                self._serve_ready(None)
        finally:
            if self._stopping or not self._inline:
                self._close_sockets()

    def _serve_ready(self, timeout: Optional[float]) -> bool:
        """Read every ready request first, then send the replies back to back (a client
        thread woken by the first reply would otherwise compete for the interpreter lock
        between the reads). Returns whether anything was ready."""
        replying = []
        events = self._sel.select(timeout)
        for key, ev in events:
            data = key.data
            if data is None:                    # wake-up
                try:
                    self._wake_r.recv(64)
                except OSError:
                    pass
                continue
            if isinstance(data, str):           # a listening socket: data = sensor name
                self._accept(key.fileobj, data)  # type: ignore[arg-type]
                continue
            if ev & selectors.EVENT_READ:
                self._receive(data)
            if data.tx and data.sock.fileno() >= 0:
                replying.append(data)
        for conn in replying:
            self._send(conn)
        return bool(events)

    def _accept(self, ls: socket.socket, name: str) -> None:
        try:
            sock, _ = ls.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = _Conn(sock, name)
        self._conns[sock.fileno()] = conn
        self._sel.register(sock, selectors.EVENT_READ, conn)

    def _receive(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            return self._drop(conn)
        rx = conn.rx
        rx += data
        while True:
            try:
                n = frame_length(rx)
                if n is None or len(rx) < n:
                    break
                reply = self._owner._answer(conn.name, rx[:n])
            except ValueError:                          # not Modbus TCP: hang up, like a device would
                return self._drop(conn)
            del rx[:n]
            self._requests += 1
            if reply:
                conn.tx += reply

    def _send(self, conn: _Conn) -> None:
        if self._inline:
            self._replied.add(conn)
        try:
            n = conn.sock.send(conn.tx)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError:
            return self._drop(conn)
        del conn.tx[:n]
        want = bool(conn.tx)
        if want != conn.want_write:             # a slow reader: wait until it can take more
            conn.want_write = want
            self._sel.modify(conn.sock, selectors.EVENT_READ | (selectors.EVENT_WRITE if want else 0), conn)

    def _drop(self, conn: _Conn) -> None:
        self._conns.pop(conn.sock.fileno(), None)
        try:
            self._sel.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        conn.sock.close()

    def _close_sockets(self) -> None:
        for conn in list(self._conns.values()):
            self._drop(conn)
        for sock in [*self._listeners, self._wake_r, self._wake_w]:
            try:
                self._sel.unregister(sock)
            except (KeyError, ValueError):
                pass
            sock.close()
        self._listeners.clear()
        self._sel.close()


_SIOCOUTQNSD = 0x894B          # Linux: bytes in a TCP socket's send queue not yet sent


def _unsent(sock: socket.socket) -> int:
    """Bytes written to ``sock`` that TCP has not sent yet. (Not SIOCOUTQ, which counts
    unacknowledged bytes: the client's delayed ACK would hold it up for tens of ms.)"""
    return struct.unpack("i", fcntl.ioctl(sock.fileno(), _SIOCOUTQNSD, b"\0\0\0\0"))[0]


class _PtyBridge:
    """Two pty pairs joined master-to-master, so that the server and the client each open a
    real tty path (pymodbus's serial server and client both need a path, not an fd)."""

    def __init__(self) -> None:
        self._m_srv, self._s_srv = os.openpty()
        self._m_cli, self._s_cli = os.openpty()
        for fd in (self._s_srv, self._s_cli):
            tty.setraw(fd)              # no echo / line discipline before pyserial opens it
        self.server_path = os.ttyname(self._s_srv)
        self.client_path = os.ttyname(self._s_cli)
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._pump, name="virtual-ft-pty", daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        peer = {self._m_srv: self._m_cli, self._m_cli: self._m_srv}
        while True:
            ready, _, _ = select.select([self._m_srv, self._m_cli, self._wake_r], [], [])
            if self._wake_r in ready:
                return
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:         # EIO while no one holds the slave open
                    continue
                os.write(peer[fd], data)

    def close(self) -> None:
        os.write(self._wake_w, b"x")
        self._thread.join(2.0)
        for fd in (self._m_srv, self._s_srv, self._m_cli, self._s_cli, self._wake_r, self._wake_w):
            os.close(fd)
