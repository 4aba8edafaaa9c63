"""The four motor converters: CANopen (CiA 301) drives with the CiA 402 profile in cyclic
synchronous torque mode (0x6060 = 10).

Wire format (see docs/protocols.md, section 2 for every byte, unit and source):

* SYNC        0x080, no data — the runtime sends it once per period; the drives sample.
* RPDO1       0x200+n, 4 bytes: controlword UINT16 (0x6040), target torque INT16 (0x6071,
              thousandths of the rated torque; the runtime commands amperes and converts
              with the motor rated current 0x6075: ``permille = round(A / rated_A · 1000)``).
* TPDO1       0x180+n, 8 bytes: statusword UINT16 (0x6041), velocity actual INT32 (0x606C,
              × ``velocity_factor`` → rad/s), torque actual INT16 (0x6077, per mille → A).
* heartbeat   0x700+n, 1 byte NMT state;  NMT command 0x000, 2 bytes (command, node).
* EMCY        0x080+n, 8 bytes: error code UINT16, error register UINT8, 5 bytes vendor.

All little-endian (CiA 301). The codec (module-level functions and constants) does no
I/O; the virtual drives in ``sim_backend.virtual_drive`` reuse it. :class:`DriveBus` is the
driver: blocking start-up with the ``canopen`` package (SDO configuration, NMT, 402 state
machine), then a non-blocking cycle on the raw python-can bus (SYNC + RPDOs + heartbeat out,
TPDO/heartbeat/EMCY in, drained with ``recv(timeout=0)``).
"""

from __future__ import annotations

import logging
import math
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping, NamedTuple, Sequence

import can

from rig_runtime.config import WHEELS, CanBus, Drive, resolve_config_path

from .base import ConfigError, CounterView, DeviceInitError, Driver, Freshness, Health, snapshot

__all__ = [
    # COB-IDs and protocol constants
    "COB_NMT", "COB_SYNC", "COB_EMCY", "COB_TPDO1", "COB_RPDO1", "COB_SDO_TX", "COB_SDO_RX",
    "COB_HEARTBEAT", "RUNTIME_NODE_ID", "MODE_CST", "DEVICE_TYPE_PROFILE",
    "NMT_START", "NMT_STOP", "NMT_ENTER_PRE_OPERATIONAL", "NMT_RESET_NODE", "NMT_RESET_COMMUNICATION",
    "NMT_INITIALISING", "NMT_STOPPED", "NMT_OPERATIONAL", "NMT_PRE_OPERATIONAL", "NMT_STATE_NAMES",
    "CW_SHUTDOWN", "CW_SWITCH_ON", "CW_ENABLE_OPERATION", "CW_DISABLE_VOLTAGE", "CW_QUICK_STOP",
    "CW_FAULT_RESET", "CW_FAULT_RESET_BIT",
    "NOT_READY_TO_SWITCH_ON", "SWITCH_ON_DISABLED", "READY_TO_SWITCH_ON", "SWITCHED_ON",
    "OPERATION_ENABLED", "FAULT", "FAULT_REACTION_ACTIVE", "QUICK_STOP_ACTIVE", "UNKNOWN",
    "STATES", "SW_MASKS", "STATUSWORD_OF_STATE",
    "EMCY_CODES", "EMCY_OVERCURRENT", "EMCY_HEARTBEAT", "EMCY_RPDO_TIMEOUT", "EMCY_PDO_LENGTH",
    "INT16_MIN", "INT16_MAX", "INT32_MIN", "INT32_MAX",
    "RPDO1", "TPDO1", "EMCY", "RPDO1_MAPPING", "TPDO1_MAPPING", "RPDO1_TRANSMISSION_TYPE",
    "TPDO1_TRANSMISSION_TYPE", "PDO_COB_ID_INVALID",
    # codec functions
    "node_cob_id", "mapping_entry", "amps_to_permille", "permille_to_amps", "velocity_to_raw",
    "raw_to_velocity", "encode_rpdo1", "decode_rpdo1", "rpdo1_frame", "encode_tpdo1",
    "decode_tpdo1", "tpdo1_frame", "sync_frame", "nmt_frame", "decode_nmt", "heartbeat_frame",
    "decode_heartbeat", "consumer_heartbeat_entry", "emcy_frame", "decode_emcy", "emcy_text",
    "state_of", "controlword_command", "next_controlword", "drive_transition",
    "startup_sdo_writes",
    # driver
    "WheelReading", "DriveReadings", "DriveBus",
]

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- constants
COB_NMT = 0x000          # NMT module control (CiA 301)
COB_SYNC = 0x080         # SYNC (CiA 301)
COB_EMCY = 0x080         # + node id, emergency (CiA 301)
COB_TPDO1 = 0x180        # + node id, predefined connection set (CiA 301)
COB_RPDO1 = 0x200        # + node id
COB_SDO_TX = 0x580       # + node id, server -> client
COB_SDO_RX = 0x600       # + node id, client -> server
COB_HEARTBEAT = 0x700    # + node id, heartbeat / boot-up (CiA 301)

RUNTIME_NODE_ID = 0x7F   # the runtime's own node id (heartbeat producer watched by the drives)
MODE_CST = 10            # 0x6060 value of cyclic synchronous torque mode (CiA 402-2)
DEVICE_TYPE_PROFILE = 402  # low 16 bits of 0x1000 of a CiA 402 drive

