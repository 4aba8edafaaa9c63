"""Robotiq FT 300-class six-axis force–torque sensors over Modbus (RTU, or TCP via a gateway).

Layers, each written once and shared with ``sim_backend.virtual_ft`` (the other end):

* register codec — :func:`wrench_from_registers` / :func:`registers_from_wrench`: holding
  registers 180–185 = Fx, Fy, Fz (INT16, 0.01 N per count) and Mx, My, Mz (INT16, 0.001 N·m);
* Modbus TCP framing — :mod:`drivers.ft_modbus` (function 0x03 only). TCP links use it
  directly, so requests to several sensors can be in flight at once; RTU links use
  pymodbus's serial client (imported only when an RTU sensor is configured);
* polling — ``_PollCore``: connects, reads one sample per sensor per round, classifies the
  outcome (sample, Modbus exception, timeout, bad frame, lost connection) and publishes an
  immutable ``_Published`` per sensor;
* driver — :class:`FTSensorSet`. Where the polling runs:

  - ``poller="process"`` (default for ``open()``): the same ``_PollCore`` in a separate OS
    process (:mod:`drivers.ft_process`), publishing into shared memory behind a seqlock.
    The Modbus I/O then never holds the runtime's interpreter lock (pymodbus held it for up
    to ~1 ms per call and delayed the 5 ms loop thread);
  - ``poller="thread"``: one thread per connection inside the runtime process (as before);
  - ``open(start_thread=False)`` + :meth:`FTSensorSet.poll_devices_once`: lockstep
    simulation, in-process and deterministic; one round sends the requests of all TCP
    sensors before collecting the replies.

  :meth:`FTSensorSet.poll` never waits on I/O and reuses what it built for a sample until
  a new one (or a new outcome) is published.

Written against pymodbus 3.16 for RTU (``device_id=`` keyword, ``trace_packet`` hook).
"""

from __future__ import annotations

import math
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Optional

from rig_runtime.clock import as_background_thread
from rig_runtime.config import FTBus, FTSensor

from .base import ConfigError, DeviceInitError, Driver, Freshness, Health
from .ft_modbus import EXCEPTION_NAMES, decode_read_response, encode_read_request, exception_text, frame_length

