"""Robotiq FT 300-class six-axis force–torque sensors over Modbus (RTU, or TCP via a gateway).

Two layers, one source of truth for the register map (``sim_backend.virtual_ft`` uses the
same codec for the other end of the wire):

* codec — :func:`wrench_from_registers` / :func:`registers_from_wrench`: holding registers
  180–185 = Fx, Fy, Fz (INT16, 0.01 N per count) and Mx, My, Mz (INT16, 0.001 N·m per count);
* driver — :class:`FTSensorSet`: one background thread per connection polls its sensors at
  ``poll_hz`` with pymodbus's synchronous client and publishes the latest sample by swapping
  a reference to an immutable object; :meth:`FTSensorSet.poll` only reads those references,
  so it never waits on I/O. For the lockstep simulation, ``open(start_thread=False)`` plus
  :meth:`FTSensorSet.poll_devices_once` does the same polling synchronously.

Written against pymodbus 3.16 (``device_id=`` keyword, ``trace_packet`` hook).
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import astuple, dataclass
from typing import Optional

import serial
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu.register_message import ReadHoldingRegistersResponse

from rig_runtime.config import FTBus, FTSensor

from .base import ConfigError, DeviceInitError, Driver, Freshness, Health

__all__ = [
    "REG_START", "REG_COUNT", "DEFAULT_UNIT_ID", "FORCE_COUNTS_PER_N", "TORQUE_COUNTS_PER_NM",
    "INT16_MIN", "INT16_MAX", "EXCEPTION_NAMES",
    "Wrench", "wrench_from_registers", "registers_from_wrench",
    "FTReading", "FTSensorSet",
]

# --------------------------------------------------------------------------- register map
REG_START = 180                 # holding register of Fx (0-based protocol address)
REG_COUNT = 6                   # Fx, Fy, Fz, Mx, My, Mz
DEFAULT_UNIT_ID = 9
FORCE_COUNTS_PER_N = 100.0      # 1 count = 0.01 N
TORQUE_COUNTS_PER_NM = 1000.0   # 1 count = 0.001 N·m
INT16_MIN, INT16_MAX = -32768, 32767
_SCALES = (FORCE_COUNTS_PER_N,) * 3 + (TORQUE_COUNTS_PER_NM,) * 3

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
_GATEWAY_CODES = (10, 11)       # the gateway answers, the sensor behind it does not
_OPEN_ATTEMPTS = 3              # requests per sensor at open() before it counts as unreachable


# --------------------------------------------------------------------------- codec
@dataclass(frozen=True, slots=True)
class Wrench:
    """Forces (N) and moments (N·m) in the sensor frame."""

    fx: float = 0.0
    fy: float = 0.0
    fz: float = 0.0
    mx: float = 0.0
    my: float = 0.0
    mz: float = 0.0

    def as_tuple(self) -> tuple[float, float, float, float, float, float]:
        return astuple(self)  # type: ignore[return-value]


def _to_signed(reg: int) -> int:
    """Unsigned 16-bit register as Modbus delivers it -> two's complement INT16."""
    if not 0 <= reg <= 0xFFFF:
        raise ValueError(f"register value {reg} outside 0..65535")
    return reg - 0x10000 if reg & 0x8000 else reg


def _to_register(value: float, counts_per_unit: float) -> int:
    """SI value -> unsigned 16-bit register (rounded, saturated at the INT16 range)."""
    if math.isnan(value):
        raise ValueError("NaN cannot be encoded as a register")
    counts = value * counts_per_unit
    if counts >= INT16_MAX:
        n = INT16_MAX
    elif counts <= INT16_MIN:
        n = INT16_MIN
    else:
        n = round(counts)
    return n & 0xFFFF


def wrench_from_registers(regs: Sequence[int]) -> Wrench:
    """Decode holding registers 180..185 (unsigned 0..65535) into a :class:`Wrench`."""
    if len(regs) != REG_COUNT:
        raise ValueError(f"expected {REG_COUNT} registers, got {len(regs)}")
    return Wrench(*(_to_signed(int(r)) / s for r, s in zip(regs, _SCALES)))


def registers_from_wrench(w: Wrench) -> list[int]:
    """Encode a :class:`Wrench` as the six registers a sensor would hold."""
    return [_to_register(v, s) for v, s in zip(w.as_tuple(), _SCALES)]


# --------------------------------------------------------------------------- readings
@dataclass(frozen=True, slots=True)
class FTReading:
    """What :meth:`FTSensorSet.poll` reports for one sensor."""

    wrench: Optional[Wrench]    # latest valid sample (kept while STALE/INVALID); None before the first
    t: float                    # clock time the sample was received (nan if none)
    age: float                  # now - t (inf if none)
    health: Health


