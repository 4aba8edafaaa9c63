"""The CiA 402 wire codec of the motor converters: CANopen (CiA 301) frames and the
CiA 402 profile in cyclic synchronous torque mode (0x6060 = 10). No I/O: the driver
(:mod:`drivers.canopen402`) and the virtual drives (:mod:`sim_backend.virtual_drive`)
both use it — one source of truth for every frame layout.

Wire format (see docs/protocols.md, section 2 for every byte, unit and source):

* SYNC        0x080, no data — the runtime sends it once per period; the drives sample.
* RPDO1       0x200+n, 4 bytes: controlword UINT16 (0x6040), target torque INT16 (0x6071,
              thousandths of the rated torque; the runtime commands amperes and converts
              with the motor rated current 0x6075: ``permille = round(A / rated_A · 1000)``).
* TPDO1       0x180+n, 8 bytes: statusword UINT16 (0x6041), velocity actual INT32 (0x606C,
              × ``velocity_factor`` → rad/s), torque actual INT16 (0x6077, per mille → A).
* heartbeat   0x700+n, 1 byte NMT state;  NMT command 0x000, 2 bytes (command, node).
* EMCY        0x080+n, 8 bytes: error code UINT16, error register UINT8, 5 bytes vendor.

All little-endian (CiA 301).
"""

from __future__ import annotations

import math
import struct

from rig_runtime.config import Drive

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
    "FAULT_STATES", "ABORT_NO_ACTION", "ABORT_FAULT", "ABORT_DISABLE_VOLTAGE", "ABORT_QUICK_STOP",
    "QUICK_STOP_TO_DISABLED", "SAFETY_OBJECTS",
]

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
FAULT_STATES = (FAULT, FAULT_REACTION_ACTIVE)

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

# 0x6007 abort connection option code (CiA 402-2): the drive's reaction to a lost
# connection (heartbeat consumer timeout, bus-off, NMT leaving OPERATIONAL)
ABORT_NO_ACTION, ABORT_FAULT, ABORT_DISABLE_VOLTAGE, ABORT_QUICK_STOP = 0, 1, 2, 3
# 0x605A quick stop option code: 1/2 = slow-down/quick-stop ramp, then SWITCH ON DISABLED;
# 5/6 = the same ramps, then stay in QUICK STOP ACTIVE (0 = disable drive function at once)
QUICK_STOP_TO_DISABLED = 2


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
        (0x6007, 0, ABORT_QUICK_STOP),          # heartbeat loss / bus-off / NMT stop: quick stop
        (0x605A, 0, QUICK_STOP_TO_DISABLED),    # quick stop ramp, then SWITCH ON DISABLED
    ]
    return tuple(writes)


# the drive's own safety settings, read back after the start-up writes (configure refuses a
# drive that did not take one: it would not stop by itself if the runtime died)
SAFETY_OBJECTS = ((0x1016, 1), (0x6007, 0), (0x605A, 0))