NMT_START = 0x01
NMT_STOP = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82

NMT_INITIALISING = 0x00  # heartbeat state byte (toggle bit 7 masked off); 0 = boot-up
NMT_STOPPED = 0x04
NMT_OPERATIONAL = 0x05
NMT_PRE_OPERATIONAL = 0x7F
NMT_STATE_NAMES = {NMT_INITIALISING: "INITIALISING", NMT_STOPPED: "STOPPED",
                   NMT_OPERATIONAL: "OPERATIONAL", NMT_PRE_OPERATIONAL: "PRE-OPERATIONAL"}

# Controlword commands (CiA 402-2 device control; canopen.profiles.p402.State402.CW_*).
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_FAULT_RESET = 0x0080
CW_FAULT_RESET_BIT = 0x0080

# 402 states, named as in canopen.profiles.p402.State402.
NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY_TO_SWITCH_ON = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
FAULT = "FAULT"
FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
UNKNOWN = "UNKNOWN"      # statusword bits match no state (or none received yet)

# Statusword mask/value per state (CiA 402-2; identical to p402.State402.SW_MASK).
SW_MASKS: tuple[tuple[str, int, int], ...] = (
    (NOT_READY_TO_SWITCH_ON, 0x4F, 0x00),
    (SWITCH_ON_DISABLED, 0x4F, 0x40),
    (READY_TO_SWITCH_ON, 0x6F, 0x21),
    (SWITCHED_ON, 0x6F, 0x23),
    (OPERATION_ENABLED, 0x6F, 0x27),
    (FAULT, 0x4F, 0x08),
    (FAULT_REACTION_ACTIVE, 0x4F, 0x0F),
    (QUICK_STOP_ACTIVE, 0x6F, 0x07),
)
STATES = tuple(s for s, _, _ in SW_MASKS)
_STATE_BITS = 0x6F       # every mask above is a subset of 0x6F


def _state_table() -> tuple[str, ...]:
    """State for each value of ``statusword & 0x6F`` (a lookup instead of 8 mask tests)."""
    table = []
    for bits in range(_STATE_BITS + 1):
        name = UNKNOWN
        for state, mask, value in SW_MASKS:
            if bits & mask == value:
                name = state
                break
        table.append(name)
    return tuple(table)


_STATE_OF_BITS = _state_table()

# Statusword a drive reports in each state: the state bits plus bit 4 (voltage enabled)
# where the power stage has voltage, bit 9 (remote: controlword is processed) always.
STATUSWORD_OF_STATE = {
    NOT_READY_TO_SWITCH_ON: 0x0200,
    SWITCH_ON_DISABLED: 0x0240,
    READY_TO_SWITCH_ON: 0x0231,
    SWITCHED_ON: 0x0233,
    OPERATION_ENABLED: 0x0237,
    FAULT: 0x0208,
    FAULT_REACTION_ACTIVE: 0x020F,
    QUICK_STOP_ACTIVE: 0x0217,
}
_FAULT_STATES = (FAULT, FAULT_REACTION_ACTIVE)

# EMCY error codes used here (CiA 301 emergency error codes, CiA 402-2).
EMCY_OVERCURRENT = 0x2310      # continuous overcurrent (device output side)
EMCY_HEARTBEAT = 0x8130        # life guard error or heartbeat error
EMCY_RPDO_TIMEOUT = 0x8250     # RPDO timeout
EMCY_PDO_LENGTH = 0x8210       # PDO not processed due to length error
EMCY_CODES = {
    0x0000: "error reset / no error",
    0x1000: "generic error",
    0x2310: "continuous overcurrent",
    0x3210: "DC link overvoltage",
    0x3220: "DC link undervoltage",
    0x4310: "drive temperature",
    0x5000: "device hardware",
    0x6000: "device software",
    0x7300: "sensor",
    0x8110: "CAN overrun",
    0x8120: "CAN error passive",
    0x8130: "heartbeat error",
    0x8140: "recovered from bus off",
    0x8210: "PDO length error",
    0x8250: "RPDO timeout",
    0xFF00: "device specific",
}

INT16_MIN, INT16_MAX = -0x8000, 0x7FFF
INT32_MIN, INT32_MAX = -0x80000000, 0x7FFFFFFF

# Frame layouts (little-endian, CiA 301).
RPDO1 = struct.Struct("<Hh")        # controlword, target torque
TPDO1 = struct.Struct("<Hih")       # statusword, velocity actual, torque actual
EMCY = struct.Struct("<HB5s")       # error code, error register, vendor bytes
_NMT = struct.Struct("<BB")         # command, node id (0 = all)

# PDO mapping (index, subindex, bit length) in frame order, and transmission types.
RPDO1_MAPPING = ((0x6040, 0, 16), (0x6071, 0, 16))
TPDO1_MAPPING = ((0x6041, 0, 16), (0x606C, 0, 32), (0x6077, 0, 16))
RPDO1_TRANSMISSION_TYPE = 0xFF      # asynchronous: the target torque acts on reception
TPDO1_TRANSMISSION_TYPE = 1         # synchronous: sampled and sent on every SYNC
PDO_COB_ID_INVALID = 0x80000000     # bit 31 of a PDO COB-ID: PDO disabled