@dataclass(frozen=True, slots=True)
class _Published:
    """Immutable state the poller swaps in; the only thing ``poll()`` reads."""

    wrench: Optional[Wrench]
    t: float
    cause: str                  # outcome of the latest transaction ("" if it was a valid sample)
    exc_code: Optional[int]     # set iff the latest transaction was a Modbus exception response
    timeouts: int
    errors: int
    bad_frames: int
    counters: tuple[tuple[str, int], ...]


_NOT_POLLED = _Published(None, math.nan, "not polled yet", None, 0, 0, 0, ())


class _Sensor:
    """Per-sensor state, written only by the thread that polls its connection."""

    def __init__(self, cfg: FTSensor, host: str, port: int) -> None:
        self.name = cfg.name
        self.unit = cfg.unit_id
        self.device = f"ft {cfg.name} ({_endpoint_text(cfg, host, port)})"
        self.wrench: Optional[Wrench] = None
        self.t = math.nan
        self.timeouts = self.errors = self.bad_frames = 0
        self.counters = {"samples": 0, "connects": 0, "connect_failures": 0, "disconnects": 0}
        self.pub = _NOT_POLLED

    def publish(self, cause: str, exc_code: Optional[int] = None) -> None:
        self.pub = _Published(self.wrench, self.t, cause, exc_code, self.timeouts, self.errors,
                              self.bad_frames, tuple(self.counters.items()))


def _endpoint_text(cfg: FTSensor, host: str, port: int) -> str:
    return f"{host}:{port}" if cfg.transport == "tcp" else cfg.serial_port


class _Link:
    """One connection (TCP socket or serial line) and the sensors polled over it."""

    def __init__(self, cfg: FTSensor, host: str, port: int, sensors: list[_Sensor]) -> None:
        self.cfg = cfg
        self.host = host
        self.port = port
        self.sensors = sensors
        self.client: ModbusTcpClient | ModbusSerialClient | None = None
        self.rx_seen = False        # bytes arrived for the current request (garbled vs. silent)
        self.retry_at = 0.0
        self.thread: Optional[threading.Thread] = None

    def trace(self, sending: bool, data: bytes) -> bytes:
        """pymodbus ``trace_packet`` hook: remember that the device sent something."""
        if not sending and data:
            self.rx_seen = True
        return data

    @property
    def connected(self) -> bool:
        return self.client is not None and self.client.connected


