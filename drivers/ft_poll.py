"""The F/T polling core: connections, transactions, the classification of their outcomes
and what is published per sensor — shared by every poller (:mod:`drivers.ft_pollers`:
thread, inline; :mod:`drivers.ft_process`: a separate process).

* links — one per distinct connection: :class:`TcpLink` (Modbus TCP with
  :mod:`drivers.ft_modbus` on a non-blocking socket, one request in flight; an endpoint
  ``("mem://NAME", port)`` is an in-process stream of :mod:`rig_runtime.wires` instead,
  which carries the same frames and answers the same calls) or
  :class:`RtuLink` (pymodbus's synchronous serial client, imported only for RTU sensors);
* :class:`PollCore` — connects, sends, reads, and classifies each transaction's outcome
  (sample, saturated sample, Modbus exception, timeout, bad frame, lost connection, failed
  connect) into an immutable :class:`Published` per sensor. Its blocking parts (``open``,
  ``round``) serve the open-time reads and the thread/process pollers; the non-blocking
  parts (``send``, ``on_readable``, ``give_up``, the outcomes) are what the inline poller
  uses too;
* :class:`Poller` — the interface of the three pollers: ``start()`` (blocking: connect and
  read every sensor once), ``latest(now)`` (never blocks), ``failure()``, ``close()``.

Timestamps of samples come from the core's ``clock`` (``time.monotonic`` for the thread and
process pollers, the ``now`` of the driver's ``poll(now)`` for the inline one).
"""

from __future__ import annotations

import abc
import errno
import math
import os
import select
import socket
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple, Optional

from rig_runtime import wires
from rig_runtime.clock import as_background_thread
from rig_runtime.config import FTBus, FTSensor

from rig_runtime.errors import ConfigError, DeviceInitError
from .ft_codec import REG_COUNT, REG_START, Wrench, wrench_from_registers
from .ft_modbus import decode_read_response, encode_read_request, exception_text, frame_length

__all__ = ["COUNTER_NAMES", "Published", "NOT_POLLED", "Sensor", "Link", "TcpLink", "RtuLink",
           "PollCore", "Poller"]

COUNTER_NAMES = ("samples", "connects", "connect_failures", "disconnects")
_GATEWAY_CODES = (10, 11)       # the gateway answers, the sensor behind it does not
_OPEN_ATTEMPTS = 3              # requests per sensor at open() before it counts as unreachable


# --------------------------------------------------------------------------- publication
class Published(NamedTuple):
    """Immutable outcome of a sensor's latest transaction: all the driver's ``poll()`` reads.
    Every publication increments one count (a sample, timeout, error, …). A named tuple: one
    is made per transaction (a third of a frozen dataclass's cost to build)."""

    wrench: Optional[Wrench]    # latest sample (kept after failures; a saturated one too, see
                                # Wrench.saturation); None before the first
    t: float                    # clock time the sample was received (nan if none)
    cause: str                  # outcome of the latest transaction ("" if it was a valid sample)
    exc_code: Optional[int]     # set iff the latest transaction was a Modbus exception response
    timeouts: int
    errors: int                 # exception responses and saturated samples
    bad_frames: int
    counters: tuple[tuple[str, int], ...]
    link_down: bool = False     # the latest outcome was a lost connection or a failed connect
    saturation: str = ""        # ``wrench.saturation``, worked out once where the wrench was decoded


NOT_POLLED = Published(None, math.nan, "not polled yet", None, 0, 0, 0, ())


class Sensor:
    """Per-sensor state, written only by whoever polls its connection; ``sink`` (the poll
    process's shared-memory writer) gets every publication too."""

    def __init__(self, cfg: FTSensor, host: str, port: int) -> None:
        self.name = cfg.name
        self.unit = cfg.unit_id
        self.device = f"ft {cfg.name} ({_endpoint_text(cfg, host, port)})"
        self.wrench: Optional[Wrench] = None
        self.t = math.nan
        self.saturation = ""            # the wrench's (Wrench.saturation), kept with it
        self.timeouts = self.errors = self.bad_frames = 0
        self.counters = dict.fromkeys(COUNTER_NAMES, 0)
        self.pub = NOT_POLLED
        self.sink: Optional[Callable[[Published], None]] = None

    def publish(self, cause: str, exc_code: Optional[int] = None, link_down: bool = False) -> None:
        self.pub = p = Published(self.wrench, self.t, cause, exc_code, self.timeouts, self.errors,
                                 self.bad_frames, tuple(self.counters.items()), link_down, self.saturation)
        if self.sink is not None:
            self.sink(p)