# --------------------------------------------------------------------------- codec
def node_cob_id(base: int, node_id: int) -> int:
    """COB-ID of a node's service (``base`` + node id), checking the node id."""
    if not 1 <= node_id <= 127:
        raise ValueError(f"CANopen node id {node_id} outside 1..127")
    return base + node_id


def mapping_entry(index: int, subindex: int, bits: int) -> int:
    """One PDO mapping entry (UINT32 ``index<<16 | subindex<<8 | bit length``)."""
    return (index << 16) | (subindex << 8) | bits


def amps_to_permille(current_A: float, rated_current_A: float) -> int:
    """Target torque 0x6071 for a current: ``round(A / rated · 1000)``, clipped to INT16."""
    if not math.isfinite(current_A):
        raise ValueError(f"current {current_A!r} is not finite")
    v = round(current_A * 1000.0 / rated_current_A)
    return INT16_MIN if v < INT16_MIN else INT16_MAX if v > INT16_MAX else v


def permille_to_amps(permille: int, rated_current_A: float) -> float:
    """Current of a torque value in thousandths of the rated torque (0x6071/0x6077)."""
    return permille * rated_current_A / 1000.0


def velocity_to_raw(omega_rad_s: float, velocity_factor: float) -> int:
    """Velocity actual 0x606C for an angular velocity, clipped to INT32 (limits = saturated)."""
    if not math.isfinite(omega_rad_s):
        raise ValueError(f"velocity {omega_rad_s!r} is not finite")
    v = round(omega_rad_s / velocity_factor)
    return INT32_MIN if v < INT32_MIN else INT32_MAX if v > INT32_MAX else v


def raw_to_velocity(raw: int, velocity_factor: float) -> float:
    """Angular velocity in rad/s of 0x606C; NaN at the INT32 limits (saturated, no measurement)."""
    if raw == INT32_MAX or raw == INT32_MIN:
        return math.nan
    return raw * velocity_factor


def encode_rpdo1(controlword: int, torque_permille: int) -> bytes:
    """RPDO1 payload: controlword UINT16, target torque INT16."""
    return RPDO1.pack(controlword, torque_permille)


def decode_rpdo1(data: bytes | bytearray) -> tuple[int, int]:
    """(controlword, target torque per mille) of an RPDO1 payload (exactly 4 bytes)."""
    if len(data) != RPDO1.size:
        raise ValueError(f"RPDO1 has {len(data)} bytes, expected {RPDO1.size}")
    return RPDO1.unpack(data)


def rpdo1_frame(node_id: int, controlword: int, torque_permille: int) -> tuple[int, bytes]:
    """(COB-ID, payload) of node ``node_id``'s RPDO1."""
    return node_cob_id(COB_RPDO1, node_id), encode_rpdo1(controlword, torque_permille)


def encode_tpdo1(statusword: int, velocity_raw: int, torque_permille: int) -> bytes:
    """TPDO1 payload: statusword UINT16, velocity actual INT32, torque actual INT16."""
    return TPDO1.pack(statusword, velocity_raw, torque_permille)


def decode_tpdo1(data: bytes | bytearray) -> tuple[int, int, int]:
    """(statusword, velocity raw, torque per mille) of a TPDO1 payload (exactly 8 bytes)."""
    if len(data) != TPDO1.size:
        raise ValueError(f"TPDO1 has {len(data)} bytes, expected {TPDO1.size}")
    return TPDO1.unpack(data)


def tpdo1_frame(node_id: int, statusword: int, velocity_raw: int, torque_permille: int) -> tuple[int, bytes]:
    """(COB-ID, payload) of node ``node_id``'s TPDO1."""
    return node_cob_id(COB_TPDO1, node_id), encode_tpdo1(statusword, velocity_raw, torque_permille)


def sync_frame() -> tuple[int, bytes]:
    """(COB-ID, payload) of SYNC: no data (no SYNC counter, 0x1019 = 0)."""
    return COB_SYNC, b""


def nmt_frame(command: int, node_id: int) -> tuple[int, bytes]:
    """(COB-ID, payload) of an NMT command; node id 0 addresses all nodes."""
    if not 0 <= node_id <= 127:
        raise ValueError(f"NMT node id {node_id} outside 0..127")
    return COB_NMT, _NMT.pack(command, node_id)


def decode_nmt(data: bytes | bytearray) -> tuple[int, int]:
    """(command, node id) of an NMT command frame."""
    if len(data) != 2:
        raise ValueError(f"NMT command has {len(data)} bytes, expected 2")
    return _NMT.unpack(data)


def heartbeat_frame(node_id: int, nmt_state: int) -> tuple[int, bytes]:
    """(COB-ID, payload) of a heartbeat (or boot-up, state 0) of ``node_id``."""
    return node_cob_id(COB_HEARTBEAT, node_id), bytes((nmt_state & 0x7F,))


def decode_heartbeat(data: bytes | bytearray) -> int:
    """NMT state of a heartbeat payload (toggle bit 7 masked off)."""
    if len(data) != 1:
        raise ValueError(f"heartbeat has {len(data)} bytes, expected 1")
    return data[0] & 0x7F


def consumer_heartbeat_entry(producer_node_id: int, time_ms: int) -> int:
    """0x1016 sub-entry: ``node id << 16 | consumer time in ms`` (time UINT16)."""
    if not 0 <= time_ms <= 0xFFFF:
        raise ValueError(f"consumer heartbeat time {time_ms} ms outside 0..65535")
    return (producer_node_id & 0x7F) << 16 | time_ms