# --------------------------------------------------------------------------- driver
class FTSensorSet(Driver):
    """All force–torque sensors of ``cfg`` (one connection per distinct endpoint)."""

    name = "ft"

    def __init__(self, cfg: FTBus, endpoints: dict[str, tuple[str, int]] | None = None, *,
                 clock: Callable[[], float] = time.monotonic, reconnect_s: float = 0.5) -> None:
        super().__init__()
        self._cfg = cfg
        self._clock = clock
        self._reconnect_s = reconnect_s
        self._links = _group_links(cfg.sensors, endpoints or {})
        self._sensors = tuple(s for link in self._links for s in link.sensors)
        self._stop = threading.Event()
        self._start_thread = True

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self._sensors)

    # ------------------------------------------------------------------ lifecycle
    def open(self, start_thread: bool = True) -> None:  # type: ignore[override]
        """Connect and read every sensor once (blocking); then poll in the background
        unless ``start_thread`` is False (lockstep: call :meth:`poll_devices_once`)."""
        self._start_thread = start_thread
        super().open()

    def _do_open(self) -> None:
        self._stop.clear()
        try:
            for link in self._links:
                self._open_link(link)
        except BaseException:
            self._close_clients()
            raise
        if self._start_thread:
            for link in self._links:
                link.thread = threading.Thread(target=self._run, args=(link,),
                                               name=f"ft-poll-{link.sensors[0].name}", daemon=True)
                link.thread.start()

    def _do_close(self) -> None:
        self._stop.set()
        for link in self._links:
            if link.thread is not None:
                link.thread.join(timeout=self._cfg.timeout_s + 2.0)
                link.thread = None
        self._close_clients()

    def _close_clients(self) -> None:
        for link in self._links:
            if link.client is not None:
                link.client.close()
                link.client = None

    def _open_link(self, link: _Link) -> None:
        """Connect and require an answer from every sensor (up to ``_OPEN_ATTEMPTS`` requests);
        failures raise DeviceInitError naming the sensor and its endpoint."""
        for s in link.sensors:
            for _ in range(_OPEN_ATTEMPTS):
                if not link.connected:          # first time, or closed after a timeout (TCP)
                    try:
                        self._connect(link)
                    except OSError as exc:
                        raise DeviceInitError(s.device, f"cannot connect: {exc}") from exc
                self._transact(link, s)
                if s.wrench is not None or s.pub.exc_code is not None:
                    break
            code = s.pub.exc_code
            if s.wrench is None and (code is None or code in _GATEWAY_CODES):
                raise DeviceInitError(s.device, f"unit {s.unit} not reachable after "
                                      f"{_OPEN_ATTEMPTS} requests: {s.pub.cause}")

    # ------------------------------------------------------------------ cycle side
    def poll(self, now: float) -> dict[str, FTReading]:
        """Latest sample of every sensor with its age and health; never waits."""
        stale_s = self._cfg.stale_s
        return {s.name: _reading(s.pub, now, stale_s) for s in self._sensors}

    # ------------------------------------------------------------------ polling side
    def poll_devices_once(self) -> None:
        """Poll every sensor once, synchronously (lockstep simulation; no thread running)."""
        if not self._open:
            raise RuntimeError("FTSensorSet.poll_devices_once() before open()")
        if any(link.thread is not None for link in self._links):
            raise RuntimeError("FTSensorSet.poll_devices_once() while the poll threads run")
        for link in self._links:
            self._service(link, force_connect=True)

    def _run(self, link: _Link) -> None:
        """Background loop of one connection: poll at ``poll_hz`` on absolute deadlines."""
        period = 1.0 / self._cfg.poll_hz
        deadline = time.monotonic()
        while not self._stop.is_set():
            try:
                self._service(link, force_connect=False)
            except Exception as exc:           # noqa: BLE001 - the thread must survive; reported in health
                self._lost(link, f"poll thread error: {exc!r}")
            deadline += period
            delay = deadline - time.monotonic()
            if delay < 0.0:                     # overran (e.g. a timeout): no catch-up burst
                deadline, delay = time.monotonic(), 0.0
            self._stop.wait(delay)

    def _service(self, link: _Link, force_connect: bool) -> None:
        """(Re)connect if needed (with back-off), then one transaction per sensor of the link;
        a connection dropped mid-round (after a timeout) is reopened for the next sensor."""
        if not link.connected and not self._reconnect(link, force_connect):
            return
        for s in link.sensors:
            if self._stop.is_set():
                return
            if not link.connected and not self._reconnect(link, True):
                return
            self._transact(link, s)

    def _reconnect(self, link: _Link, force: bool) -> bool:
        now = time.monotonic()
        if not force and now < link.retry_at:
            return False
        try:
            self._connect(link)
        except OSError as exc:
            link.retry_at = now + self._reconnect_s
            for s in link.sensors:
                s.counters["connect_failures"] += 1
                s.publish(f"cannot connect: {exc}")
            return False
        return True

    def _connect(self, link: _Link) -> None:
        """Open the transport ourselves (to see the OS error), then hand it to pymodbus."""
        if link.client is not None:
            link.client.close()
        client = _make_client(link, self._cfg.timeout_s)
        client.socket = _open_transport(link, client, self._cfg.timeout_s)
        link.client = client
        for s in link.sensors:
            s.counters["connects"] += 1

    def _transact(self, link: _Link, s: _Sensor) -> None:
        """One read of registers 180..185; classify the outcome and publish it."""
        assert link.client is not None
        link.rx_seen = False
        try:
            rr = link.client.read_holding_registers(REG_START, count=REG_COUNT, device_id=s.unit)
        except ConnectionException as exc:
            return self._lost(link, f"connection lost: {exc}")
        except ModbusIOException as exc:
            if link.rx_seen:
                return self._bad_frame(link, s, f"garbled response: {exc}")
            return self._timeout(link, s)
        except OSError as exc:
            return self._lost(link, f"connection lost: {exc}")
        except (ModbusException, ValueError, IndexError) as exc:
            return self._bad_frame(link, s, f"undecodable response: {exc}")
        t = self._clock()
        if rr.isError():
            return self._exception(s, getattr(rr, "exception_code", -1))
        regs = getattr(rr, "registers", None)
        if not isinstance(rr, ReadHoldingRegistersResponse) or regs is None or len(regs) != REG_COUNT:
            return self._bad_frame(link, s, f"unexpected response {rr}")
        s.wrench, s.t = wrench_from_registers(regs), t
        s.counters["samples"] += 1
        s.publish("")

    def _timeout(self, link: _Link, s: _Sensor) -> None:
        s.timeouts += 1
        s.publish(f"no answer within {self._cfg.timeout_s:g} s (timeout)")
        _flush(link)

    def _bad_frame(self, link: _Link, s: _Sensor, cause: str) -> None:
        s.bad_frames += 1
        s.publish(cause)
        _flush(link)

    def _exception(self, s: _Sensor, code: int) -> None:
        s.errors += 1
        s.publish(f"Modbus exception {code} ({EXCEPTION_NAMES.get(code, 'unknown')})", exc_code=code)

    def _lost(self, link: _Link, cause: str) -> None:
        if link.client is not None:
            link.client.close()
        for s in link.sensors:
            s.counters["disconnects"] += 1
            s.publish(cause)