def _endpoint_text(cfg: FTSensor, host: str, port: int) -> str:
    return f"{host}:{port}" if cfg.transport == "tcp" else cfg.serial_port


# --------------------------------------------------------------------------- links
class Link:
    """One connection (TCP socket or serial line) and the sensors polled over it."""

    rtu = False

    def __init__(self, cfg: FTSensor, host: str, port: int, sensors: list[Sensor]) -> None:
        self.cfg = cfg
        self.host = host
        self.port = port
        self.sensors = sensors
        self.retry_at = -math.inf
        self.thread: Optional[threading.Thread] = None

    @property
    def connected(self) -> bool:
        raise NotImplementedError

    def connect(self, timeout_s: float) -> None:
        """Open the transport (closing an old one), blocking; OSError (refused, unreachable,
        no such port) propagates."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class TcpLink(Link):
    """Modbus TCP with :mod:`drivers.ft_modbus`: a non-blocking socket, one request in
    flight, the reply assembled from whatever ``recv`` returns. A ``mem://`` host is an
    in-process stream (:class:`rig_runtime.wires.WireEnd`: ``send``/``recv``/``close`` as a
    non-blocking socket answers them; a connect completes within the call)."""

    def __init__(self, *a: Any) -> None:
        super().__init__(*a)
        self.sock: Optional[socket.socket] = None
        self.connecting = False         # a non-blocking connect in progress (inline poller)
        self.addr: Optional[tuple] = None   # the peer address of the last connection (resolved once)
        self.tid = 0
        self.buf = bytearray()
        self.pending: Optional[Sensor] = None
        self.since = 0.0                # clock time of the pending request / connect

    @property
    def connected(self) -> bool:
        return self.sock is not None and not self.connecting

    def connect(self, timeout_s: float) -> None:
        self.close()
        if wires.is_url(self.host):
            self.sock = wires.connect(self.host)        # type: ignore[assignment]
            return
        sock = socket.create_connection(self.addr or (self.host, self.port), timeout=timeout_s)
        self._adopt(sock)
        self.addr = sock.getpeername()

    def connect_nowait(self) -> bool:
        """Start a connect to the address of the last connection without waiting: True if
        connected already (a peer on this host: the handshake completes within the call),
        False while in progress (:meth:`connect_done`); OSError if it failed already."""
        self.close()
        if wires.is_url(self.host):
            self.sock = wires.connect(self.host)        # type: ignore[assignment]
            return True
        addr = self.addr or (self.host, self.port)
        sock = socket.socket(socket.AF_INET6 if ":" in addr[0] else socket.AF_INET, socket.SOCK_STREAM)
        sock.setblocking(False)
        err = sock.connect_ex(addr)
        if err not in (0, errno.EINPROGRESS):
            sock.close()
            raise OSError(err, os.strerror(err))
        self._adopt(sock)
        self.connecting = True
        return self.connect_done()

    def connect_done(self) -> bool:
        """Whether the connect started by :meth:`connect_nowait` has completed (never waits);
        OSError if it failed."""
        assert self.sock is not None
        _, writable, _ = select.select([], [self.sock], [], 0.0)
        if not writable:
            return False
        err = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if err:
            self.close()
            raise OSError(err, os.strerror(err))
        self.connecting = False
        return True

    def _adopt(self, sock: socket.socket) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        self.sock = sock

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        self.connecting = False
        self.pending = None

    def send(self, s: Sensor) -> None:
        """Send the request for ``s`` (12 bytes into an idle socket: never blocks)."""
        assert self.sock is not None
        self.tid = (self.tid + 1) & 0xFFFF
        self.buf = bytearray()
        self.pending = s
        frame = encode_read_request(self.tid, s.unit, REG_START, REG_COUNT)
        if self.sock.send(frame) != len(frame):
            raise OSError("request only partly sent")


class RtuLink(Link):
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


# --------------------------------------------------------------------------- polling core
class PollCore:
    """Connections, transactions and their classification, wherever the polling runs."""

    def __init__(self, cfg: FTBus, endpoints: dict[str, tuple[str, int]], clock: Callable[[], float],
                 reconnect_s: float) -> None:
        self.cfg = cfg
        self.clock = clock
        self.reconnect_s = reconnect_s
        self.links = group_links(cfg.sensors, endpoints)
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
        """One poll thread per link (:meth:`run`)."""
        for link in self.links:
            link.thread = threading.Thread(target=self.run, args=(link,),
                                           name=f"ft-poll-{link.sensors[0].name}", daemon=True)
            link.thread.start()

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

    def _open_link(self, link: Link) -> None:
        for s in link.sensors:
            for _ in range(_OPEN_ATTEMPTS):
                if not link.connected:          # first time, or closed after a timeout (TCP)
                    try:
                        self.connect(link)
                    except OSError as exc:
                        raise DeviceInitError(s.device, f"cannot connect: {exc}") from exc
                self._transact(link, s)
                if s.wrench is not None or s.pub.exc_code is not None:
                    break
            code = s.pub.exc_code
            if s.wrench is None and (code is None or code in _GATEWAY_CODES):
                raise DeviceInitError(s.device, f"unit {s.unit} not reachable after "
                                      f"{_OPEN_ATTEMPTS} requests: {s.pub.cause}")

    # ------------------------------------------------------------------ blocking rounds
    def run(self, link: Link) -> None:
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
                self.lost(link, f"poll thread error: {exc!r}")
            deadline += period
            delay = deadline - time.monotonic()
            if delay < 0.0:                     # overran (e.g. a timeout): no catch-up burst
                deadline, delay = time.monotonic(), 0.0
            self.stop.wait(delay)

    def round(self, links: Sequence[Link], force_connect: bool) -> None:
        """One transaction per sensor of ``links``, blocking. Step ``i`` sends the request of
        every TCP link's ``i``-th sensor, does the RTU ones (blocking) meanwhile, then collects
        the TCP replies together: one timeout, not one round trip per sensor. A link whose
        (re)connect fails (or is backing off) sits the round out; a connection dropped
        mid-round (after a timeout) is reopened for the link's next sensor."""
        skip: set[int] = set()
        for i in range(max(len(link.sensors) for link in links)):
            if self.stop.is_set():
                return
            inflight: list[TcpLink] = []
            for link in links:
                if i >= len(link.sensors) or id(link) in skip:
                    continue
                if not link.connected and not self.reconnect(link, force_connect or i > 0):
                    skip.add(id(link))
                    continue
                s = link.sensors[i]
                if link.rtu:
                    self._transact_rtu(link, s)     # type: ignore[arg-type]
                elif self.send(link, s):            # type: ignore[arg-type]
                    inflight.append(link)           # type: ignore[arg-type]
            if inflight:
                self._collect(inflight)

    def _transact(self, link: Link, s: Sensor) -> None:
        """One complete transaction (open-time reads)."""
        if link.rtu:
            self._transact_rtu(link, s)     # type: ignore[arg-type]
        elif self.send(link, s):            # type: ignore[arg-type]
            self._collect([link])           # type: ignore[list-item]

    def reconnect(self, link: Link, force: bool) -> bool:
        """Blocking reconnect unless backing off after a failed one (``force`` ignores that)."""
        if not force and self.clock() < link.retry_at:
            return False
        try:
            self.connect(link)
        except OSError as exc:
            self.connect_failed(link, exc)
            return False
        return True

    def connect(self, link: Link) -> None:
        link.connect(self.cfg.timeout_s)
        self.connected(link)

    def connected(self, link: Link) -> None:
        for s in link.sensors:
            s.counters["connects"] += 1

    def connect_failed(self, link: Link, exc: OSError) -> None:
        link.close()
        link.retry_at = self.clock() + self.reconnect_s
        for s in link.sensors:
            s.counters["connect_failures"] += 1
            s.publish(f"cannot connect: {exc}", link_down=True)

    def _collect(self, inflight: list[TcpLink]) -> None:
        """Wait for the replies of requests just sent (at most ``timeout_s``), classify each."""
        deadline = time.monotonic() + self.cfg.timeout_s
        streams = [link for link in inflight if isinstance(link.sock, wires.WireEnd)]
        for link in streams:                # in-process: wait on the wire itself
            while not self.on_readable(link):
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    self.give_up(link)
                    break
                link.sock.wait_readable(remaining)      # type: ignore[union-attr]
        if streams:
            inflight = [link for link in inflight if link not in streams]
        pending = {link.sock.fileno(): link for link in inflight}   # type: ignore[union-attr]
        poller = select.poll()
        for fd in pending:
            poller.register(fd, select.POLLIN)
        while pending:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                break
            for fd, _ in poller.poll(remaining * 1e3):
                if self.on_readable(pending[fd]):
                    poller.unregister(fd)
                    del pending[fd]
        for link in pending.values():
            self.give_up(link)

    # ------------------------------------------------------------------ TCP steps (never block)
    def send(self, link: TcpLink, s: Sensor) -> bool:
        """Send the request for ``s``; False (and the connection reported lost) on failure."""
        try:
            link.send(s)
        except OSError as exc:
            self.lost(link, f"connection lost: {exc}")
            return False
        link.since = self.clock()
        return True

    def on_readable(self, link: TcpLink) -> bool:
        """Read what arrived for the pending request; True once the transaction is over
        (reply, garbage, EOF), False while the reply is incomplete or nothing arrived."""
        s = link.pending
        assert s is not None and link.sock is not None
        try:
            data = link.sock.recv(512)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError as exc:
            self.lost(link, f"connection lost: {exc}")
            return True
        if not data:
            self.lost(link, "connection lost: closed by the peer")
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
            self.bad_frame(link, s, f"garbled response: {exc}")
            return True
        link.pending = None
        t = self.clock()
        if code is not None:
            self.exception(s, code)
        else:
            self.sample(s, regs, t)         # type: ignore[arg-type]
        return True

    def give_up(self, link: TcpLink) -> None:
        """The pending request got no complete reply within ``timeout_s``."""
        s = link.pending
        assert s is not None
        if link.buf:
            self.bad_frame(link, s, f"truncated response: {len(link.buf)} bytes, then nothing "
                           f"within {self.cfg.timeout_s:g} s")
        else:
            self.timeout(link, s)

    # ------------------------------------------------------------------ RTU
    def _transact_rtu(self, link: RtuLink, s: Sensor) -> None:
        """One read of registers 180..185 with pymodbus's serial client (blocking)."""
        from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
        from pymodbus.pdu.register_message import ReadHoldingRegistersResponse

        assert link.client is not None
        link.rx_seen = False
        try:
            rr = link.client.read_holding_registers(REG_START, count=REG_COUNT, device_id=s.unit)
        except ConnectionException as exc:
            return self.lost(link, f"connection lost: {exc}")
        except ModbusIOException as exc:
            if link.rx_seen:
                return self.bad_frame(link, s, f"garbled response: {exc}")
            return self.timeout(link, s)
        except OSError as exc:
            return self.lost(link, f"connection lost: {exc}")
        except (ModbusException, ValueError, IndexError) as exc:
            return self.bad_frame(link, s, f"undecodable response: {exc}")
        t = self.clock()
        if rr.isError():
            return self.exception(s, getattr(rr, "exception_code", -1))
        regs = getattr(rr, "registers", None)
        if not isinstance(rr, ReadHoldingRegistersResponse) or regs is None or len(regs) != REG_COUNT:
            return self.bad_frame(link, s, f"unexpected response {rr}")
        self.sample(s, regs, t)

    # ------------------------------------------------------------------ outcomes
    def sample(self, s: Sensor, regs: Sequence[int], t: float) -> None:
        """A register block arrived: a sample, or — an axis at an INT16 limit — a saturated
        reading, published like a sample (the driver's health marks it INVALID, see
        :attr:`Wrench.saturation`) but counted in ``errors``, not ``samples``."""
        w = wrench_from_registers(regs)
        cause = w.saturation
        s.wrench, s.t, s.saturation = w, t, cause
        if cause:
            s.errors += 1
        else:
            s.counters["samples"] += 1
        s.publish(cause)

    def timeout(self, link: Link, s: Sensor) -> None:
        s.timeouts += 1
        s.publish(f"no answer within {self.cfg.timeout_s:g} s (timeout)")
        _flush(link)

    def bad_frame(self, link: Link, s: Sensor, cause: str) -> None:
        s.bad_frames += 1
        s.publish(cause)
        _flush(link)

    def exception(self, s: Sensor, code: int) -> None:
        s.errors += 1
        s.publish(exception_text(code), exc_code=code)

    def lost(self, link: Link, cause: str) -> None:
        link.close()
        for s in link.sensors:
            s.counters["disconnects"] += 1
            s.publish(cause, link_down=True)


