"""Virtual CiA 402 motor converters on a python-can bus — the other end of
``drivers.canopen402``.

Each drive is a ``canopen.LocalNode`` built from the same EDS as the runtime's
``RemoteNode``: canopen serves SDO (expedited and segmented) and NMT commands from that
object dictionary. Everything cyclic is done here, with the frame layouts of
``drivers.canopen402`` (one source of truth): RPDO1 drives the 402 state machine and the
target torque, SYNC triggers TPDO1 (statusword, velocity actual, torque actual), the
heartbeat producer (0x1017) and consumer (0x1016) run on the set's clock, and a watchdog
cuts the current when SYNC or RPDO1 stop.

Behaviour a real converter has and this one models (docs/protocols.md, section 2):

* RPDO1 transmission type 0xFF acts on reception; 0..240 latches the target at the next SYNC.
* TPDO1 transmission type n in 1..240 is sent on every n-th SYNC; other types send nothing.
* PDO mappings are honoured: a mapping other than the codec's is packed/unpacked generically
  from the object dictionary, so a runtime that forgets to map gets short frames.
* Torque only in OPERATION ENABLED with NMT OPERATIONAL and mode 10, clipped to 0x6072;
  amperes from per-mille via the *drive's* 0x6075 (the value the runtime wrote).
* Watchdog: once armed by the first SYNC/RPDO in OPERATIONAL, no SYNC or no RPDO1 for longer
  than ``cfg.watchdog_ms`` while the power stage is on -> FAULT, EMCY 0x8250, zero current.
* Heartbeat consumer: runs from its configuration (the write of 0x1016:1 starts the clock,
  not the producer's first heartbeat, so a runtime that dies right after configuring is
  noticed too); silence for longer than the consumer time -> EMCY 0x8130 and the reaction
  0x6007 asks for; 0x1016:1 = 0 switches the consumer off (a clean stop).
* Connection lost (heartbeat consumer timeout, leaving NMT OPERATIONAL with the power stage
  on) -> 0x6007: 0 nothing, 1 FAULT, 2 disable voltage, 3 quick stop; a quick stop ends per
  0x605A (1, 2: SWITCH ON DISABLED; 5, 6: stays QUICK STOP ACTIVE; the ramp is instantaneous
  here), zero current either way.
* Fault reset (rising edge of controlword bit 7) -> SWITCH ON DISABLED and EMCY 0x0000,
  unless an injected fault persists.

Two ways to run: lockstep, ``service(t)`` handles every pending frame and the timers at
simulated time ``t``; realtime, ``start_realtime()`` runs a thread on wall time (or on a
``time_fn`` you give — a constant one serves the runtime's blocking start-up in lockstep).
"""

from __future__ import annotations

import contextlib
import functools
import math
import random
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import can
import canopen
from canopen.nmt import NmtSlave

from drivers.cia402 import (
    ABORT_FAULT, ABORT_NO_ACTION, ABORT_QUICK_STOP,
    COB_HEARTBEAT, COB_NMT, COB_SDO_RX, COB_SDO_TX, COB_SYNC, CW_DISABLE_VOLTAGE, EMCY_HEARTBEAT,
    EMCY_OVERCURRENT, EMCY_PDO_LENGTH, EMCY_RPDO_TIMEOUT, FAULT, INT32_MAX, MODE_CST,
    NMT_INITIALISING, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL, NMT_STATE_NAMES, OPERATION_ENABLED,
    PDO_COB_ID_INVALID, QUICK_STOP_ACTIVE, RPDO1, RPDO1_MAPPING, STATUSWORD_OF_STATE, SWITCH_ON_DISABLED,
    SWITCHED_ON, TPDO1, TPDO1_MAPPING, drive_transition, emcy_frame, heartbeat_frame, mapping_entry,
    node_cob_id, velocity_to_raw,
)
from rig_runtime.config import WHEELS, CanBus, Drive, resolve_config_path
from rig_runtime.eds import object_dictionary

__all__ = ["FAULT_KINDS", "VirtualDrive", "VirtualDriveSet"]