# --------------------------------------------------------------------------- helpers
def _reading(p: _Published, now: float, stale_s: float) -> FTReading:
    """Turn a published state into a reading: FRESH / STALE (with cause) / INVALID (code)."""
    age = now - p.t if p.wrench is not None else math.inf
    if p.exc_code is not None:
        state, cause = Freshness.INVALID, p.cause
    elif p.wrench is None:
        state, cause = Freshness.STALE, f"no sample yet ({p.cause})"
    elif age <= stale_s:
        state, cause = Freshness.FRESH, ""
    else:
        state, cause = Freshness.STALE, f"latest sample {age:.3f} s old" + (f" ({p.cause})" if p.cause else "")
    health = Health(state=state, cause=cause, bad_frames=p.bad_frames, timeouts=p.timeouts,
                    errors=p.errors, counters=dict(p.counters))
    return FTReading(p.wrench, p.t, age, health)


def _group_links(sensors: Sequence[FTSensor], endpoints: dict[str, tuple[str, int]]) -> list[_Link]:
    """One link per distinct connection; several RTU sensors may share one serial line."""
    names = [s.name for s in sensors]
    if len(set(names)) != len(names):
        raise ConfigError(None, "devices.ft.sensors", "distinct sensor names", names)
    unknown = set(endpoints) - set(names)
    if unknown:
        raise ConfigError(None, "devices.ft.sensors", "endpoint overrides for configured sensors only",
                          sorted(unknown))
    links: dict[tuple, _Link] = {}
    for cfg in sensors:
        host, port = endpoints.get(cfg.name, (cfg.host, cfg.port))
        key = _link_key(cfg, host, port)
        link = links.get(key)
        if link is None:
            links[key] = _Link(cfg, host, port, [_Sensor(cfg, host, port)])
            continue
        _check_shared(link, cfg)
        link.sensors.append(_Sensor(cfg, host, port))
    return list(links.values())


def _link_key(cfg: FTSensor, host: str, port: int) -> tuple:
    if cfg.transport == "tcp":
        return ("tcp", host, port)
    if not cfg.serial_port:
        raise ConfigError(None, f"devices.ft.sensors.{cfg.name}.serial_port",
                          "a serial port for transport 'rtu'")
    return ("rtu", cfg.serial_port)


def _check_shared(link: _Link, cfg: FTSensor) -> None:
    """Sensors on one connection need distinct unit ids (and one baud rate on a serial line)."""
    if cfg.unit_id in {s.unit for s in link.sensors}:
        raise ConfigError(None, f"devices.ft.sensors.{cfg.name}.unit_id",
                          "a unit id not used by another sensor on the same connection", cfg.unit_id)
    if cfg.transport == "rtu" and cfg.baudrate != link.cfg.baudrate:
        raise ConfigError(None, f"devices.ft.sensors.{cfg.name}.baudrate",
                          f"the baud rate of the other sensors on {cfg.serial_port}", cfg.baudrate)


def _make_client(link: _Link, timeout_s: float) -> ModbusTcpClient | ModbusSerialClient:
    """pymodbus sync client; retries=0 so one request costs at most one timeout."""
    cfg = link.cfg
    if cfg.transport == "tcp":
        return ModbusTcpClient(link.host, port=link.port, timeout=timeout_s, retries=0,
                               trace_packet=link.trace, name=f"ft-{cfg.name}")
    return ModbusSerialClient(cfg.serial_port, baudrate=cfg.baudrate, bytesize=8, parity="N",
                              stopbits=1, timeout=timeout_s, retries=0, trace_packet=link.trace,
                              name=f"ft-{cfg.name}")


def _open_transport(link: _Link, client, timeout_s: float):
    """Open the socket / serial port exactly as pymodbus's ``connect()`` would, but let the
    OSError (refused, unreachable, no such port) propagate instead of logging it."""
    if link.cfg.transport == "tcp":
        return socket.create_connection((link.host, link.port), timeout=timeout_s)
    port = serial.serial_for_url(link.cfg.serial_port, timeout=timeout_s, write_timeout=timeout_s,
                                 bytesize=8, parity="N", stopbits=1, baudrate=link.cfg.baudrate,
                                 exclusive=True)
    port.inter_byte_timeout = client.inter_byte_timeout
    return port


def _flush(link: _Link) -> None:
    """After a timeout or garbled frame on TCP, drop the connection so a late or partial
    answer cannot poison the next request (reconnected on the next poll). The serial
    client already discards stale input before each request."""
    if link.cfg.transport == "tcp" and link.client is not None:
        link.client.close()