def emcy_frame(node_id: int, code: int, register: int = 0, vendor: bytes = b"") -> tuple[int, bytes]:
    """(COB-ID, payload) of an EMCY: error code, error register, up to 5 vendor bytes."""
    if len(vendor) > 5:
        raise ValueError("EMCY vendor data is at most 5 bytes")
    return node_cob_id(COB_EMCY, node_id), EMCY.pack(code, register, vendor)


def decode_emcy(data: bytes | bytearray) -> tuple[int, int, bytes]:
    """(error code, error register, vendor bytes) of an EMCY payload (exactly 8 bytes)."""
    if len(data) != EMCY.size:
        raise ValueError(f"EMCY has {len(data)} bytes, expected {EMCY.size}")
    return EMCY.unpack(data)


def emcy_text(code: int) -> str:
    """Short name of an EMCY error code (exact code, else its error class)."""
    name = EMCY_CODES.get(code) or EMCY_CODES.get(code & 0xFF00) or EMCY_CODES.get(code & 0xF000)
    return name or "unknown error"


def state_of(statusword: int) -> str:
    """402 state of a statusword (one of :data:`STATES`, or :data:`UNKNOWN`)."""
    return _STATE_OF_BITS[statusword & _STATE_BITS]


def controlword_command(controlword: int) -> str:
    """Device-control command of the low controlword bits (CiA 402-2)."""
    if not controlword & 0x02:
        return "DISABLE VOLTAGE"
    if not controlword & 0x04:
        return "QUICK STOP"
    if not controlword & 0x01:
        return "SHUTDOWN"
    if not controlword & 0x08:
        return "SWITCH ON"
    return "ENABLE OPERATION"


# Controlword that moves a drive one step towards OPERATION ENABLED (the path of
# p402.State402.NEXTSTATE2ANY); None = wait, the drive leaves the state by itself.
_NEXT_CONTROLWORD = {
    SWITCH_ON_DISABLED: CW_SHUTDOWN,
    READY_TO_SWITCH_ON: CW_SWITCH_ON,
    SWITCHED_ON: CW_ENABLE_OPERATION,
    OPERATION_ENABLED: CW_ENABLE_OPERATION,
    QUICK_STOP_ACTIVE: CW_DISABLE_VOLTAGE,
    FAULT: CW_FAULT_RESET,
    NOT_READY_TO_SWITCH_ON: None,
    FAULT_REACTION_ACTIVE: None,
    UNKNOWN: None,
}


def next_controlword(state: str) -> int | None:
    """Controlword for the next step towards OPERATION ENABLED (fault reset needs a rising edge)."""
    return _NEXT_CONTROLWORD[state]


def drive_transition(state: str, controlword: int, previous_controlword: int) -> str:
    """The drive side of the 402 state machine (CiA 402-2): new state after a
    controlword. Automatic transitions (0, 1, 13, 14) are the device's business."""
    if state == FAULT:
        rising = controlword & CW_FAULT_RESET_BIT and not previous_controlword & CW_FAULT_RESET_BIT
        return SWITCH_ON_DISABLED if rising else FAULT
    if state in (NOT_READY_TO_SWITCH_ON, FAULT_REACTION_ACTIVE, UNKNOWN):
        return state
    cmd = controlword_command(controlword)
    if cmd == "DISABLE VOLTAGE":                                   # 7, 9, 10, 12
        return SWITCH_ON_DISABLED
    if cmd == "QUICK STOP":                                        # 7, 10, 11
        if state == OPERATION_ENABLED or state == QUICK_STOP_ACTIVE:
            return QUICK_STOP_ACTIVE
        return SWITCH_ON_DISABLED
    if state == QUICK_STOP_ACTIVE:                                 # 16 only on enable
        return OPERATION_ENABLED if cmd == "ENABLE OPERATION" else state
    if cmd == "SHUTDOWN":                                          # 2, 6, 8
        return READY_TO_SWITCH_ON
    if state == SWITCH_ON_DISABLED:                                # only 2 leaves it
        return state
    if cmd == "SWITCH ON":                                         # 3, 5
        return SWITCHED_ON
    return OPERATION_ENABLED                                       # 4, or 3+4 from READY


def startup_sdo_writes(drive: Drive, consumer_node_id: int, consumer_time_ms: int) -> tuple[tuple[int, int, int], ...]:
    """The SDO downloads (index, subindex, value) that configure one drive, in order.

    PDOs are reconfigured the CiA 301 way: disable (COB-ID bit 31), clear the
    mapping count, write entries, set the count, re-enable.
    """
    n = drive.node_id
    rpdo_id, tpdo_id = node_cob_id(COB_RPDO1, n), node_cob_id(COB_TPDO1, n)
    writes: list[tuple[int, int, int]] = [
        (0x6060, 0, MODE_CST),
        (0x6075, 0, round(drive.rated_current_A * 1000.0)),   # mA
        (0x6071, 0, 0),
        (0x1400, 1, PDO_COB_ID_INVALID | rpdo_id),
        (0x1400, 2, RPDO1_TRANSMISSION_TYPE),
        (0x1600, 0, 0),
    ]
    writes += [(0x1600, i + 1, mapping_entry(*m)) for i, m in enumerate(RPDO1_MAPPING)]
    writes += [
        (0x1600, 0, len(RPDO1_MAPPING)),
        (0x1400, 1, rpdo_id),
        (0x1800, 1, PDO_COB_ID_INVALID | tpdo_id),
        (0x1800, 2, TPDO1_TRANSMISSION_TYPE),
        (0x1A00, 0, 0),
    ]
    writes += [(0x1A00, i + 1, mapping_entry(*m)) for i, m in enumerate(TPDO1_MAPPING)]
    writes += [
        (0x1A00, 0, len(TPDO1_MAPPING)),
        (0x1800, 1, tpdo_id),
        (0x1016, 1, consumer_heartbeat_entry(consumer_node_id, consumer_time_ms)),
        (0x1017, 0, drive.heartbeat_ms),
    ]
    return tuple(writes)