def _flush(link: Link) -> None:
    """After a timeout or garbled frame on TCP, drop the connection so a late or partial
    answer cannot poison the next request (reconnected before the next one). The serial
    client already discards stale input before each request."""
    if not link.rtu:
        link.close()


# --------------------------------------------------------------------------- the poller interface
class Poller(abc.ABC):
    """Where the polling runs. ``start()`` connects and reads every sensor once (blocking;
    DeviceInitError names the sensor), then polls; ``latest(now)`` returns every sensor's
    latest :class:`Published`, in :attr:`names` order, without waiting; ``close()`` stops
    and releases everything (idempotent; ``latest`` still answers afterwards)."""

    def __init__(self, cfg: FTBus, endpoints: dict[str, tuple[str, int]], reconnect_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.core = PollCore(cfg, endpoints, clock, reconnect_s)     # ConfigError for a bad layout

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.core.sensors)

    @abc.abstractmethod
    def start(self) -> None: ...

    def latest(self, now: float) -> tuple[Published, ...]:
        return tuple([s.pub for s in self.core.sensors])

    def failure(self) -> str:
        """"" while the poller works; otherwise why samples stopped (asked every poll)."""
        return ""

    @abc.abstractmethod
    def close(self) -> None: ...


# --------------------------------------------------------------------------- layout
def group_links(sensors: Sequence[FTSensor], endpoints: dict[str, tuple[str, int]]) -> list[Link]:
    """One link per distinct connection; several RTU sensors may share one serial line."""
    names = [s.name for s in sensors]
    if len(set(names)) != len(names):
        raise ConfigError(None, "devices.ft.sensors", "distinct sensor names", names)
    unknown = set(endpoints) - set(names)
    if unknown:
        raise ConfigError(None, "devices.ft.sensors", "endpoint overrides for configured sensors only",
                          sorted(unknown))
    links: dict[tuple, Link] = {}
    for cfg in sensors:
        host, port = endpoints.get(cfg.name, (cfg.host, cfg.port))
        key = _link_key(cfg, host, port)
        link = links.get(key)
        if link is None:
            cls = TcpLink if cfg.transport == "tcp" else RtuLink
            links[key] = cls(cfg, host, port, [Sensor(cfg, host, port)])
            continue
        _check_shared(link, cfg)
        link.sensors.append(Sensor(cfg, host, port))
    return list(links.values())


def _link_key(cfg: FTSensor, host: str, port: int) -> tuple:
    if cfg.transport == "tcp":
        return ("tcp", host, port)
    if not cfg.serial_port:
        raise ConfigError(None, f"devices.ft.sensors.{cfg.name}.serial_port",
                          "a serial port for transport 'rtu'")
    return ("rtu", cfg.serial_port)


def _check_shared(link: Link, cfg: FTSensor) -> None:
    """Sensors on one connection need distinct unit ids (and one baud rate on a serial line)."""
    if cfg.unit_id in {s.unit for s in link.sensors}:
        raise ConfigError(None, f"devices.ft.sensors.{cfg.name}.unit_id",
                          "a unit id not used by another sensor on the same connection", cfg.unit_id)
    if cfg.transport == "rtu" and cfg.baudrate != link.cfg.baudrate:
        raise ConfigError(None, f"devices.ft.sensors.{cfg.name}.baudrate",
                          f"the baud rate of the other sensors on {cfg.serial_port}", cfg.baudrate)