__all__ = [
    "REG_START", "REG_COUNT", "DEFAULT_UNIT_ID", "FORCE_COUNTS_PER_N", "TORQUE_COUNTS_PER_NM",
    "INT16_MIN", "INT16_MAX", "EXCEPTION_NAMES", "POLLERS",
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
_U16x6, _I16x6 = struct.Struct("=6H"), struct.Struct("=6h")   # two's complement by reinterpretation

_GATEWAY_CODES = (10, 11)       # the gateway answers, the sensor behind it does not
_OPEN_ATTEMPTS = 3              # requests per sensor at open() before it counts as unreachable
POLLERS = ("process", "thread")
COUNTER_NAMES = ("samples", "connects", "connect_failures", "disconnects")


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
        return (self.fx, self.fy, self.fz, self.mx, self.my, self.mz)


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
    try:
        fx, fy, fz, mx, my, mz = _I16x6.unpack(_U16x6.pack(*regs))
    except struct.error:                # out of 0..65535 or not integers: the checked path says which
        fx, fy, fz, mx, my, mz = (_to_signed(int(r)) for r in regs)
    return Wrench(fx / FORCE_COUNTS_PER_N, fy / FORCE_COUNTS_PER_N, fz / FORCE_COUNTS_PER_N,
                  mx / TORQUE_COUNTS_PER_NM, my / TORQUE_COUNTS_PER_NM, mz / TORQUE_COUNTS_PER_NM)


def registers_from_wrench(w: Wrench) -> list[int]:
    """Encode a :class:`Wrench` as the six registers a sensor would hold."""
    return [_to_register(v, s) for v, s in zip(w.as_tuple(), _SCALES)]


# --------------------------------------------------------------------------- readings
class FTReading(NamedTuple):
    """What :meth:`FTSensorSet.poll` reports for one sensor (a new object per call; its
    ``health`` is shared between calls while nothing changed — treat it as read-only).
    A named tuple, like the other drivers' readings: built every 5 ms, it costs a third
    of a frozen dataclass."""

    wrench: Optional[Wrench]    # latest valid sample (kept while STALE/INVALID); None before the first
    t: float                    # clock time the sample was received (nan if none)
    age: float                  # now - t (inf if none)
    health: Health



@dataclass(frozen=True, slots=True)
class _Published:
    """Immutable outcome of a sensor's latest transaction; all that ``poll()`` reads."""

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
    """Per-sensor state, written only by the thread that polls its connection; ``sink``
    (the poll process's shared-memory writer) gets every publication too."""

    def __init__(self, cfg: FTSensor, host: str, port: int) -> None:
        self.name = cfg.name
        self.unit = cfg.unit_id
        self.device = f"ft {cfg.name} ({_endpoint_text(cfg, host, port)})"
        self.wrench: Optional[Wrench] = None
        self.t = math.nan
        self.timeouts = self.errors = self.bad_frames = 0
        self.counters = dict.fromkeys(COUNTER_NAMES, 0)
        self.pub = _NOT_POLLED
        self.sink: Optional[Callable[[_Published], None]] = None

    def publish(self, cause: str, exc_code: Optional[int] = None) -> None:
        self.pub = p = _Published(self.wrench, self.t, cause, exc_code, self.timeouts, self.errors,
                                  self.bad_frames, tuple(self.counters.items()))
        if self.sink is not None:
            self.sink(p)


def _endpoint_text(cfg: FTSensor, host: str, port: int) -> str:
    return f"{host}:{port}" if cfg.transport == "tcp" else cfg.serial_port


# --------------------------------------------------------------------------- links
class _Link:
    """One connection (TCP socket or serial line) and the sensors polled over it."""

    rtu = False

    def __init__(self, cfg: FTSensor, host: str, port: int, sensors: list[_Sensor]) -> None:
        self.cfg = cfg
        self.host = host
        self.port = port
        self.sensors = sensors
        self.retry_at = 0.0
        self.thread: Optional[threading.Thread] = None

    @property
    def connected(self) -> bool:
        raise NotImplementedError

    def connect(self, timeout_s: float) -> None:
        """Open the transport (closing an old one); OSError (refused, unreachable, no such
        port) propagates."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class _TcpLink(_Link):
    """Modbus TCP with :mod:`drivers.ft_modbus`: a non-blocking socket, one request in
    flight, the reply assembled from whatever ``recv`` returns."""

    def __init__(self, *a: Any) -> None:
        super().__init__(*a)
        self.sock: Optional[socket.socket] = None
        self.tid = 0
        self.buf = bytearray()
        self.pending: Optional[_Sensor] = None

    @property
    def connected(self) -> bool:
        return self.sock is not None

    def connect(self, timeout_s: float) -> None:
        self.close()
        sock = socket.create_connection((self.host, self.port), timeout=timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        self.sock = sock

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        self.pending = None

    def send(self, s: _Sensor) -> None:
        """Send the request for ``s`` (12 bytes into an idle socket: never blocks)."""
        assert self.sock is not None
        self.tid = (self.tid + 1) & 0xFFFF
        self.buf = bytearray()
        self.pending = s
        frame = encode_read_request(self.tid, s.unit, REG_START, REG_COUNT)
        if self.sock.send(frame) != len(frame):
            raise OSError("request only partly sent")


class _RtuLink(_Link):
    """Modbus RTU through pymodbus's synchronous serial client (blocking per request)."""

    rtu = True

    def __init__(self, *a: Any) -> None:
        super().__init__(*a)
        self.client: Any = None
        self.rx_seen = False        # bytes arrived for the current request (garbled vs. silent)

    @property
    def connected(self) -> bool:
        return self.client is not None and self.client.connected

    def trace(self, sending: bool, data: bytes) -> bytes:
        """pymodbus ``trace_packet`` hook: remember that the device sent something."""
        if not sending and data:
            self.rx_seen = True
        return data

    def connect(self, timeout_s: float) -> None:
        """Open the serial port ourselves (to see the OS error), then hand it to pymodbus."""
        import serial
        from pymodbus.client import ModbusSerialClient

        self.close()
        cfg = self.cfg
        client = ModbusSerialClient(cfg.serial_port, baudrate=cfg.baudrate, bytesize=8, parity="N",
                                    stopbits=1, timeout=timeout_s, retries=0, trace_packet=self.trace,
                                    name=f"ft-{cfg.name}")
        port = serial.serial_for_url(cfg.serial_port, timeout=timeout_s, write_timeout=timeout_s,
                                     bytesize=8, parity="N", stopbits=1, baudrate=cfg.baudrate,
                                     exclusive=True)
        port.inter_byte_timeout = client.inter_byte_timeout
        client.socket = port
        self.client = client

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None


# --------------------------------------------------------------------------- polling
class _PollCore:
    """The polling side, wherever it runs (runtime thread, lockstep, poll process)."""

    def __init__(self, cfg: FTBus, endpoints: dict[str, tuple[str, int]], clock: Callable[[], float],
                 reconnect_s: float) -> None:
        self.cfg = cfg
        self.clock = clock
        self.reconnect_s = reconnect_s
        self.links = _group_links(cfg.sensors, endpoints)
        self.sensors = tuple(s for link in self.links for s in link.sensors)
        self.stop = threading.Event()

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Connect and require an answer from every sensor (blocking); DeviceInitError names
        the sensor and its endpoint. Closes what it opened on failure."""
        self.stop.clear()
        try:
            for link in self.links:
                self._open_link(link)
        except BaseException:
            self.close_links()
            raise

    def start_threads(self) -> None:
        for link in self.links:
            link.thread = threading.Thread(target=self.run, args=(link,),
                                           name=f"ft-poll-{link.sensors[0].name}", daemon=True)
            link.thread.start()

    @property
    def threads_running(self) -> bool:
        return any(link.thread is not None for link in self.links)

    def close(self) -> None:
        """Stop the poll threads (each finishes its request: ≤ ``timeout_s``), close links."""
        self.stop.set()
        for link in self.links:
            if link.thread is not None:
                link.thread.join(timeout=self.cfg.timeout_s + 2.0)
                link.thread = None
        self.close_links()

    def close_links(self) -> None:
        for link in self.links:
            link.close()

    def _open_link(self, link: _Link) -> None:
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

    # ------------------------------------------------------------------ rounds
    def run(self, link: _Link) -> None:
        """Poll thread of one connection: a round at ``poll_hz`` on absolute deadlines (no
        catch-up burst after a timeout). Runs SCHED_OTHER: a thread inherits its creator's
        policy, and the runtime may already run SCHED_FIFO."""
        as_background_thread()
        period = 1.0 / self.cfg.poll_hz
        deadline = time.monotonic()
        links = [link]
        while not self.stop.is_set():
            try:
                self.round(links, force_connect=False)
            except Exception as exc:           # noqa: BLE001 - the thread must survive; reported in health
                self._lost(link, f"poll thread error: {exc!r}")
            deadline += period
            delay = deadline - time.monotonic()
            if delay < 0.0:                     # overran (e.g. a timeout): no catch-up burst
                deadline, delay = time.monotonic(), 0.0
            self.stop.wait(delay)

    def round(self, links: Sequence[_Link], force_connect: bool) -> None:
        """One transaction per sensor of ``links``. Step ``i`` sends the request of every
        TCP link's ``i``-th sensor, does the RTU ones (blocking) meanwhile, then collects the
        TCP replies together: one timeout, not one round trip per sensor. A link whose
        (re)connect fails (or is backing off) sits the round out; a connection dropped
        mid-round (after a timeout) is reopened for the link's next sensor."""
        skip: set[int] = set()
        for i in range(max(len(link.sensors) for link in links)):
            if self.stop.is_set():
                return
            inflight: list[_TcpLink] = []
            for link in links:
                if i >= len(link.sensors) or id(link) in skip:
                    continue
                if not link.connected and not self._reconnect(link, force_connect or i > 0):
                    skip.add(id(link))
                    continue
                s = link.sensors[i]
                if link.rtu:
                    self._transact_rtu(link, s)     # type: ignore[arg-type]
                elif self._send(link, s):           # type: ignore[arg-type]
                    inflight.append(link)           # type: ignore[arg-type]
            if inflight:
                self._collect(inflight)

    def _transact(self, link: _Link, s: _Sensor) -> None:
        """One complete transaction (open-time reads)."""
        if link.rtu:
            self._transact_rtu(link, s)     # type: ignore[arg-type]
        elif self._send(link, s):           # type: ignore[arg-type]
            self._collect([link])           # type: ignore[list-item]

    def _reconnect(self, link: _Link, force: bool) -> bool:
        now = time.monotonic()
        if not force and now < link.retry_at:
            return False
        try:
            self._connect(link)
        except OSError as exc:
            link.retry_at = now + self.reconnect_s
            for s in link.sensors:
                s.counters["connect_failures"] += 1
                s.publish(f"cannot connect: {exc}")
            return False
        return True

    def _connect(self, link: _Link) -> None:
        link.connect(self.cfg.timeout_s)
        for s in link.sensors:
            s.counters["connects"] += 1

    # ------------------------------------------------------------------ TCP
    def _send(self, link: _TcpLink, s: _Sensor) -> bool:
        try:
            link.send(s)
        except OSError as exc:
            self._lost(link, f"connection lost: {exc}")
            return False
        return True

    def _collect(self, inflight: list[_TcpLink]) -> None:
        """Wait for the replies of requests just sent (at most ``timeout_s``), classify each."""
        deadline = time.monotonic() + self.cfg.timeout_s
        pending = {link.sock.fileno(): link for link in inflight}   # type: ignore[union-attr]
        poller = select.poll()
        for fd in pending:
            poller.register(fd, select.POLLIN)
        while pending:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                break
            for fd, _ in poller.poll(remaining * 1e3):
                if self._on_readable(pending[fd]):
                    poller.unregister(fd)
                    del pending[fd]
        for link in pending.values():
            s = link.pending
            assert s is not None
            if link.buf:
                self._bad_frame(link, s, f"truncated response: {len(link.buf)} bytes, then nothing "
                                f"within {self.cfg.timeout_s:g} s")
            else:
                self._timeout(link, s)

    def _on_readable(self, link: _TcpLink) -> bool:
        """Read what arrived; True once the transaction is over (reply, garbage, EOF)."""
        s = link.pending
        assert s is not None and link.sock is not None
        try:
            data = link.sock.recv(512)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError as exc:
            self._lost(link, f"connection lost: {exc}")
            return True
        if not data:
            self._lost(link, "connection lost: closed by the peer")
            return True
        buf = link.buf
        buf += data
        try:
            n = frame_length(buf)
            if n is None or len(buf) < n:
                return False
            if len(buf) > n:
                raise ValueError(f"{len(buf) - n} bytes after the frame")
            regs, code = decode_read_response(buf, link.tid, s.unit, REG_COUNT)
        except ValueError as exc:
            self._bad_frame(link, s, f"garbled response: {exc}")
            return True
        link.pending = None
        t = self.clock()
        if code is not None:
            self._exception(s, code)
        else:
            self._sample(s, regs, t)        # type: ignore[arg-type]
        return True

    # ------------------------------------------------------------------ RTU
    def _transact_rtu(self, link: _RtuLink, s: _Sensor) -> None:
        """One read of registers 180..185 with pymodbus's serial client."""
        from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
        from pymodbus.pdu.register_message import ReadHoldingRegistersResponse

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
        t = self.clock()
        if rr.isError():
            return self._exception(s, getattr(rr, "exception_code", -1))
        regs = getattr(rr, "registers", None)
        if not isinstance(rr, ReadHoldingRegistersResponse) or regs is None or len(regs) != REG_COUNT:
            return self._bad_frame(link, s, f"unexpected response {rr}")
        self._sample(s, regs, t)

    # ------------------------------------------------------------------ outcomes
    def _sample(self, s: _Sensor, regs: Sequence[int], t: float) -> None:
        s.wrench, s.t = wrench_from_registers(regs), t
        s.counters["samples"] += 1
        s.publish("")

    def _timeout(self, link: _Link, s: _Sensor) -> None:
        s.timeouts += 1
        s.publish(f"no answer within {self.cfg.timeout_s:g} s (timeout)")
        _flush(link)

    def _bad_frame(self, link: _Link, s: _Sensor, cause: str) -> None:
        s.bad_frames += 1
        s.publish(cause)
        _flush(link)

    def _exception(self, s: _Sensor, code: int) -> None:
        s.errors += 1
        s.publish(exception_text(code), exc_code=code)

    def _lost(self, link: _Link, cause: str) -> None:
        link.close()
        for s in link.sensors:
            s.counters["disconnects"] += 1
            s.publish(cause)


def _flush(link: _Link) -> None:
    """After a timeout or garbled frame on TCP, drop the connection so a late or partial
    answer cannot poison the next request (reconnected on the next poll). The serial
    client already discards stale input before each request."""
    if not link.rtu:
        link.close()


# --------------------------------------------------------------------------- loop side
class _View:
    """What ``poll()`` built from a sensor's latest publication, kept until the next one."""

    __slots__ = ("name", "sensor", "pub", "has_sample", "fixed", "fresh")

    def __init__(self, sensor: _Sensor) -> None:
        self.name = sensor.name
        self.sensor = sensor
        self.pub: Optional[_Published] = None
        self.has_sample = False
        self.fixed: Optional[Health] = None     # health regardless of age (INVALID / no sample yet)
        self.fresh: Optional[Health] = None     # health while the sample is young enough

    def rebuild(self, p: _Published) -> None:
        self.pub = p
        self.has_sample = p.wrench is not None
        if p.exc_code is not None:
            self.fixed = _health(p, Freshness.INVALID, p.cause)
        elif p.wrench is None:
            self.fixed = _health(p, Freshness.STALE, f"no sample yet ({p.cause})")
        else:
            self.fixed = None
            self.fresh = _health(p, Freshness.FRESH, "")


def _health(p: _Published, state: Freshness, cause: str) -> Health:
    return Health(state=state, cause=cause, bad_frames=p.bad_frames, timeouts=p.timeouts,
                  errors=p.errors, counters=dict(p.counters))


# --------------------------------------------------------------------------- driver
class FTSensorSet(Driver):
    """All force–torque sensors of ``cfg`` (one connection per distinct endpoint).

    ``poller`` says where ``open()`` (with ``start_thread=True``) polls: ``"process"`` (a
    separate OS process; timestamps from ``clock`` there, so it must be picklable and
    system-wide — ``time.monotonic`` is) or ``"thread"`` (threads in this process).
    ``poller_cpus`` optionally pins the poll process (e.g. away from the loop's CPU).
    """

    name = "ft"

    def __init__(self, cfg: FTBus, endpoints: dict[str, tuple[str, int]] | None = None, *,
                 clock: Callable[[], float] = time.monotonic, reconnect_s: float = 0.5,
                 poller: str = "process", poller_cpus: Optional[Iterable[int]] = None) -> None:
        super().__init__()
        if poller not in POLLERS:
            raise ValueError(f"poller must be one of {', '.join(POLLERS)}, got {poller!r}")
        self._cfg = cfg
        self._poller = poller
        self._poller_cpus = None if poller_cpus is None else tuple(poller_cpus)
        self._endpoints = dict(endpoints or {})
        self._core = _PollCore(cfg, self._endpoints, clock, reconnect_s)
        self._sensors = self._core.sensors
        self._views = tuple(_View(s) for s in self._sensors)
        self._stale_s = cfg.stale_s
        self._start_thread = True
        self._proc: Any = None              # ft_process.PollProcess while the poll process runs
        self._inflight: list = []              # lockstep: links whose reply poll_devices_finish collects
        self._refresh: Optional[Callable[[], None]] = None

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self._sensors)

    @property
    def poll_process(self) -> Optional[Any]:
        """The running poll process (``multiprocessing.Process``), or None."""
        return None if self._proc is None else self._proc.process

    # ------------------------------------------------------------------ lifecycle
    def open(self, start_thread: bool = True) -> None:  # type: ignore[override]
        """Connect and read every sensor once (blocking); then poll in the background
        (``poller``) unless ``start_thread`` is False (lockstep: call :meth:`poll_devices_once`)."""
        self._start_thread = start_thread
        super().open()

    def _do_open(self) -> None:
        if not self._start_thread:
            self._core.open()
        elif self._poller == "thread":
            self._core.open()
            self._core.start_threads()
        else:
            from .ft_process import PollProcess

            proc = PollProcess(self._cfg, self._endpoints, self._core, cpus=self._poller_cpus)
            proc.start()                    # DeviceInitError as open() in-process would raise
            self._proc = proc
            self._refresh = proc.reader.refresh
            self._refresh()                 # the samples the child read while opening

    def _do_close(self) -> None:
        proc, self._proc, self._refresh = self._proc, None, None
        if proc is not None:
            proc.close()                    # last states stay in the sensors for poll() after close
        else:
            self._core.close()

    # ------------------------------------------------------------------ cycle side
    def poll(self, now: float) -> dict[str, FTReading]:
        """Latest sample of every sensor with its age and health; never waits. Builds
        health objects only when a new outcome was published (or while STALE)."""
        refresh = self._refresh
        if refresh is not None:
            refresh()
        stale_s = self._stale_s
        out = {}
        for v in self._views:
            p = v.sensor.pub
            if p is not v.pub:
                v.rebuild(p)
            h = v.fixed
            if h is None:
                age = now - p.t
                h = v.fresh if age <= stale_s else self._stale(p, age)
            else:
                age = now - p.t if v.has_sample else math.inf
            out[v.name] = FTReading(p.wrench, p.t, age, h)
        return out

    def _stale(self, p: _Published, age: float) -> Health:
        cause = p.cause
        if self._proc is not None and (dead := self._proc.death_cause()):
            cause = dead
        return _health(p, Freshness.STALE, f"latest sample {age:.3f} s old" + (f" ({cause})" if cause else ""))

    # ------------------------------------------------------------------ polling side
    def poll_devices_once(self) -> None:
        """Poll every sensor once, synchronously (lockstep simulation; no poller running)."""
        self.poll_devices_start()
        self.poll_devices_finish()

    def poll_devices_start(self) -> None:
        """Lockstep, first half of :meth:`poll_devices_once`: send every sensor's request
        (one TCP sensor per connection, the usual layout) and return; the simulator can
        answer them in its own thread before :meth:`poll_devices_finish` collects the
        replies. Other layouts (RTU, several sensors on one gateway) do the whole round here."""
        if not self._open:
            raise RuntimeError("FTSensorSet.poll_devices_start() before open()")
        if self._proc is not None or self._core.threads_running:
            raise RuntimeError("FTSensorSet.poll_devices_start() while the poller runs")
        core = self._core
        links = core.links
        self._inflight = []
        if any(link.rtu or len(link.sensors) != 1 for link in links):
            core.round(links, force_connect=True)
            return
        for link in links:
            if not link.connected and not core._reconnect(link, True):
                continue
            if core._send(link, link.sensors[0]):       # type: ignore[arg-type]
                self._inflight.append(link)

    def poll_devices_finish(self) -> None:
        """Lockstep, second half: wait for the replies of :meth:`poll_devices_start`'s
        requests (at most the configured timeout) and publish them."""
        inflight, self._inflight = self._inflight, []
        if inflight:
            self._core._collect(inflight)


# --------------------------------------------------------------------------- helpers
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
            cls = _TcpLink if cfg.transport == "tcp" else _RtuLink
            links[key] = cls(cfg, host, port, [_Sensor(cfg, host, port)])
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