# kind -> default parameters (see inject())
FAULT_KINDS: dict[str, dict[str, Any]] = {
    "dropout": {},                                  # no TPDO1 at all
    "no_heartbeat": {},                             # heartbeat producer silent
    "bus_error": {"fraction": 0.5, "error_frames": True},  # frames lost both ways
    "out_of_range": {"mode": "overcurrent"},        # or mode="saturate": velocity = INT32_MAX
    "stuck": {},                                    # TPDO1 repeats its last payload
    "offset": {"omega_rad_s": 1.0},                 # velocity actual off by this much (alias: amount)
    "corrupt": {"dlc": 5, "fraction": 1.0},         # this fraction of TPDO1s truncated to dlc bytes
    # the wheel gets no torque: "announced" the drive faults (EMCY 0x5000); "silent" it stays
    # OPERATION ENABLED and answers every SYNC, its torque actual the (no) current it measures (a lost phase)
    "motor_outage": {"mode": "announced"},
}
EMCY_MOTOR_OUTAGE = 0x5000      # device hardware
_ALIASES = {("offset", "amount"): "omega_rad_s"}

_POWER_ON = (SWITCHED_ON, OPERATION_ENABLED, QUICK_STOP_ACTIVE)
# the 402 transition is a pure function of (state, controlword, previous controlword), and a
# cyclic RPDO repeats the same few: memoised
_transition = functools.lru_cache(maxsize=1024)(drive_transition)
_Message = can.Message
_CODEC_RPDO_MAP = tuple(mapping_entry(*m) for m in RPDO1_MAPPING)
_RPDO1_SIZE, _unpack_rpdo, _pack_tpdo = RPDO1.size, RPDO1.unpack_from, TPDO1.pack
_CODEC_TPDO_MAP = tuple(mapping_entry(*m) for m in TPDO1_MAPPING)
# error register 0x1001 bits per EMCY class (CiA 301 object 0x1001): generic | current / communication
_ERROR_REGISTER = {0x23: 0x03, 0x81: 0x11, 0x82: 0x11}


class _SimNmtSlave(NmtSlave):
    """NMT slave whose heartbeat is produced on the set's clock, not python-can's timer thread."""

    def __init__(self, node_id: int, local_node, on_period: Callable[[int], None]) -> None:
        super().__init__(node_id, local_node)
        self._on_period = on_period

    def start_heartbeat(self, heartbeat_time_ms: int) -> None:
        self._heartbeat_time_ms = heartbeat_time_ms
        self._on_period(heartbeat_time_ms)

    def stop_heartbeat(self) -> None:
        self._on_period(0)

    def update_heartbeat(self) -> None:
        """The producer reads the state when it sends; nothing to update."""


class _SimNetwork(canopen.Network):
    """A canopen Network that is never connected: frames in are fed by the set, frames out
    (SDO responses, boot-up) go through the set so fault injection sees them."""

    def __init__(self, owner: "VirtualDriveSet", bus: can.BusABC) -> None:
        super().__init__(bus)
        self._owner = owner

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._owner._tx(can_id, bytes(data), self._owner._by_sdo_tx.get(can_id))


