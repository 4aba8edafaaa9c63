"""The four motor converters: the CiA 402 driver on a python-can bus.

Start-up (``configure``, blocking) uses the ``canopen`` package: SDO configuration, PDO
mapping, the drives' heartbeat consumer, NMT start — no power. ``activate`` (the
supervisor's ARM transition) walks every drive to OPERATION ENABLED with the cyclic
RPDO controlwords; ``deactivate`` quick-stops and disables. The cycle runs on the raw
python-can bus (SYNC + RPDOs + heartbeat out; TPDO/heartbeat/EMCY in, drained with
``recv(timeout=0)``). Frame layouts: :mod:`drivers.cia402`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Mapping, NamedTuple, Sequence

import can

from rig_runtime.config import WHEELS, CanBus, Drive, resolve_config_path
from rig_runtime.eds import object_dictionary    # the EDS parsed once per process
from rig_runtime.errors import ConfigError, DeviceInitError
from rig_runtime.hardware import Driver, Freshness, Health, health

from .cia402 import (  # the codec
    COB_SYNC, COB_EMCY, COB_TPDO1, COB_RPDO1, COB_SDO_TX, COB_SDO_RX,
    COB_HEARTBEAT, RUNTIME_NODE_ID, MODE_CST, DEVICE_TYPE_PROFILE, NMT_START, NMT_ENTER_PRE_OPERATIONAL,
    NMT_OPERATIONAL, NMT_STATE_NAMES, CW_ENABLE_OPERATION, CW_DISABLE_VOLTAGE, CW_QUICK_STOP, CW_FAULT_RESET,
    CW_FAULT_RESET_BIT, OPERATION_ENABLED, UNKNOWN, INT16_MAX, INT32_MIN,
    INT32_MAX, RPDO1, TPDO1, EMCY, node_cob_id, amps_to_permille,
    nmt_frame, emcy_text, state_of, next_controlword, startup_sdo_writes, SAFETY_OBJECTS,
    FAULT_STATES,
)

__all__ = ["WheelReading", "DriveReadings", "DriveBus"]

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- readings
class WheelReading(NamedTuple):
    """One drive after a poll.

    What the driver observed; whether it is recent enough is the supervisor's rule
    (``limits.stale_periods`` against ``syncs_unanswered``).

    ``omega`` (rad/s, 0x606C) and ``current_A`` (torque actual 0x6077 in A) are from the
    latest valid TPDO1; ``t`` is the ``now`` of the poll in which it arrived (NaN before
    the first). When the TPDO stops or is garbled the last values and their ``t`` are kept
    and ``syncs_unanswered`` counts on; a velocity at the INT32 limit is reported as NaN.
    ``statusword``/``state`` are from the latest TPDO1 (or the start-up SDO read),
    ``nmt_state`` from the latest heartbeat (None before the first). ``health`` is an
    immutable value (the same object poll after poll while nothing changes): INVALID only
    for what the drive says (EMCY, a fault state, NMT not operational, a saturated
    velocity) or for its heartbeat missing past the consumer time; ``health.bad_frames``
    counts the frames of this drive discarded as garbled (wrong DLC) since configure.
    """

    wheel: str
    node_id: int
    omega: float
    current_A: float
    statusword: int
    state: str
    nmt_state: int | None
    t: float
    health: Health
    syncs_unanswered: int = 0    # SYNCs this runtime sent since the latest valid TPDO1 arrived
                                 # (0 again with each valid TPDO1)

    @property
    def enabled(self) -> bool:
        return self.state == OPERATION_ENABLED


@dataclass(frozen=True, slots=True)
class DriveReadings:
    """All drives of one bus after a poll: ``readings["fl"].omega``; iteration in wheel order.

    ``bus`` is the health of the bus itself: INVALID only while the driver is not
    configured; ``errors`` counts send failures, receive failures and error frames since
    configure, ``cause`` describes the latest of them ("" if none); ``bus_error_t`` is the
    ``now`` of the poll/write in which the latest happened (-inf: never) — how recent a
    bus error must be to stop the rig is the supervisor's rule. ``enabled``: the driver is
    active and every drive's latest statusword says OPERATION ENABLED with a reading that is
    not INVALID (a stale one still counts: whether a drive went silent is the supervisor's
    stale rule, which then names that drive).
    """

    t: float
    wheels: dict[str, WheelReading]
    bus: Health
    enabled: bool
    bus_error_t: float = -math.inf

    def __getitem__(self, wheel: str) -> WheelReading:
        return self.wheels[wheel]

    def __iter__(self) -> Iterator[WheelReading]:
        return iter(self.wheels.values())

    def __len__(self) -> int:
        return len(self.wheels)


# --------------------------------------------------------------------------- driver
_FRESH, _INVALID = Freshness.FRESH, Freshness.INVALID
_INFINITIES = (math.inf, -math.inf)
_MAX_FRAMES_PER_POLL = 2000       # bound on one drain (a flooding bus must not stall the loop)


class _Node:
    """Per-drive state of :class:`DriveBus` (plain attributes: the cycle touches them all)."""

    __slots__ = (
        "cfg", "wheel", "node_id", "A_per_permille", "rated_A", "velocity_factor",
        "hb_timeout_s", "max_permille", "rpdo_msg", "rpdo_data",
        "sw", "state", "omega", "current", "tpdo_t", "saturated", "bad_dlc", "hb_lost",
        "unanswered", "hb_t", "nmt", "emcy_code", "emcy_reg", "stepping", "last_cw", "bad_frames", "timeouts", "errors",
        "counters", "health",
    )

    def __init__(self, cfg: Drive, heartbeat_timeout_factor: float) -> None:
        self.cfg = cfg
        self.wheel = cfg.wheel
        self.node_id = cfg.node_id
        self.hb_timeout_s = cfg.heartbeat_ms * heartbeat_timeout_factor / 1000.0
        self.A_per_permille = cfg.rated_current_A / 1000.0
        self.rated_A = cfg.rated_current_A
        self.velocity_factor = cfg.velocity_factor
        self.max_permille = INT16_MAX
        self.rpdo_msg = can.Message(arbitration_id=node_cob_id(COB_RPDO1, cfg.node_id),
                                    data=bytes(RPDO1.size), is_extended_id=False)
        self.rpdo_data = self.rpdo_msg.data   # bytearray, packed in place every cycle
        self.reset()

    def reset(self) -> None:
        """Forget everything received (each open starts a session)."""
        self.sw = -1
        self.state = UNKNOWN
        self.omega = self.current = math.nan
        self.tpdo_t: float | None = None
        self.unanswered = 0             # SYNCs sent since the latest valid TPDO1
        self.saturated = False
        self.bad_dlc = 0                # DLC of the latest TPDO1 if it was garbled, else 0
        self.hb_lost = False            # in a heartbeat-missing episode (counted once in timeouts)
        self.hb_t: float | None = None
        self.nmt: int | None = None
        self.emcy_code = 0
        self.emcy_reg = 0
        self.stepping = False
        self.last_cw = CW_DISABLE_VOLTAGE
        self.bad_frames = self.timeouts = self.errors = 0
        self.counters = {"tpdo": 0, "heartbeat": 0, "emcy": 0, "saturated": 0}
        self.health = Health(Freshness.INVALID, "not configured")    # the latest value handed out


class DriveBus(Driver):
    """All CiA 402 drives configured on one CAN bus.

    ``configure()`` (blocking) creates the python-can bus unless one is passed in, configures
    every drive over SDO with the ``canopen`` package (mode 10, rated current, RPDO1/TPDO1,
    heartbeats) and starts them (NMT) — no power: until :meth:`activate` every RPDO carries
    controlword 0 (disable voltage). ``activate()`` (the supervisor's ARM transition) walks
    each drive to OPERATION ENABLED with the cyclic RPDOs (:attr:`enabled` tells when all
    are there); ``deactivate()`` is the safe stop. Every period: ``write(currents, now)`` sends SYNC, one RPDO1 per drive and, every
    ``cfg.heartbeat_ms``, the runtime's heartbeat; ``poll(now)`` drains the bus and returns
    :class:`DriveReadings`. Neither blocks nor raises for bus trouble: send failures and
    error frames are counted (``send_errors``, ``error_frames``) and reported with the
    time of the latest (``DriveReadings.bus_error_t``) — judged by the supervisor.

    Times (``now``) are the loop's clock (simulated in lockstep); received frames are
    stamped with the ``now`` of the poll that drains them.

    A drive only gets torque while it is OPERATION ENABLED; once it leaves that state by
    itself (fault, heartbeat or RPDO timeout) it is held disabled (controlword 0) until
    deactivated and activated again — nothing re-enables it silently.

    The driver judges no freshness: a drive's TPDO1 is reported with its arrival time and
    the SYNCs left unanswered since; missing, frozen or garbled TPDOs are the supervisor's
    rules (stale, stuck, corrupt). Only the heartbeat has a timeout here (see ``_classify``).
    """

    DISABLE_SEND_TIMEOUT_S = 0.002      # per frame, only in deactivate() (see there)

    def __init__(self, cfg: CanBus, bus: can.BusABC | None = None, period_s: float = 0.005, *,
                 eds_path: str | Path | None = None, runtime_node_id: int = RUNTIME_NODE_ID,
                 sdo_timeout_s: float = 0.3, enable_timeout_s: float = 1.0) -> None:
        super().__init__()
        if not cfg.drives:
            raise ConfigError(None, "devices.can.drives", "at least one drive")
        if not 1 <= runtime_node_id <= 127 or runtime_node_id in {d.node_id for d in cfg.drives}:
            raise ConfigError(None, "runtime_node_id", "a node id 1..127 no drive uses", runtime_node_id)
        self.cfg = cfg
        self.period_s = period_s
        self.name = f"can {cfg.interface}:{cfg.channel}"
        self.eds_path = Path(eds_path) if eds_path is not None else resolve_config_path(cfg.eds)
        self.runtime_node_id = runtime_node_id
        self.sdo_timeout_s = sdo_timeout_s
        self.enable_timeout_s = enable_timeout_s
        self.consumer_time_ms = round(cfg.heartbeat_ms * cfg.heartbeat_timeout_factor)
        if not cfg.heartbeat_ms < self.consumer_time_ms <= 0xFFFF:
            raise ConfigError(None, "devices.can.heartbeat_timeout_factor",
                              f"a factor > 1 giving a consumer time <= 65535 ms (heartbeat_ms {cfg.heartbeat_ms})",
                              cfg.heartbeat_timeout_factor)
        order = {w: i for i, w in enumerate(WHEELS)}
        drives = sorted(cfg.drives, key=lambda d: order[d.wheel])
        self._nodes = tuple(_Node(d, cfg.heartbeat_timeout_factor) for d in drives)
        self.wheels = tuple(d.wheel for d in self._nodes)       # order of sequence commands
        # COB-ID -> (the handler of its frames, the drive): resolved once, one lookup per frame
        # (the class's functions, not bound methods: no reference cycle through the table)
        self._rx: dict[int, tuple[Callable[[DriveBus, _Node, bytearray, float], None], _Node]] = {}
        for d in self._nodes:
            self._rx[node_cob_id(COB_TPDO1, d.node_id)] = (DriveBus._on_tpdo, d)
            self._rx[node_cob_id(COB_HEARTBEAT, d.node_id)] = (DriveBus._on_heartbeat, d)
            self._rx[node_cob_id(COB_EMCY, d.node_id)] = (DriveBus._on_emcy, d)
        self._sdo_replies = {node_cob_id(COB_SDO_TX, d.node_id) for d in self._nodes}
        self._sync_msg = can.Message(arbitration_id=COB_SYNC, data=b"", is_extended_id=False)
        self._hb_msg = can.Message(arbitration_id=node_cob_id(COB_HEARTBEAT, runtime_node_id),
                                   data=bytes((NMT_OPERATIONAL,)), is_extended_id=False)
        self._hb_period_s = cfg.heartbeat_ms / 1000.0
        self._bus_arg = bus
        self._bus: can.BusABC | None = None
        self._send_many = None
        self._out: list[can.Message] = []
        self._owns_bus = False
        self._reset_session()

    # ------------------------------------------------------------------ state
    def _reset_session(self) -> None:
        """Counters and received state of a new session."""
        for d in self._nodes:
            d.reset()
        self._t_ref: float | None = None
        self._last_now = 0.0
        self._hb_next = -math.inf
        self._want_enabled = False
        self._isolated: set[str] = set()     # wheels whose drive is held off while the others run
        self._bus_err_t = -math.inf
        self._bus_err_desc = ""
        self._bus_errors = 0
        self._bus_counters = {
            "send_errors": 0, "error_frames": 0, "rx_frames": 0, "foreign_frames": 0,
            "rx_overflow": 0, "nan_commands": 0, "missing_commands": 0, "clipped_commands": 0}
        self._bus_health = Health(Freshness.INVALID, "not configured")
        self._enabled = False

    @property
    def enabled(self) -> bool:
        """Active, and every drive OPERATION ENABLED and not INVALID at the latest poll."""
        return self._enabled

    @property
    def send_errors(self) -> int:
        """Frames python-can refused to send (CanError) since configure."""
        return self._bus_counters["send_errors"]

    @property
    def error_frames(self) -> int:
        """CAN error frames received since configure."""
        return self._bus_counters["error_frames"]

    def counters(self) -> dict[str, int]:
        """The bus's counters, and each drive's as ``WHEEL.name``."""
        out = dict(self._bus_counters)
        for d in self._nodes:
            out.update({f"{d.wheel}.{k}": v for k, v in d.counters.items()})
        return out

    @property
    def last_bus_error(self) -> str:
        """Description of the latest send failure or error frame ("" if none)."""
        return self._bus_err_desc

    # ------------------------------------------------------------------ open / close
    def _device(self, d: _Node) -> str:
        return f"{self.name} node {d.node_id} ({d.wheel})"

    def _configure(self) -> None:
        """Create/attach the bus, configure and start every drive (no power); clean up on failure."""
        self._reset_session()
        bus = self._bus_arg
        if bus is None:
            try:
                bus = can.Bus(interface=self.cfg.interface, channel=self.cfg.channel,
                              bitrate=self.cfg.bitrate)
            except Exception as exc:  # noqa: BLE001 - any backend failure is an init failure
                raise DeviceInitError(self.name, f"cannot open CAN bus at {self.cfg.bitrate} bit/s: "
                                                 f"{type(exc).__name__}: {exc}") from exc
            self._owns_bus = True
        self._bus = bus
        # one write per period where the bus can batch frames (rig_slcan); else send each
        self._send_many = getattr(bus, "send_many", None)
        try:
            self._start_up(bus)
        except BaseException:
            self._safe_stop(0.0)         # whatever state a drive was left in: disabled
            self._release_bus()
            raise

    def _start_up(self, bus: can.BusABC) -> None:
        """canopen Network on the bus (its Notifier only for the start-up), then per drive:
        pre-operational, SDO configuration, start (NMT operational: PDOs and heartbeats flow,
        the power stage stays off)."""
        import canopen  # heavy; only the blocking start-up needs it

        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = 0.01          # stop() joins within one receive timeout
        try:
            network.connect()
        except Exception as exc:  # noqa: BLE001
            raise DeviceInitError(self.name, f"cannot attach canopen to the bus: {exc}") from exc
        try:
            nodes = [self._add_node(canopen, network, d) for d in self._nodes]
            for node, d in zip(nodes, self._nodes):
                self._configure_drive(node, d)
            for node, d in zip(nodes, self._nodes):
                self._nmt(node, d, "OPERATIONAL")
        finally:
            notifier, network.notifier = network.notifier, None
            if notifier is not None:
                notifier.stop(1.0)

    def _add_node(self, canopen, network, d: _Node):
        """A RemoteNode for drive ``d`` with the EDS object dictionary."""
        try:
            od = object_dictionary(self.eds_path, d.node_id)
        except Exception as exc:  # noqa: BLE001
            raise DeviceInitError(self._device(d), f"cannot load EDS {self.eds_path}: {exc}") from exc
        node = canopen.RemoteNode(d.node_id, od)
        node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
        network.add_node(node)
        return node

    def _nmt(self, node, d: _Node, state: str) -> None:
        try:
            node.nmt.state = state
        except can.CanError as exc:
            raise DeviceInitError(self._device(d), f"cannot send NMT {state}: {exc}") from exc

    def _sdo_read(self, node, d: _Node, index: int, sub: int = 0) -> int:
        """Upload one object; no answer or an abort -> DeviceInitError naming the node."""
        import canopen
        var = node.object_dictionary.get_variable(index, sub)
        try:
            return var.decode_raw(node.sdo.upload(index, sub))
        except canopen.SdoCommunicationError as exc:
            raise DeviceInitError(self._device(d), f"no SDO answer reading 0x{index:04X}:{sub} ({exc}); "
                                  "drive powered, node id and bitrate right?") from exc
        except (canopen.SdoAbortedError, can.CanError) as exc:
            raise DeviceInitError(self._device(d), f"SDO read 0x{index:04X}:{sub} failed: {exc}") from exc

    def _sdo_write(self, node, d: _Node, index: int, sub: int, value: int) -> None:
        """Download one object; no answer or an abort -> DeviceInitError naming the node."""
        import canopen
        var = node.object_dictionary.get_variable(index, sub)
        try:
            node.sdo.download(index, sub, var.encode_raw(value))
        except canopen.SdoCommunicationError as exc:
            raise DeviceInitError(self._device(d), f"no SDO answer writing 0x{index:04X}:{sub} ({exc}); "
                                  "drive powered, node id and bitrate right?") from exc
        except (canopen.SdoAbortedError, can.CanError) as exc:
            raise DeviceInitError(self._device(d), f"SDO write 0x{index:04X}:{sub} = 0x{value:X} "
                                  f"refused: {exc}") from exc

    def _configure_drive(self, node, d: _Node) -> None:
        """Pre-operational, check it is a 402 drive, write the start-up objects."""
        self._nmt(node, d, "PRE-OPERATIONAL")
        device_type = self._sdo_read(node, d, 0x1000)
        if device_type & 0xFFFF != DEVICE_TYPE_PROFILE:
            raise DeviceInitError(self._device(d), f"not a CiA 402 drive (device type 0x{device_type:08X})")
        writes = startup_sdo_writes(d.cfg, self.runtime_node_id, self.consumer_time_ms)
        for index, sub, value in writes:
            self._sdo_write(node, d, index, sub, value)
        wrote = {(i, s): v for i, s, v in writes}
        for index, sub in SAFETY_OBJECTS:       # the drive must stop by itself if the runtime dies
            got = self._sdo_read(node, d, index, sub)
            if got != wrote[index, sub]:
                raise DeviceInitError(self._device(d), f"0x{index:04X}:{sub} reads 0x{got:X} after writing "
                                      f"0x{wrote[index, sub]:X}: the drive did not take its safety setting")
        self._wait_for(node, d, 0x6061, MODE_CST, "mode of operation display")
        d.max_permille = min(self._sdo_read(node, d, 0x6072), INT16_MAX)
        log.info("%s configured (rated %.3f A, max torque %d per mille)", self._device(d),
                 d.cfg.rated_current_A, d.max_permille)

    def _wait_for(self, node, d: _Node, index: int, value: int, what: str) -> None:
        """Poll an object until it shows ``value`` (drives take a moment to switch modes)."""
        deadline = time.monotonic() + self.enable_timeout_s
        while (got := self._sdo_read(node, d, index)) != value:
            if time.monotonic() > deadline:
                raise DeviceInitError(self._device(d), f"{what} (0x{index:04X}) is {got}, expected {value}")
            time.sleep(0.002)

    def _release_bus(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None and self._owns_bus:
            self._owns_bus = False
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001 - a vanished adapter must not stop shutdown
                pass

    def _close_time(self) -> float:
        return self._last_now

    def _close(self) -> None:
        """Safe stop of the drives (also when never activated: whatever state they are in),
        switch off their heartbeat consumers (a clean stop must not leave every drive
        faulting on the runtime's missing heartbeat), then release the bus (ours only)."""
        try:
            self._consumers_off(self._last_now)     # first: a clean stop must not look like a dead runtime
            self._safe_stop(self._last_now)
        finally:
            self._release_bus()
            self._enabled = False

    def _consumers_off(self, now: float) -> None:
        """Expedited SDO download 0x1016:01 = 0 to every drive, fire and forget (the
        answers are not awaited: a drive that misses it only logs a heartbeat fault)."""
        if self._bus is None:
            return
        for d in self._nodes:
            data = bytes((0x23, 0x16, 0x10, 0x01, 0, 0, 0, 0))
            self._send(can.Message(arbitration_id=node_cob_id(COB_SDO_RX, d.node_id), data=data,
                                   is_extended_id=False), now, self.DISABLE_SEND_TIMEOUT_S)

    # ------------------------------------------------------------------ cycle: out
    def _send(self, msg: can.Message, now: float, timeout: float = 0.0) -> bool:
        """Send (without waiting by default); a failure is counted and reported, never raised."""
        try:
            self._bus.send(msg, timeout=timeout)
            return True
        except Exception as exc:  # noqa: BLE001 - CanError, OSError of a vanished adapter
            self._bus_counters["send_errors"] += 1
            self._bus_error(now, f"send of 0x{msg.arbitration_id:03X} failed: {exc}")
            return False

    def _bus_error(self, now: float, desc: str) -> None:
        self._bus_err_t = now
        self._bus_err_desc = desc
        self._bus_errors += 1

    def write(self, currents: Mapping[str, float] | Sequence[float], now: float) -> None:
        """SYNC, then RPDO1 (controlword + target torque) per drive, then the heartbeat if due.

        ``currents``: amperes per wheel, a mapping by wheel name or a sequence in the order
        of :attr:`wheels`. Missing or non-finite values are sent as 0 A (counted).
        """
        if self._bus is None:
            return
        self._last_now = now
        if self._t_ref is None:
            self._t_ref = now
        out = self._out
        out.clear()
        out.append(self._sync_msg)
        by_name = hasattr(currents, "get")
        n_given = -1 if by_name else len(currents)
        command = self._command
        pack = RPDO1.pack_into
        for i, d in enumerate(self._nodes):
            if by_name:
                x = currents.get(d.wheel)
            else:
                x = currents[i] if i < n_given else None
            cw, tq = command(d, x)
            pack(d.rpdo_data, 0, cw, tq)
            d.last_cw = cw
            out.append(d.rpdo_msg)
        if now >= self._hb_next:
            out.append(self._hb_msg)
            nxt = self._hb_next + self._hb_period_s
            self._hb_next = nxt if nxt > now else now + self._hb_period_s
        send_many = self._send_many
        if send_many is None:
            sent = self._send(out[0], now)     # the SYNC
            for i in range(1, len(out)):       # no slice: nothing allocated per cycle
                self._send(out[i], now)
        else:
            try:
                send_many(out)
                sent = True
            except Exception as exc:  # noqa: BLE001 - CanError, OSError of a vanished adapter
                sent = False
                self._bus_counters["send_errors"] += 1
                self._bus_error(now, f"send of SYNC + {len(out) - 1} frames failed: {exc}")
        if sent:                        # a SYNC on the wire asks every drive for a TPDO1
            for d in self._nodes:
                d.unanswered += 1

    def _command(self, d: _Node, x: float | None) -> tuple[int, int]:
        """(controlword, torque per mille) for one drive this period."""
        c = self._bus_counters
        if x is None:
            c["missing_commands"] += 1
            x = 0.0
        elif x != x or x in _INFINITIES:
            c["nan_commands"] += 1
            x = 0.0
        if not self._want_enabled:
            return CW_DISABLE_VOLTAGE, 0
        if self._isolated and d.wheel in self._isolated:     # lost: quick stop, then disabled
            return (CW_QUICK_STOP if d.state == OPERATION_ENABLED else CW_DISABLE_VOLTAGE), 0
        if d.stepping:
            if d.state != OPERATION_ENABLED:
                return self._step(d), 0
            d.stepping = False
            d.emcy_code = 0                     # a fault that is reset is no longer active
        if d.state != OPERATION_ENABLED:
            return CW_DISABLE_VOLTAGE, 0        # left OPERATION ENABLED by itself: hold off
        tq = amps_to_permille(x, d.rated_A)
        m = d.max_permille
        if tq > m or tq < -m:
            c["clipped_commands"] += 1
            tq = m if tq > 0 else -m
        return CW_ENABLE_OPERATION, tq

    @staticmethod
    def _step(d: _Node) -> int:
        """Next controlword on the way to OPERATION ENABLED (alternating 0 / 0x80 in FAULT).

        Each step's command is idempotent in the state it leads to, so the one-period lag of
        the TPDO statusword only repeats a command. While the state is not known (or the
        drive moves by itself) the last controlword is repeated, which changes nothing.
        """
        cw = next_controlword(d.state)
        if cw is None:
            return d.last_cw & ~CW_FAULT_RESET_BIT
        if cw == CW_FAULT_RESET and d.last_cw & CW_FAULT_RESET_BIT:
            return CW_DISABLE_VOLTAGE
        return cw

    def _activate(self, now: float) -> None:
        """Non-blocking: NMT start, then the following writes walk each drive to OPERATION
        ENABLED (fault reset included), with zero torque until it gets there. Watch
        :attr:`enabled`; torque flows from the write after it turns True."""
        self._nmt_start(now, enable=True)

    def _deactivate(self, now: float) -> None:
        self._safe_stop(now)

    def _resume(self, now: float) -> None:
        """After a safe stop (NMT pre-operational): NMT start again, so that TPDOs and the
        drives' states come back while every RPDO carries "disable voltage" and zero torque
        — the state ``configure()`` leaves. ARM's ``activate`` then walks them to OPERATION
        ENABLED as at the first arming."""
        self._nmt_start(now, enable=False)

    def _nmt_start(self, now: float, enable: bool) -> None:
        """NMT start to every drive; ``enable``: the following writes walk them to OPERATION
        ENABLED, else they say "disable voltage" with zero torque."""
        if self._bus is None:
            return
        for d in self._nodes:
            cob, data = nmt_frame(NMT_START, d.node_id)
            self._send(can.Message(arbitration_id=cob, data=data, is_extended_id=False), now)
            d.stepping = enable
            d.state = UNKNOWN       # re-learn it from a TPDO sent after this (none in pre-op)
        self._want_enabled = enable
        self._isolated.clear()

    def isolate(self, wheel: str, now: float) -> None:
        """Hold one drive off while the others run (the supervisor's RECONFIGURED: its wheel
        is lost): zero torque, quick stop, then disable voltage, from the next write. Until the
        next activation."""
        self._isolated.add(wheel)

    def _safe_stop(self, now: float) -> None:
        """Zero torque, quick stop, disable voltage, NMT pre-operational, each step to every
        drive before the next. Up to 16 frames in a burst, so each send may wait up to
        ``DISABLE_SEND_TIMEOUT_S`` for room in the adapter's queue (rather than lose a
        disable frame). Later writes keep the drives disabled (and SYNC/heartbeat going)."""
        if self._bus is None:
            return
        wait = self.DISABLE_SEND_TIMEOUT_S
        for d in self._nodes:
            if self._want_enabled and d.state == OPERATION_ENABLED:
                self._send_rpdo(d, CW_ENABLE_OPERATION, 0, now, wait)
        for cw in (CW_QUICK_STOP, CW_DISABLE_VOLTAGE):
            for d in self._nodes:
                self._send_rpdo(d, cw, 0, now, wait)
        for d in self._nodes:
            cob, data = nmt_frame(NMT_ENTER_PRE_OPERATIONAL, d.node_id)
            self._send(can.Message(arbitration_id=cob, data=data, is_extended_id=False), now, wait)
            d.stepping = False
        self._want_enabled = False

    def _send_rpdo(self, d: _Node, cw: int, tq: int, now: float, timeout: float = 0.0) -> None:
        RPDO1.pack_into(d.rpdo_data, 0, cw, tq)
        d.last_cw = cw
        self._send(d.rpdo_msg, now, timeout)

    # ------------------------------------------------------------------ cycle: in
    def poll(self, now: float) -> DriveReadings:
        """Drain every received frame without blocking; readings with health per drive."""
        self._last_now = now
        if self._t_ref is None:
            self._t_ref = now
        bus = self._bus
        if bus is not None:
            self._drain(bus, now)
        return self._readings(now)

    def _drain(self, bus: can.BusABC, now: float) -> None:
        c = self._bus_counters
        recv = bus.recv
        rx = self._rx
        n = 0
        while n < _MAX_FRAMES_PER_POLL:
            try:
                msg = recv(0.0)
            except Exception as exc:  # noqa: BLE001 - poll never raises into the loop
                self._bus_error(now, f"receive failed: {exc}")
                break
            if msg is None:
                break
            n += 1
            if msg.is_error_frame:
                c["error_frames"] += 1
                self._bus_error(now, "error frame on the bus")
                continue
            entry = rx.get(msg.arbitration_id)
            if entry is None or msg.is_remote_frame or msg.is_extended_id:
                if msg.arbitration_id not in self._sdo_replies:
                    c["foreign_frames"] += 1
                continue
            on_frame, d = entry
            on_frame(self, d, msg.data, now)
        else:
            c["rx_overflow"] += 1
        c["rx_frames"] += n

    def _on_tpdo(self, d: _Node, data: bytearray, now: float) -> None:
        if len(data) != 8:
            d.bad_frames += 1
            d.bad_dlc = len(data)
            return
        sw, vel, tq = TPDO1.unpack_from(data)
        d.bad_dlc = 0
        d.sw = sw
        d.state = state_of(sw)
        if vel == INT32_MAX or vel == INT32_MIN:
            if not d.saturated:
                d.counters["saturated"] += 1
            d.saturated = True
            d.omega = math.nan
        else:
            d.saturated = False
            d.omega = vel * d.velocity_factor
        d.current = tq * d.A_per_permille
        d.tpdo_t = now
        d.unanswered = 0
        d.counters["tpdo"] += 1

    def _on_heartbeat(self, d: _Node, data: bytearray, now: float) -> None:
        if len(data) != 1:
            d.bad_frames += 1
            return
        d.nmt = data[0] & 0x7F
        d.hb_t = now
        d.counters["heartbeat"] += 1

    def _on_emcy(self, d: _Node, data: bytearray, now: float) -> None:
        if len(data) != EMCY.size:
            d.bad_frames += 1
            return
        code, reg, _ = EMCY.unpack_from(data)
        d.counters["emcy"] += 1
        if code & 0xFF00 == 0:                  # CiA 301: 0x00xx = error reset / no error
            d.emcy_code = 0
            return
        d.errors += 1
        d.emcy_code, d.emcy_reg = code, reg

    # ------------------------------------------------------------------ health
    def _classify(self, d: _Node, now: float) -> tuple[Freshness, str]:
        """INVALID for what the drive says about itself, every cause spelled out; else FRESH,
        with a note of what was observed (no TPDO yet, a garbled latest TPDO). Each
        observation is looked at once; the text is built only when there is one to report
        (the nominal cycle builds none)."""
        emcy = d.emcy_code
        fault_state = d.state in FAULT_STATES
        # The heartbeat is CANopen's error control (CiA 301 heartbeat consumer): a producer
        # silent past its consumer time *is* the protocol's "node lost" event, with the time
        # configured per drive (heartbeat_ms x heartbeat_timeout_factor, the same time the
        # drives use for the runtime) — not a freshness rule of this runtime's, so it stays here.
        hb_age = now - (d.hb_t if d.hb_t is not None else self._t_ref)
        hb_missing = hb_age > d.hb_timeout_s
        if hb_missing:
            if not d.hb_lost:
                d.hb_lost = True
                d.timeouts += 1
        else:
            d.hb_lost = False
        nmt = d.nmt
        nmt_off = not hb_missing and nmt is not None and nmt != NMT_OPERATIONAL
        no_tpdo = d.tpdo_t is None
        if not (emcy or fault_state or hb_missing or nmt_off or d.saturated or no_tpdo or d.bad_dlc):
            return _FRESH, ""
        invalid: list[str] = []
        if emcy:
            invalid.append(f"EMCY 0x{emcy:04X} {emcy_text(emcy)} (register 0x{d.emcy_reg:02X})")
        if fault_state:
            invalid.append(f"drive in {d.state}")
        if hb_missing:
            invalid.append(f"heartbeat missing for {hb_age * 1e3:.0f} ms")
        if nmt_off:
            invalid.append(f"NMT state {NMT_STATE_NAMES.get(nmt, hex(nmt))}")
        if d.saturated:
            invalid.append("velocity at the INT32 limit (saturated, not a measurement)")
        notes: list[str] = []
        if no_tpdo:
            notes.append("no TPDO received yet")
        if d.bad_dlc:
            notes.append(f"garbled TPDO discarded (DLC {d.bad_dlc} != 8, {d.bad_frames} since open)")
        if invalid:
            return _INVALID, "; ".join(invalid + notes)
        return _FRESH, "; ".join(notes)

    def _readings(self, now: float) -> DriveReadings:
        wheels: dict[str, WheelReading] = {}
        is_open = self._bus is not None
        enabled = is_open and self._want_enabled
        nan = math.nan
        for d in self._nodes:
            if is_open:
                state, cause = self._classify(d, now)
            else:
                state, cause = Freshness.INVALID, "driver not configured"
            d.health = health(d.health, state, cause, d.bad_frames, d.timeouts, d.errors)
            t = d.tpdo_t
            sw = d.sw
            wheels[d.wheel] = WheelReading(d.wheel, d.node_id, d.omega, d.current, sw if sw > 0 else 0,
                                           d.state, d.nmt, nan if t is None else t, d.health,
                                           d.unanswered)
            if enabled and (state is _INVALID or d.state != OPERATION_ENABLED):
                enabled = False
        self._enabled = enabled
        if is_open:
            state, cause = Freshness.FRESH, self._bus_err_desc and f"bus error: {self._bus_err_desc}"
        else:
            state, cause = Freshness.INVALID, "driver not configured"
        self._bus_health = health(self._bus_health, state, cause, 0, 0, self._bus_errors)
        return DriveReadings(now, wheels, self._bus_health, enabled, self._bus_err_t)