# --------------------------------------------------------------------------- readings
class WheelReading(NamedTuple):
    """One drive after a poll.

    ``omega`` (rad/s, 0x606C) and ``current_A`` (torque actual 0x6077 in A) are from the
    latest valid TPDO1; ``t`` is the ``now`` of the poll in which it arrived (NaN before
    the first). When the TPDO stops or is garbled the last values and their ``t`` are kept
    (STALE); a velocity at the INT32 limit is reported as NaN. ``statusword``/``state``
    are from the latest TPDO1 (or the start-up SDO read), ``nmt_state`` from the latest
    heartbeat (None before the first). ``health`` is a snapshot (its ``counters`` a read-only
    live view); decide on ``health.state``, not on NaN checks. Immutable; a named tuple
    because a frozen dataclass costs three times as much to build, every 5 ms.
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

    @property
    def enabled(self) -> bool:
        return self.state == OPERATION_ENABLED


@dataclass(frozen=True, slots=True)
class DriveReadings:
    """All drives of one bus after a poll: ``readings["fl"].omega``; iteration in wheel order.

    ``bus`` is the health of the bus itself (send failures, error frames, counters);
    ``ready``: every drive OPERATION ENABLED with a FRESH reading.
    """

    t: float
    wheels: dict[str, WheelReading]
    bus: Health
    ready: bool

    def __getitem__(self, wheel: str) -> WheelReading:
        return self.wheels[wheel]

    def __iter__(self) -> Iterator[WheelReading]:
        return iter(self.wheels.values())

    def __len__(self) -> int:
        return len(self.wheels)


# --------------------------------------------------------------------------- driver
_TPDO, _HEARTBEAT, _EMCY = 1, 2, 3
_FRESH = Freshness.FRESH
_MAX_FRAMES_PER_POLL = 2000       # bound on one drain (a flooding bus must not stall the loop)


class _Node:
    """Per-drive state of :class:`DriveBus` (plain attributes: the cycle touches them all)."""

    __slots__ = (
        "cfg", "wheel", "node_id", "A_per_permille", "rated_A", "velocity_factor",
        "hb_timeout_s", "max_permille", "rpdo_msg", "rpdo_data",
        "sw", "state", "vel_raw", "tq_raw", "omega", "current", "tpdo_t", "saturated",
        "frozen_n", "cmd_changes", "cmd_ref", "last_cmd", "bad_t", "bad_dlc", "timed_out", "frozen_flag",
        "hb_t", "nmt", "emcy_code", "emcy_reg", "stepping", "last_cw", "health", "counters_view", "snap",
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
        self.vel_raw = self.tq_raw = 0
        self.omega = self.current = math.nan
        self.tpdo_t: float | None = None
        self.saturated = False
        self.frozen_n = 0
        self.cmd_changes = self.cmd_ref = 0
        self.last_cmd = 0
        self.bad_t = -math.inf
        self.bad_dlc = 0
        self.timed_out = False
        self.frozen_flag = False
        self.hb_t: float | None = None
        self.nmt: int | None = None
        self.emcy_code = 0
        self.emcy_reg = 0
        self.stepping = False
        self.last_cw = CW_DISABLE_VOLTAGE
        self.health = Health(cause="not open", counters={
            "tpdo": 0, "heartbeat": 0, "emcy": 0, "frozen": 0, "saturated": 0})
        self.counters_view = CounterView(self.health.counters)
        self.snap: Health | None = None         # the latest snapshot handed out


class DriveBus(Driver):
    """All CiA 402 drives configured on one CAN bus.

    ``open()`` (blocking) creates the python-can bus unless one is passed in, configures
    every drive over SDO with the ``canopen`` package (mode 10, rated current, RPDO1/TPDO1,
    heartbeats), starts them (NMT) and walks the 402 state machine to OPERATION ENABLED.
    Then every period: ``write(currents, now)`` sends SYNC, one RPDO1 per drive and, every
    ``cfg.heartbeat_ms``, the runtime's heartbeat; ``poll(now)`` drains the bus and returns
    :class:`DriveReadings`. Neither blocks nor raises for bus trouble: send failures and
    error frames are counted (``send_errors``, ``error_frames``) and make every drive
    INVALID ("bus error: …") for ``tpdo_timeout_periods`` periods.

    Times (``now``) are the loop's clock (simulated in lockstep); received frames are
    stamped with the ``now`` of the poll that drains them.

    A drive only gets torque while it is OPERATION ENABLED; once it leaves that state by
    itself (fault, heartbeat or RPDO timeout) it is held disabled (controlword 0) until
    :meth:`enable` — nothing re-enables it silently. :meth:`disable` is the safe stop.

    ``frozen_periods``: a TPDO1 payload repeated bit for bit this many times while the torque
    command changed is reported STALE ("frozen"); 0 switches the check off.
    """

    DISABLE_SEND_TIMEOUT_S = 0.002      # per frame, only in disable() (see there)

    def __init__(self, cfg: CanBus, bus: can.BusABC | None = None, period_s: float = 0.005, *,
                 eds_path: str | Path | None = None, runtime_node_id: int = RUNTIME_NODE_ID,
                 sdo_timeout_s: float = 0.3, enable_timeout_s: float = 1.0,
                 frozen_periods: int = 20) -> None:
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
        self.frozen_periods = frozen_periods
        self._tpdo_timeout = cfg.tpdo_timeout_periods
        self._hold = cfg.tpdo_timeout_periods * period_s     # how long a bus/frame event is reported
        self.consumer_time_ms = round(cfg.heartbeat_ms * cfg.heartbeat_timeout_factor)
        if not cfg.heartbeat_ms < self.consumer_time_ms <= 0xFFFF:
            raise ConfigError(None, "devices.can.heartbeat_timeout_factor",
                              f"a factor > 1 giving a consumer time <= 65535 ms (heartbeat_ms {cfg.heartbeat_ms})",
                              cfg.heartbeat_timeout_factor)
        order = {w: i for i, w in enumerate(WHEELS)}
        drives = sorted(cfg.drives, key=lambda d: order[d.wheel])
        self._nodes = tuple(_Node(d, cfg.heartbeat_timeout_factor) for d in drives)
        self.wheels = tuple(d.wheel for d in self._nodes)       # order of sequence commands
        self._rx = {}
        for d in self._nodes:
            self._rx[node_cob_id(COB_TPDO1, d.node_id)] = (_TPDO, d)
            self._rx[node_cob_id(COB_HEARTBEAT, d.node_id)] = (_HEARTBEAT, d)
            self._rx[node_cob_id(COB_EMCY, d.node_id)] = (_EMCY, d)
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
        self._bus_err_t = -math.inf
        self._bus_err_desc = ""
        self._bus_health = Health(state=Freshness.FRESH, counters={
            "send_errors": 0, "error_frames": 0, "rx_frames": 0, "foreign_frames": 0,
            "rx_overflow": 0, "nan_commands": 0, "missing_commands": 0, "clipped_commands": 0})
        self._bus_view = CounterView(self._bus_health.counters)
        self._bus_snap: Health | None = None
        self._ready = False

    @property
    def ready(self) -> bool:
        """All drives OPERATION ENABLED and FRESH at the latest poll."""
        return self._ready

    @property
    def send_errors(self) -> int:
        """Frames python-can refused to send (CanError) since open."""
        return self._bus_health.counters["send_errors"]

    @property
    def error_frames(self) -> int:
        """CAN error frames received since open."""
        return self._bus_health.counters["error_frames"]

    @property
    def last_bus_error(self) -> str:
        """Description of the latest send failure or error frame ("" if none)."""
        return self._bus_err_desc

    # ------------------------------------------------------------------ open / close
    def _device(self, d: _Node) -> str:
        return f"{self.name} node {d.node_id} ({d.wheel})"

    def _do_open(self) -> None:
        """Create/attach the bus, configure and enable every drive; clean up on failure."""
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
            self._want_enabled = False
            self.disable(0.0)            # drives already enabled must not stay enabled
            self._release_bus()
            raise
        self._want_enabled = True

    def _start_up(self, bus: can.BusABC) -> None:
        """canopen Network on the bus (its Notifier only for the start-up), then per drive:
        pre-operational, SDO configuration, start, 402 state machine."""
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
                self._configure(node, d)
            for node, d in zip(nodes, self._nodes):
                self._nmt(node, d, "OPERATIONAL")
            for node, d in zip(nodes, self._nodes):
                self._enable_via_sdo(node, d)
        finally:
            notifier, network.notifier = network.notifier, None
            if notifier is not None:
                notifier.stop(1.0)

    def _add_node(self, canopen, network, d: _Node):
        """A RemoteNode for drive ``d`` with the EDS object dictionary."""
        try:
            od = canopen.import_od(str(self.eds_path), d.node_id)
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

    def _configure(self, node, d: _Node) -> None:
        """Pre-operational, check it is a 402 drive, write the start-up objects."""
        self._nmt(node, d, "PRE-OPERATIONAL")
        device_type = self._sdo_read(node, d, 0x1000)
        if device_type & 0xFFFF != DEVICE_TYPE_PROFILE:
            raise DeviceInitError(self._device(d), f"not a CiA 402 drive (device type 0x{device_type:08X})")
        for index, sub, value in startup_sdo_writes(d.cfg, self.runtime_node_id, self.consumer_time_ms):
            self._sdo_write(node, d, index, sub, value)
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

    def _enable_via_sdo(self, node, d: _Node) -> None:
        """Walk the 402 state machine to OPERATION ENABLED with SDO writes of 0x6040."""
        deadline = time.monotonic() + self.enable_timeout_s
        while True:
            sw = self._sdo_read(node, d, 0x6041)
            state = state_of(sw)
            if state == OPERATION_ENABLED:
                break
            if time.monotonic() > deadline:
                raise DeviceInitError(self._device(d), f"402 state machine stuck in {state} "
                                      f"(statusword 0x{sw:04X}) after {self.enable_timeout_s} s")
            cw = next_controlword(state)
            if cw == CW_FAULT_RESET:
                self._sdo_write(node, d, 0x6040, 0, CW_DISABLE_VOLTAGE)   # rising edge of bit 7
            if cw is not None:
                self._sdo_write(node, d, 0x6040, 0, cw)
            time.sleep(0.001)
        d.sw, d.state, d.last_cw = sw, state, CW_ENABLE_OPERATION

    def _release_bus(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None and self._owns_bus:
            self._owns_bus = False
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001 - a vanished adapter must not stop shutdown
                pass

    def _do_close(self) -> None:
        """Safe stop of the drives, switch off their heartbeat consumers (a clean stop
        must not leave every drive faulting on the runtime's missing heartbeat), then
        release the bus (ours only)."""
        try:
            self.disable(self._last_now)
            self._consumers_off(self._last_now)
        finally:
            self._release_bus()
            self._ready = False

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
            self._bus_health.counters["send_errors"] += 1
            self._bus_error(now, f"send of 0x{msg.arbitration_id:03X} failed: {exc}")
            return False

    def _bus_error(self, now: float, desc: str) -> None:
        self._bus_err_t = now
        self._bus_err_desc = desc
        self._bus_health.errors += 1

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
            for msg in out:
                self._send(msg, now)
            return
        try:
            send_many(out)
        except Exception as exc:  # noqa: BLE001 - CanError, OSError of a vanished adapter
            self._bus_health.counters["send_errors"] += 1
            self._bus_error(now, f"send of SYNC + {len(out) - 1} frames failed: {exc}")

    def _command(self, d: _Node, x: float | None) -> tuple[int, int]:
        """(controlword, torque per mille) for one drive this period."""
        c = self._bus_health.counters
        if x is None:
            c["missing_commands"] += 1
            x = 0.0
        elif x != x or x in (math.inf, -math.inf):
            c["nan_commands"] += 1
            x = 0.0
        if not self._want_enabled:
            return CW_DISABLE_VOLTAGE, 0
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
        if tq != d.last_cmd:
            d.cmd_changes += 1
            d.last_cmd = tq
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

    def enable(self, now: float) -> None:
        """Non-blocking re-enable (after :meth:`disable` or a drive fault): NMT start, then
        the following writes walk each drive to OPERATION ENABLED (fault reset included),
        with zero torque until it gets there. Drives that are enabled and FRESH are left
        alone. Watch :attr:`ready`; torque flows from the write after it turns True."""
        if self._bus is None:
            return
        for d in self._nodes:
            if (self._want_enabled and not d.stepping and d.state == OPERATION_ENABLED
                    and d.health.state is Freshness.FRESH):
                continue                # running fine: no zero-torque gap for it
            cob, data = nmt_frame(NMT_START, d.node_id)
            self._send(can.Message(arbitration_id=cob, data=data, is_extended_id=False), now)
            d.stepping = True
            d.state = UNKNOWN       # re-learn it from a TPDO sent after this (none in pre-op)
        self._want_enabled = True

    def disable(self, now: float) -> None:
        """Safe stop: zero torque, quick stop, disable voltage, NMT pre-operational, each
        step to every drive before the next. Up to 16 frames in a burst, so each send may
        wait up to ``DISABLE_SEND_TIMEOUT_S`` for room in the adapter's queue (rather than
        lose a disable frame). Later writes keep the drives disabled (and SYNC/heartbeat
        going) until :meth:`enable`."""
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
        c = self._bus_health.counters
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
            kind, d = entry
            if kind == _TPDO:
                self._on_tpdo(d, msg.data, now)
            elif kind == _HEARTBEAT:
                self._on_heartbeat(d, msg.data, now)
            else:
                self._on_emcy(d, msg.data)
        else:
            c["rx_overflow"] += 1
        c["rx_frames"] += n

    def _on_tpdo(self, d: _Node, data: bytearray, now: float) -> None:
        if len(data) != 8:
            d.health.bad_frames += 1
            d.bad_t = now
            d.bad_dlc = len(data)
            return
        sw, vel, tq = TPDO1.unpack_from(data)
        if sw == d.sw and vel == d.vel_raw and tq == d.tq_raw:
            d.frozen_n += 1
        else:
            d.frozen_n = 0
            d.cmd_ref = d.cmd_changes
        d.sw, d.vel_raw, d.tq_raw = sw, vel, tq
        d.state = _STATE_OF_BITS[sw & _STATE_BITS]
        if vel == INT32_MAX or vel == INT32_MIN:
            if not d.saturated:
                d.health.counters["saturated"] += 1
            d.saturated = True
            d.omega = math.nan
        else:
            d.saturated = False
            d.omega = vel * d.velocity_factor
        d.current = tq * d.A_per_permille
        d.tpdo_t = now
        d.health.counters["tpdo"] += 1

    def _on_heartbeat(self, d: _Node, data: bytearray, now: float) -> None:
        if len(data) != 1:
            d.health.bad_frames += 1
            return
        d.nmt = data[0] & 0x7F
        d.hb_t = now
        d.health.counters["heartbeat"] += 1

    def _on_emcy(self, d: _Node, data: bytearray) -> None:
        if len(data) != EMCY.size:
            d.health.bad_frames += 1
            return
        code, reg, _ = EMCY.unpack_from(data)
        d.health.counters["emcy"] += 1
        if code & 0xFF00 == 0:                  # CiA 301: 0x00xx = error reset / no error
            d.emcy_code = 0
            return
        d.health.errors += 1
        d.emcy_code, d.emcy_reg = code, reg

    # ------------------------------------------------------------------ health
    def _periods(self, age: float) -> int:
        return int(age / self.period_s + 0.5)

    def _classify(self, d: _Node, now: float) -> tuple[Freshness, str]:
        """Freshness and cause of one drive: INVALID causes first, then STALE ones."""
        hold = self._hold                       # how long an event is reported
        fp = self.frozen_periods
        frozen = fp > 0 and d.frozen_n >= fp and d.cmd_changes != d.cmd_ref
        if frozen and not d.frozen_flag:
            d.health.counters["frozen"] += 1
        d.frozen_flag = frozen
        tpdo_t, hb_t = d.tpdo_t, d.hb_t
        # the last term is _periods(now - tpdo_t) < tpdo_timeout_periods (int() of a value
        # that is < N exactly when the value is)
        if (not frozen and tpdo_t is not None and hb_t is not None and d.nmt == NMT_OPERATIONAL
                and not d.emcy_code and not d.saturated and now - hb_t <= d.hb_timeout_s
                and now - self._bus_err_t > hold and now - d.bad_t > hold
                and d.state not in _FAULT_STATES
                and (now - tpdo_t) / self.period_s + 0.5 < self._tpdo_timeout):
            d.timed_out = False
            return _FRESH, ""                   # the usual case, without building any text
        return self._diagnose(d, now, hold, frozen)

    def _diagnose(self, d: _Node, now: float, hold: float, frozen: bool) -> tuple[Freshness, str]:
        """The full classification with every cause spelled out (anything not nominal)."""
        invalid: list[str] = []
        if now - self._bus_err_t <= hold:
            invalid.append(f"bus error: {self._bus_err_desc}")
        if d.emcy_code:
            invalid.append(f"EMCY 0x{d.emcy_code:04X} {emcy_text(d.emcy_code)} (register 0x{d.emcy_reg:02X})")
        if d.state in _FAULT_STATES:
            invalid.append(f"drive in {d.state}")
        hb_age = now - (d.hb_t if d.hb_t is not None else self._t_ref)
        if hb_age > d.hb_timeout_s:
            invalid.append(f"heartbeat missing for {hb_age * 1e3:.0f} ms")
        elif d.nmt is not None and d.nmt != NMT_OPERATIONAL:
            invalid.append(f"NMT state {NMT_STATE_NAMES.get(d.nmt, hex(d.nmt))}")
        if d.saturated:
            invalid.append("velocity at the INT32 limit (saturated, not a measurement)")
        stale: list[str] = []
        is_stale = d.tpdo_t is None
        if is_stale:
            stale.append(f"no TPDO received yet ({self._periods(now - self._t_ref)} periods)")
        else:
            n = self._periods(now - d.tpdo_t)
            if n >= self.cfg.tpdo_timeout_periods:
                is_stale = True
                stale.append(f"TPDO missing for {n} periods")
                if not d.timed_out:
                    d.timed_out = True
                    d.health.timeouts += 1
            else:
                d.timed_out = False
        if now - d.bad_t <= hold:   # noted; stale only once the TPDO is missing for too long
            stale.append(f"garbled TPDO discarded (DLC {d.bad_dlc} != 8, {d.health.bad_frames} since open)")
        if frozen:
            is_stale = True
            stale.append(f"TPDO values frozen for {d.frozen_n} periods while the torque command changed")
        if invalid:
            return Freshness.INVALID, "; ".join(invalid + stale)
        if is_stale:
            return Freshness.STALE, "; ".join(stale)
        return Freshness.FRESH, "; ".join(stale)    # a garbled frame alone: still fresh, noted

    def _readings(self, now: float) -> DriveReadings:
        wheels: dict[str, WheelReading] = {}
        is_open = self._bus is not None
        ready = is_open and self._want_enabled
        classify = self._classify
        nan = math.nan
        for d in self._nodes:
            h = d.health
            if is_open:
                state, cause = classify(d, now)
            else:
                state, cause = Freshness.INVALID, "driver not open"
            h.state = state
            h.cause = cause
            snap = d.snap = snapshot(h, d.counters_view, d.snap)
            t = d.tpdo_t
            sw = d.sw
            wheels[d.wheel] = WheelReading(d.wheel, d.node_id, d.omega, d.current, sw if sw > 0 else 0,
                                           d.state, d.nmt, nan if t is None else t, snap)
            if ready and (state is not _FRESH or d.state != OPERATION_ENABLED):
                ready = False
        self._ready = ready
        b = self._bus_health
        if now - self._bus_err_t <= self._hold:
            b.state, b.cause = Freshness.INVALID, f"bus error: {self._bus_err_desc}"
        elif self._bus is None:
            b.state, b.cause = Freshness.INVALID, "driver not open"
        else:
            b.state, b.cause = Freshness.FRESH, ""
        bus = self._bus_snap = snapshot(b, self._bus_view, self._bus_snap)
        return DriveReadings(now, wheels, bus, ready)
