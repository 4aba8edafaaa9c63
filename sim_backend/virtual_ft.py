"""Simulated force–torque sensors: the other end of the FT 300 wire, behind real pymodbus servers.

One pymodbus server per sensor — Modbus TCP on 127.0.0.1 (a free port unless given), or
Modbus RTU on a pseudo-terminal pair — all served by one asyncio loop on a background
thread. Holding registers 180..185 are filled from the latest :class:`Wrench` with the
driver's own codec (:func:`drivers.ft300.registers_from_wrench`), so there is one register
map for both ends. Faults are injected per sensor and act on the wire:

=============== ==========================================================================
``dropout``     the request is processed but no answer is sent (the client times out)
``corrupt``     ``mode="garble"`` (default): TCP — byte count of the answer set to 0xFF,
                undecodable; RTU — CRC inverted. ``mode="truncate"``: only the first half
                of the answer frame is sent
``stuck``       registers frozen at their value when the fault was injected
``offset``      ``fx=…, …, mz=…`` (SI) added to the wrench before encoding
``out_of_range`` answer with a Modbus exception response, ``code=4`` (device failure) unless given
=============== ==========================================================================
"""

from __future__ import annotations

import asyncio
import os
import select
import threading
import tty
from collections.abc import Mapping, Sequence
from dataclasses import fields, replace
from typing import Any, Optional

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.ft300 import DEFAULT_UNIT_ID, REG_COUNT, REG_START, Wrench, registers_from_wrench

__all__ = ["VirtualFTServer", "FAULT_KINDS"]

FAULT_KINDS = ("dropout", "corrupt", "stuck", "offset", "out_of_range")
_WRENCH_FIELDS = tuple(f.name for f in fields(Wrench))
_START_TIMEOUT_S = 5.0


class VirtualFTServer:
    """Simulated FT sensors; ``endpoints`` (TCP) and ``serial_ports`` (RTU) say where to connect."""

    def __init__(self, names: Sequence[str], unit_id: int = DEFAULT_UNIT_ID, host: str = "127.0.0.1",
                 ports: Optional[Mapping[str, int]] = None, rtu: Sequence[str] = (),
                 baudrate: int = 19200) -> None:
        if len(set(names)) != len(names):
            raise ValueError(f"sensor names must be distinct: {list(names)}")
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
        self._servers: list[ModbusTcpServer | ModbusSerialServer] = []
        self._bridges: list[_PtyBridge] = []
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._thread: Optional[threading.Thread] = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "VirtualFTServer":
        """Start the loop thread and every server; returns once all are listening."""
        if self._thread is not None:
            return self
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run_loop, name="virtual-ft", daemon=True)
        self._thread.start()
        try:
            asyncio.run_coroutine_threadsafe(self._start_servers(), self._loop).result(_START_TIMEOUT_S)
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Stop every server, the loop thread and the pty bridges. Idempotent."""
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

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------------ plant side
    def set_wrench(self, name: str, w: Wrench) -> None:
        """New physical value for one sensor (any thread)."""
        self._check_name(name)
        with self._lock:
            self._wrenches[name] = w

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

    def clear(self, name: str, kind: Optional[str] = None) -> None:
        """End one fault, or all faults of the sensor when ``kind`` is None."""
        self._check_name(name)
        if kind is not None and kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {kind!r} (known: {', '.join(FAULT_KINDS)})")
        with self._lock:
            self._faults[name] = {} if kind is None else {k: v for k, v in self._faults[name].items() if k != kind}

    def _check_name(self, name: str) -> None:
        if name not in self._wrenches:
            raise KeyError(f"no simulated FT sensor {name!r} (have: {', '.join(self.names)})")

    def _registers_locked(self, name: str) -> list[int]:
        """Registers the sensor would answer with now (caller holds the lock)."""
        faults = self._faults[name]
        if "stuck" in faults:
            return list(faults["stuck"]["registers"])
        w = self._wrenches[name]
        if "offset" in faults:
            off = faults["offset"]
            w = replace(w, **{k: getattr(w, k) + off.get(k, 0.0) for k in _WRENCH_FIELDS})
        return registers_from_wrench(w)

    # ------------------------------------------------------------------ server side
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
            device = SimDevice(id=self.unit_id, action=self._make_action(name),
                               simdata=[SimData(REG_START, values=[0] * REG_COUNT,
                                                datatype=DataType.REGISTERS, readonly=True)])
            tracer = self._make_tracer(name)
            if name in self._rtu:
                bridge = _PtyBridge()
                self._bridges.append(bridge)
                server = ModbusSerialServer(device, port=bridge.server_path, baudrate=self.baudrate,
                                            trace_packet=tracer)
            else:
                server = ModbusTcpServer(device, address=(self.host, self._ports.get(name, 0)),
                                         trace_packet=tracer)
            self._servers.append(server)
            await server.serve_forever(background=True)
            if name in self._rtu:
                self.serial_ports[name] = self._bridges[-1].client_path
            else:
                self.endpoints[name] = (self.host, server.transport.sockets[0].getsockname()[1])

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
                    return ExcCodes(fault["code"])
                registers[0:REG_COUNT] = self._registers_locked(name)
                self._served[name] += 1
            return None
        return action

    def _make_tracer(self, name: str):
        """trace_packet hook: drop or mangle outgoing frames while a wire fault is active."""
        rtu = name in self._rtu

        def trace(sending: bool, data: bytes) -> bytes:
            if not sending:
                return data
            faults = self._faults[name]
            if "dropout" in faults:
                return b""
            if "corrupt" in faults:
                return _mangle(data, faults["corrupt"]["mode"], rtu)
            return data
        return trace


def _check_fault(kind: str, params: dict[str, Any]) -> dict[str, Any]:
    """Validate fault parameters; returns them with defaults filled in."""
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