class VirtualDrive:
    """One simulated converter (use it through :class:`VirtualDriveSet`)."""

    def __init__(self, owner: "VirtualDriveSet", cfg: Drive, od_path: Path) -> None:
        self.owner = owner
        self.cfg = cfg
        self.wheel = cfg.wheel
        self.node_id = cfg.node_id
        self.node = canopen.LocalNode(cfg.node_id, object_dictionary(od_path, cfg.node_id))   # parsed once per process
        old = self.node.nmt
        self.node.nmt = _SimNmtSlave(cfg.node_id, self.node, self._set_heartbeat_period)
        self.node._write_callbacks.remove(old.on_write)
        self.node.add_write_callback(self.node.nmt.on_write)
        self.node.add_write_callback(self._on_od_write)
        self.node.add_read_callback(self._on_od_read)
        self.faults: dict[str, dict[str, Any]] = {}
        self.omega = 0.0
        self._in_pdo = False
        self._reset_application()

    # ------------------------------------------------------------------ state
    def _reset_application(self) -> None:
        """Power-on state of the drive (also after NMT reset node)."""
        self.state = SWITCH_ON_DISABLED     # NOT READY -> SWITCH ON DISABLED is automatic
        self.cw = CW_DISABLE_VOLTAGE
        self.target = 0                     # per mille, acting
        self.pending = 0                    # per mille, waiting for SYNC (synchronous RPDO)
        self.error_code = 0
        self.hb_period_s = 0.0
        self.hb_next = math.inf
        self.consumer_last: float | None = None
        self.wd_armed = False
        self.wd_sync = self.wd_rpdo = 0.0
        self.sync_count = 0
        self.last_tpdo: bytes | None = None
        self.counters = {"rpdo": 0, "sync": 0, "tpdo": 0, "emcy": 0, "rx_dropped": 0, "tx_dropped": 0,
                         "pdo_length_errors": 0, "watchdog_trips": 0, "heartbeat_events": 0}
        self._cfg_dirty = True
        self._load_config()

    def _od(self, index: int, sub: int = 0) -> int:
        var = self.node.object_dictionary.get_variable(index, sub)
        return var.decode_raw(self.node.get_data(index, sub))

    def _load_config(self) -> None:
        """Cache the object-dictionary values the cyclic path needs (after any SDO write)."""
        if not self._cfg_dirty:
            return
        self._cfg_dirty = False
        self.mode = self._od(0x6060)
        self.rated_A = self._od(0x6075) / 1000.0
        self.max_permille = self._od(0x6072)
        rc, tc = self._od(0x1400, 1), self._od(0x1800, 1)
        self.rpdo_cob = None if rc & PDO_COB_ID_INVALID else rc & 0x7FF
        self.tpdo_cob = None if tc & PDO_COB_ID_INVALID else tc & 0x7FF
        self.rpdo_type, self.tpdo_type = self._od(0x1400, 2), self._od(0x1800, 2)
        self.rpdo_map = tuple(self._od(0x1600, i) for i in range(1, self._od(0x1600, 0) + 1))
        self.tpdo_map = tuple(self._od(0x1A00, i) for i in range(1, self._od(0x1A00, 0) + 1))
        entry = self._od(0x1016, 1)
        self.consumer_node = (entry >> 16) & 0x7F
        self.consumer_s = (entry & 0xFFFF) / 1000.0
        if self.consumer_s == 0:
            self.consumer_last = None           # consumer switched off
        self.abort_code = self._od(0x6007)
        self.qs_option = self._od(0x605A)
        # derived for the cyclic path
        self._codec_rpdo = self.rpdo_map == _CODEC_RPDO_MAP
        self._codec_tpdo = self.tpdo_map == _CODEC_TPDO_MAP
        self._sync_rpdo = self.rpdo_type <= 240
        self._tpdo_every = self.tpdo_type if self.tpdo_cob is not None and 1 <= self.tpdo_type <= 240 else 0
        self.owner._routes_dirty = True

    @property
    def nmt(self) -> int:
        return self.node.nmt._state

    def current_A(self) -> float:
        """Current the power stage applies now."""
        p = self._applied_permille()
        return p * self.rated_A / 1000.0 if p else 0.0

    def _applied_permille(self) -> int:
        """Torque (per mille of rated) the power stage applies now: the clipped target while
        OPERATION ENABLED in CST with the node operational and the motor there, else 0 —
        what :meth:`current_A` and :meth:`torque_actual` both report, decided once."""
        if self._cfg_dirty:
            self._load_config()
        if self.state != OPERATION_ENABLED or self.node.nmt._state != NMT_OPERATIONAL or self.mode != MODE_CST:
            return 0
        if self.faults and "motor_outage" in self.faults:
            return 0
        return self._effective_permille()

    def _effective_permille(self) -> int:
        m = self.max_permille
        t = self.target
        return m if t > m else -m if t < -m else t

    def statusword(self) -> int:
        if self._cfg_dirty:
            self._load_config()
        sw = STATUSWORD_OF_STATE[self.state]
        if self.state == OPERATION_ENABLED and self.mode == MODE_CST:
            sw |= 0x1000                    # bit 12 in CST: drive follows the target
        return sw

    def torque_actual(self) -> int:
        p = self._applied_permille()
        return p if p * self.rated_A / 1000.0 != 0.0 else 0

    # ------------------------------------------------------------------ object dictionary hooks
    def _on_od_read(self, index: int, subindex: int, od) -> int | None:
        """Live values for SDO uploads (and the generic TPDO packer)."""
        if index == 0x6041:
            return self.statusword()
        if index == 0x6061:
            self._load_config()
            return self.mode
        if index == 0x606C:
            return self._velocity_raw()
        if index == 0x6077:
            return self.torque_actual()
        if index == 0x603F:
            return self.error_code
        if index == 0x1001:
            return _ERROR_REGISTER.get(self.error_code >> 8, 0x01) if self.error_code else 0
        return None

    def _on_od_write(self, index: int, subindex: int, od, data: bytes) -> None:
        """Controlword/target torque act at once; anything else refreshes the config cache."""
        if index == 0x6040:
            self.apply_controlword(int.from_bytes(data, "little"))
        elif index == 0x6071:
            self.pending = int.from_bytes(data, "little", signed=True)
            if not (self._in_pdo and self.rpdo_type <= 240):    # SDO, or asynchronous RPDO
                self.target = self.pending
        else:
            self._cfg_dirty = True              # reloaded once canopen has stored ``data`` (after this hook)
            if index == 0x1016 and subindex == 1:   # the consumer runs from its configuration
                self.consumer_last = self.owner._now if int.from_bytes(data, "little") & 0xFFFF else None

    def _set_heartbeat_period(self, ms: int) -> None:
        self.hb_period_s = ms / 1000.0
        self.hb_next = self.owner._now if ms > 0 else math.inf

    # ------------------------------------------------------------------ 402 state machine
    def apply_controlword(self, cw: int) -> None:
        new = _transition(self.state, cw, self.cw)
        self.cw = cw
        if self.state == FAULT and new != FAULT:
            if self._persistent_fault():
                return
            self.error_code = 0
            self._emcy(0x0000, 0)                       # error reset
        self.state = new

    def _persistent_fault(self) -> bool:
        f = self.faults.get("out_of_range")
        return f is not None and f["mode"] == "overcurrent"

    def fault(self, code: int) -> None:
        """Fault reaction (instantaneous here): FAULT, zero current, EMCY."""
        if self.state == FAULT:
            return
        self.state = FAULT
        self.error_code = code
        self._emcy(code, _ERROR_REGISTER.get(code >> 8, 0x01))

    def connection_lost(self, emcy_code: int | None) -> None:
        """The reaction 0x6007 asks for (CiA 402-2); ``emcy_code`` is reported in any case."""
        if self._cfg_dirty:
            self._load_config()
        code = self.abort_code
        if code == ABORT_FAULT:
            self.fault(emcy_code if emcy_code is not None else EMCY_HEARTBEAT)
            return
        if emcy_code is not None:
            self.error_code = emcy_code
            self._emcy(emcy_code, _ERROR_REGISTER.get(emcy_code >> 8, 0x01))
        if self.state not in _POWER_ON or code == ABORT_NO_ACTION:
            return
        if code == ABORT_QUICK_STOP and self.qs_option in (5, 6):
            self.state = QUICK_STOP_ACTIVE          # ramped to zero, stays there
        else:
            self.state = SWITCH_ON_DISABLED         # disable voltage, or a quick stop that ends disabled

    def _emcy(self, code: int, register: int) -> None:
        self.counters["emcy"] += 1
        cob, data = emcy_frame(self.node_id, code, register)
        self.owner._tx(cob, data, self)

    # ------------------------------------------------------------------ frames in
    def rx_sdo(self, cob: int, data: bytearray, t: float) -> None:
        """An SDO request to this drive off the bus (lost to an injected bus error, or served)."""
        if "bus_error" in self.faults and self.owner._dropped(self, "rx_dropped"):
            return
        self.node.sdo.on_request(cob, data, t)

    def on_sync(self, t: float) -> None:
        if self.node.nmt._state != NMT_OPERATIONAL:
            return
        if self._cfg_dirty:
            self._load_config()
        self.counters["sync"] += 1
        if not self.wd_armed:
            self._arm(t)
        self.wd_sync = t
        if self._sync_rpdo:
            self.target = self.pending
        every = self._tpdo_every
        if not every:
            return
        self.sync_count += 1
        if self.sync_count % every == 0:
            self._send_tpdo()

    def on_rpdo(self, cob: int, data: bytearray, t: float) -> None:
        """An RPDO1 to this drive off the bus (lost to an injected bus error, or taken)."""
        if "bus_error" in self.faults and self.owner._dropped(self, "rx_dropped"):
            return
        if self.node.nmt._state != NMT_OPERATIONAL:
            return
        if self._cfg_dirty:
            self._load_config()
        if self._codec_rpdo and len(data) == _RPDO1_SIZE:
            cw, tq = _unpack_rpdo(data)
            self.pending = tq
            if not self._sync_rpdo:
                self.target = tq
            self.apply_controlword(cw)
        elif not self._unpack_generic(data):
            self.counters["pdo_length_errors"] += 1
            self._emcy(EMCY_PDO_LENGTH, 0x11)
            return
        self.counters["rpdo"] += 1
        if not self.wd_armed:
            self._arm(t)
        self.wd_rpdo = t

    def _unpack_generic(self, data: bytearray) -> bool:
        """Write each mapped object from its slice of the RPDO (False on a length mismatch)."""
        entries = [(e >> 16, (e >> 8) & 0xFF, (e & 0xFF) // 8) for e in self.rpdo_map]
        if sum(n for _, _, n in entries) != len(data):
            return False
        pos = 0
        self._in_pdo = True
        try:
            for index, sub, n in entries:
                self.node.set_data(index, sub, bytes(data[pos:pos + n]))
                pos += n
        finally:
            self._in_pdo = False
        return True

    def on_consumer_heartbeat(self, t: float) -> None:
        if self.consumer_s > 0:
            self.consumer_last = t

    def on_nmt(self, data: bytearray, t: float) -> None:
        before = self.nmt
        self.node.nmt.on_command(COB_NMT, data, t)
        after = self.nmt
        if after == before:
            return
        if after == NMT_OPERATIONAL:
            self.wd_armed = False               # armed again by the first SYNC/RPDO
            self.sync_count = 0
        elif before == NMT_OPERATIONAL and self.state in _POWER_ON:
            self.connection_lost(None)
        if after == NMT_INITIALISING:
            self._reset(data[0])

    def _reset(self, command: int) -> None:
        """NMT reset node (0x81: all objects) or communication (0x82: 0x1000-0x1FFF)."""
        store = self.node.data_store
        for index in list(store):
            if command == 0x81 or 0x1000 <= index <= 0x1FFF:
                del store[index]
        if command == 0x81:
            self._reset_application()
        else:
            self.hb_period_s, self.hb_next = 0.0, math.inf
            self.consumer_last = None
            self._cfg_dirty = True
            self._load_config()
        cob, data = heartbeat_frame(self.node_id, NMT_INITIALISING)   # boot-up
        self.owner._tx(cob, data, self)
        self.node.nmt._state = NMT_PRE_OPERATIONAL
        ms = self._od(0x1017)
        self._set_heartbeat_period(ms)

    def _arm(self, t: float) -> None:
        if not self.wd_armed:
            self.wd_armed = True
            self.wd_sync = self.wd_rpdo = t

    # ------------------------------------------------------------------ frames out
    def _velocity_raw(self) -> int:
        f = self.faults
        if "out_of_range" in f and f["out_of_range"]["mode"] == "saturate":
            return INT32_MAX
        omega = self.omega + f["offset"]["omega_rad_s"] if "offset" in f else self.omega
        return velocity_to_raw(omega, self.cfg.velocity_factor)

    def _send_tpdo(self) -> None:
        f = self.faults
        if not f and self._codec_tpdo:
            # the cyclic case: no fault to apply, the codec's mapping, no bus_error check
            payload = _pack_tpdo(self.statusword(), self._velocity_raw(), self.torque_actual())
            self.last_tpdo = payload
            self.counters["tpdo"] += 1
            # _tx without a bus_error fault: can.Message(arbitration_id=cob, data=payload, is_extended_id=False)
            self.owner._put(_Message(0.0, self.tpdo_cob, False, False, False, None, len(payload), bytearray(payload)))
            return
        if "dropout" in f:
            return
        if "stuck" in f and self.last_tpdo is not None:
            payload = self.last_tpdo
        elif self.tpdo_map == _CODEC_TPDO_MAP:
            payload = TPDO1.pack(self.statusword(), self._velocity_raw(), self.torque_actual())
        else:
            payload = b"".join(self.node.get_data(e >> 16, (e >> 8) & 0xFF) for e in self.tpdo_map)
        self.last_tpdo = payload
        c = f.get("corrupt")
        if c is not None and (c["fraction"] >= 1.0 or self.owner._rng.random() < c["fraction"]):
            payload = payload[:c["dlc"]]
        self.counters["tpdo"] += 1
        self.owner._tx(self.tpdo_cob, payload, self)

    # ------------------------------------------------------------------ timers
    def timers(self, t: float) -> None:
        """Injected overcurrent, heartbeat consumer, watchdog, heartbeat producer at time t."""
        if self._cfg_dirty:
            self._load_config()
        if self.faults and self._persistent_fault() and self.state in _POWER_ON:
            self.fault(EMCY_OVERCURRENT)
        mo = self.faults.get("motor_outage") if self.faults else None
        if mo is not None and mo["mode"] == "announced" and self.state in _POWER_ON:
            self.fault(EMCY_MOTOR_OUTAGE)
        last = self.consumer_last
        if last is not None and t - last > self.consumer_s:
            self.consumer_last = None                   # re-armed by the next heartbeat
            self.counters["heartbeat_events"] += 1
            self.connection_lost(EMCY_HEARTBEAT)
        if self.wd_armed and self.state in _POWER_ON and self.node.nmt._state == NMT_OPERATIONAL:
            ws, wr = self.wd_sync, self.wd_rpdo
            if t - (ws if ws < wr else wr) > self.owner.watchdog_s:
                self.counters["watchdog_trips"] += 1
                self.wd_armed = False
                self.fault(EMCY_RPDO_TIMEOUT)
        if self.hb_next <= t:
            self._heartbeat(t)

    def _heartbeat(self, t: float) -> None:
        """Producer: one heartbeat when due (after a long gap, one — missed ones are not replayed)."""
        if self.hb_next > t:
            return
        if "no_heartbeat" not in self.faults:
            cob, data = heartbeat_frame(self.node_id, self.nmt)
            self.owner._tx(cob, data, self)
        nxt = self.hb_next + self.hb_period_s
        self.hb_next = nxt if nxt > t else t + self.hb_period_s


class VirtualDriveSet:
    """One virtual CiA 402 drive per configured drive, on one python-can bus.

    The plant feeds ``set_wheel_speed(wheel, omega)`` and reads ``current_A(wheel)``. Call
    ``service(t)`` (lockstep) after the runtime wrote and before it polls, or run
    ``start_realtime()``. Faults: ``inject(kind, wheel=None, **params)`` / ``clear(kind)``,
    kinds and default parameters in :data:`FAULT_KINDS`.
    """

    def __init__(self, cfg: CanBus, bus: can.BusABC, eds_path: str | Path | None = None, seed: int = 0) -> None:
        self.cfg = cfg
        self.bus = bus
        self.watchdog_s = cfg.watchdog_ms / 1000.0
        self._rng = random.Random(seed)
        self._now = 0.0
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._routes: dict[int, tuple[int, VirtualDrive]] = {}
        self._routes_dirty = True
        self.tx_errors = 0
        self._outbox: list[can.Message] | None = None    # hold(): frames kept until release()
        # a LockstepBus takes our fresh messages without copying them
        self._send = getattr(bus, "send_owned", None) or bus.send
        self._send_many = getattr(bus, "send_many_owned", None)      # a batch of fresh frames, given up
        path = Path(eds_path) if eds_path is not None else resolve_config_path(cfg.eds)
        self._network = _SimNetwork(self, bus)
        self._by_sdo_tx: dict[int, VirtualDrive] = {}
        self.drives: dict[str, VirtualDrive] = {}
        for dcfg in cfg.drives:
            d = VirtualDrive(self, dcfg, path)
            self._network.add_node(d.node)
            self._by_sdo_tx[node_cob_id(COB_SDO_TX, d.node_id)] = d
            self.drives[d.wheel] = d
        self._drive_list = list(self.drives.values())
        self._wheel_order = [self.drives.get(w) for w in WHEELS]
        for d in self.drives.values():          # power on: boot-up, then PRE-OPERATIONAL
            cob, data = heartbeat_frame(d.node_id, NMT_INITIALISING)
            self._tx(cob, data, d)
            d.node.nmt._state = NMT_PRE_OPERATIONAL

    # ------------------------------------------------------------------ plant interface
    def set_wheel_speed(self, wheel: str, omega_rad_s: float) -> None:
        """Wheel angular velocity (rad/s) the drive measures from now on."""
        self._set_omega(self.drives[wheel], omega_rad_s)

    def set_wheel_speeds(self, omegas: Sequence[float]) -> None:
        """All four wheel speeds (rad/s) at once, in ``WHEELS`` order (the lockstep
        simulator's call every step)."""
        set_omega = self._set_omega
        for w, d, om in zip(WHEELS, self._wheel_order, omegas):
            if d is None:
                raise KeyError(f"no virtual drive for wheel {w!r}")
            set_omega(d, om)

    @staticmethod
    def _set_omega(d: VirtualDrive, omega_rad_s: float) -> None:
        if not -math.inf < omega_rad_s < math.inf:
            raise ValueError(f"wheel speed of {d.wheel} is {omega_rad_s!r}")
        d.omega = float(omega_rad_s)

    def current_A(self, wheel: str) -> float:
        """Current the converter of ``wheel`` applies (0 unless OPERATION ENABLED and commanded)."""
        return self.drives[wheel].current_A()

    def operation_enabled(self) -> bool:
        """Whether every drive's power stage is in OPERATION ENABLED (the simulators start
        scenario time the first time it is: the runtime enables the drives at its ARM)."""
        for d in self._drive_list:
            if d.state != OPERATION_ENABLED:
                return False
        return True

    def status(self) -> dict[str, dict[str, Any]]:
        """Per wheel, JSON-ready (``rig sim``'s status): applied current, 402 and NMT state,
        error code, counters, times of the latest SYNC / RPDO1 (None before the first)."""
        out = {}
        with self._lock:
            for w in WHEELS:
                d = self.drives.get(w)
                if d is None:
                    continue
                out[w] = {"current_A": d.current_A(), "state": d.state,
                          "nmt": NMT_STATE_NAMES.get(d.nmt, hex(d.nmt)), "error_code": d.error_code,
                          "watchdog_trips": d.counters["watchdog_trips"],
                          "heartbeat_events": d.counters["heartbeat_events"],
                          "counters": dict(d.counters),
                          "last_sync_t": d.wd_sync if d.wd_armed or d.counters["sync"] else None,
                          "last_rpdo_t": d.wd_rpdo if d.wd_armed or d.counters["rpdo"] else None}
        return out

    def state(self, wheel: str) -> str:
        """402 state of the drive of ``wheel``."""
        return self.drives[wheel].state

    def nmt_state(self, wheel: str) -> str:
        """NMT state name of the drive of ``wheel``."""
        n = self.drives[wheel].nmt
        return NMT_STATE_NAMES.get(n, hex(n))

    def od_value(self, wheel: str, index: int, subindex: int = 0) -> int:
        """An object of the drive's dictionary as the runtime would read it over SDO."""
        return self.drives[wheel]._od(index, subindex)

    # ------------------------------------------------------------------ faults
    def inject(self, kind: str, wheel: str | None = None, **params: Any) -> None:
        """Start fault ``kind`` on one drive (all if ``wheel`` is None); see FAULT_KINDS."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {kind!r} (known: {', '.join(FAULT_KINDS)})")
        params = {_ALIASES.get((kind, k), k): v for k, v in params.items()}
        unknown = set(params) - set(FAULT_KINDS[kind])
        if unknown:
            raise ValueError(f"fault {kind!r} takes {sorted(FAULT_KINDS[kind]) or 'no parameters'}, got {sorted(unknown)}")
        p = {**FAULT_KINDS[kind], **params}
        if kind == "out_of_range" and p["mode"] not in ("overcurrent", "saturate"):
            raise ValueError("out_of_range mode is 'overcurrent' or 'saturate'")
        if kind == "motor_outage" and p["mode"] not in ("announced", "silent"):
            raise ValueError("motor_outage mode is 'announced' or 'silent'")
        if kind == "corrupt" and not 0 <= p["dlc"] <= 7:
            raise ValueError("corrupt dlc must be 0..7 (8 is the valid length)")
        if "fraction" in p and not 0.0 <= p["fraction"] <= 1.0:
            raise ValueError(f"{kind} fraction must be within 0..1")
        for d in self._targets(wheel):
            d.faults[kind] = p

    def clear(self, kind: str | None = None, wheel: str | None = None) -> None:
        """End fault ``kind`` (every kind if None) on one drive or all."""
        for d in self._targets(wheel):
            if kind is None:
                d.faults.clear()
            else:
                d.faults.pop(kind, None)

    def _targets(self, wheel: str | None) -> list[VirtualDrive]:
        if wheel is None:
            return list(self.drives.values())
        if wheel not in self.drives:
            raise KeyError(f"no virtual drive for wheel {wheel!r}")
        return [self.drives[wheel]]

    def _dropped(self, d: VirtualDrive | None, direction: str) -> bool:
        """Whether a frame to/from ``d`` is lost to an injected bus error (error frame sent)."""
        if d is None:
            return False
        f = d.faults.get("bus_error")
        if f is None or self._rng.random() >= f["fraction"]:
            return False
        d.counters[direction] += 1
        if f["error_frames"]:
            self._put(can.Message(is_error_frame=True, arbitration_id=0, dlc=0))
        return True

    # ------------------------------------------------------------------ frames
    def _tx(self, cob: int, data: bytes, d: VirtualDrive | None) -> None:
        if d is not None and "bus_error" in d.faults and self._dropped(d, "tx_dropped"):
            return
        # positional: can.Message(arbitration_id=cob, data=data, is_extended_id=False), cheaper
        self._put(_Message(0.0, cob, False, False, False, None, len(data), bytearray(data)))

    def _put(self, msg: can.Message) -> None:
        """Send a fresh message now, or keep it for ``release()`` while held."""
        if self._outbox is not None:
            self._outbox.append(msg)
            return
        try:
            self._send(msg)
        except can.CanError:
            self.tx_errors += 1

    def hold(self) -> None:
        """Keep the frames the drives send until ``release()``, in order (lockstep: the
        simulated rig writes the laser frames before it spends time on these sends)."""
        if self._outbox is None:
            self._outbox = []

    def release(self) -> None:
        """Send the frames kept since ``hold()``, in order, and send directly again."""
        box, self._outbox = self._outbox, None
        if not box:
            return
        send_many = self._send_many
        if send_many is not None:           # the lockstep bus: the whole outbox in one call
            try:
                send_many(box)
                return
            except can.CanError:
                self.tx_errors += len(box)
                return
        send = self._send
        for msg in box:
            try:
                send(msg)
            except can.CanError:
                self.tx_errors += 1

    def _route_table(self) -> dict[int, Callable[[int, bytearray, float], None]]:
        """COB-ID -> the handler of its frames ``(cob, data, t)``, resolved once per
        configuration (rebuilt after a drive's PDO configuration changed): the SDO requests
        and RPDO1 of each drive, then SYNC, NMT and every heartbeat COB-ID (which win over a
        PDO configured onto them)."""
        if self._routes_dirty:
            self._routes_dirty = False
            routes: dict[int, Callable[[int, bytearray, float], None]] = {}
            for d in self.drives.values():
                routes[node_cob_id(COB_SDO_RX, d.node_id)] = d.rx_sdo
                if d.rpdo_cob is not None:
                    routes[d.rpdo_cob] = d.on_rpdo
            routes[COB_SYNC] = self._rx_sync
            routes[COB_NMT] = self._rx_nmt
            for node in range(1, 0x80):
                routes[COB_HEARTBEAT + node] = self._rx_heartbeat
            self._routes = routes
        return self._routes

    def _handle(self, msg: can.Message, t: float) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        cob = msg.arbitration_id
        handler = (self._route_table() if self._routes_dirty else self._routes).get(cob)
        if handler is not None:
            handler(cob, msg.data, t)

    def _rx_sync(self, cob: int, data: bytearray, t: float) -> None:
        for d in self._drive_list:
            if not ("bus_error" in d.faults and self._dropped(d, "rx_dropped")):
                d.on_sync(t)

    def _rx_nmt(self, cob: int, data: bytearray, t: float) -> None:
        if len(data) == 2:
            for d in self._drive_list:
                if not self._dropped(d, "rx_dropped"):
                    d.on_nmt(data, t)

    def _rx_heartbeat(self, cob: int, data: bytearray, t: float) -> None:
        for d in self._drive_list:
            d._load_config()
            if cob - COB_HEARTBEAT == d.consumer_node and not self._dropped(d, "rx_dropped"):
                d.on_consumer_heartbeat(t)

    def _drain_and_tick(self, t: float) -> None:
        self._now = t
        recv, handle = self.bus.recv, self._handle
        while (msg := recv(0.0)) is not None:
            handle(msg, t)
        for d in self._drive_list:
            d.timers(t)

    # ------------------------------------------------------------------ running
    def service(self, t: float) -> None:
        """Lockstep: handle every pending frame, then heartbeats and watchdogs at time ``t``."""
        if self._thread is not None:
            raise RuntimeError("the virtual drives run in realtime; stop() before service()")
        with self._lock:
            self._drain_and_tick(t)

    def start_realtime(self, time_fn: Callable[[], float] = time.monotonic, tick_s: float = 0.0005) -> None:
        """Serve the bus from a thread; timers run on ``time_fn`` (checked every ``tick_s``)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, args=(time_fn, tick_s),
                                        name="virtual-drives", daemon=True)
        self._thread.start()

    def _run(self, time_fn: Callable[[], float], tick_s: float) -> None:
        recv = self.bus.recv
        while not self._stop.is_set():
            msg = recv(tick_s)                  # blocks without the GIL until a frame or tick
            with self._lock:
                t = time_fn()
                self._now = t
                if msg is not None:
                    self._handle(msg, t)
                self._drain_and_tick(t)

    def stop(self) -> None:
        """Stop the realtime thread (no-op in lockstep). The bus stays open (it is the caller's)."""
        th, self._thread = self._thread, None
        if th is not None:
            self._stop.set()
            th.join(5.0)

    close = stop

    @contextlib.contextmanager
    def serving(self, t: float | None = None) -> Iterator["VirtualDriveSet"]:
        """Answer frames from a thread for the duration of a block — the runtime's blocking
        ``DriveBus.open()`` in a lockstep run: ``with drives.serving(t0): driver.open()``.
        Timers run at the frozen time ``t`` (wall time if None)."""
        self.start_realtime(time.monotonic if t is None else (lambda: t))
        try:
            yield self
        finally:
            self.stop()

    def __enter__(self) -> "VirtualDriveSet":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
