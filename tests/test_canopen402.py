"""CiA 402 drives: codec, driver against the virtual drives and against canopen's own LocalNode."""

from __future__ import annotations

import math
import random
import time
import uuid

import can
import canopen
import pytest
from canopen.profiles.p402 import State402
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers import cia402 as c4
from rig_runtime.errors import ConfigError, DeviceInitError
from rig_runtime.hardware import Freshness
from drivers.canopen402 import DriveBus
from rig_runtime.config import WHEELS, CanBus, Drive, resolve_config_path
from sim_backend.virtual_drive import VirtualDriveSet

H = 0.005
RATED = 8.0
VF = 0.0001                       # velocity factor, rad/s per unit of 0x606C
STEP_A = RATED / 1000.0           # one per-mille step of the target torque
EDS = resolve_config_path("irdw-drive.eds")
BASE_SPEEDS = {"fl": 30.0, "fr": 31.0, "rl": -29.0, "rr": 0.5}
# configure() against drives a thread answers (the virtual drives serving, canopen's
# LocalNode): the driver's 0.3 s SDO timeout has no retry, so a stall of that thread on a
# loaded machine would fail the start-up. Only the missing-node test wants a short one.
SDO_TIMEOUT_S = 2.0


def drives(*ids: int) -> tuple[Drive, ...]:
    return tuple(Drive(wheel=w, node_id=n, rated_current_A=RATED, velocity_factor=VF)
                 for w, n in zip(WHEELS, ids))


def can_cfg(channel: str, ids=(1, 2, 3, 4), **kw) -> CanBus:
    return CanBus(interface="virtual", channel=channel, drives=drives(*ids), **kw)


@pytest.fixture
def channel() -> str:
    return f"test-{uuid.uuid4().hex}"


@pytest.fixture
def buses(channel):
    """Runtime side and device side of one python-can virtual bus."""
    a = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    b = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    yield a, b
    a.shutdown()
    b.shutdown()


class Rig:
    """Driver and virtual drives in lockstep: poll, write, devices react, t += h."""

    def __init__(self, drv: DriveBus, vds: VirtualDriveSet) -> None:
        self.drv, self.vds, self.t = drv, vds, 0.0
        self.seen_speeds: dict[str, set[float]] = {w: set() for w in WHEELS}

    def speeds_at(self, t: float) -> dict[str, float]:
        return {w: v + 0.3 * math.sin(7.0 * t + i) for i, (w, v) in enumerate(BASE_SPEEDS.items())}

    def cycle(self, currents, n: int = 1):
        for _ in range(n):
            for w, v in self.speeds_at(self.t).items():
                self.vds.set_wheel_speed(w, v)
                self.seen_speeds[w].add(v)
            self.drv.poll(self.t)
            cmd = currents(self.t) if callable(currents) else currents
            self.drv.write(cmd, self.t)
            self.vds.service(self.t)
            self.t += H
        return self.drv.poll(self.t)

    def activate(self, currents=None, max_cycles: int = 40):
        """``activate`` (the supervisor's ARM) and step until every drive is OPERATION ENABLED."""
        self.drv.activate(self.t)
        for _ in range(max_cycles):
            r = self.cycle({} if currents is None else currents)
            if r.enabled:
                return r
        raise AssertionError([(y.state, y.health.cause) for y in r])

    def measured(self, wheel: str, omega: float, offset: float = 0.0) -> bool:
        """Whether ``omega`` is one of the speeds the plant really had (± quantisation)."""
        return any(abs(omega - (v + offset)) <= VF / 2 + 1e-12 for v in self.seen_speeds[wheel])


def open_lockstep(drv: DriveBus, vds: VirtualDriveSet) -> None:
    """The blocking start-up needs answers: serve the bus from a thread at frozen time 0."""
    with vds.serving(0.0):
        drv.configure()


@pytest.fixture
def configured(buses, channel):
    """Configured (drives started, no power), not activated."""
    cfg = can_cfg(channel)
    vds = VirtualDriveSet(cfg, buses[1])
    drv = DriveBus(cfg, buses[0], period_s=H, sdo_timeout_s=SDO_TIMEOUT_S)
    open_lockstep(drv, vds)
    yield Rig(drv, vds)
    drv.close()


@pytest.fixture
def rig(configured):
    """Configured, activated and stepped until every drive is OPERATION ENABLED."""
    configured.activate()
    return configured


# =========================================================================== codec
def test_rpdo_hand_worked():
    # node 3, enable operation, 2.0 A at 8 A rated -> 250 per mille = 0x00FA
    assert c4.amps_to_permille(2.0, 8.0) == 250
    assert c4.rpdo1_frame(3, 0x000F, 250) == (0x203, bytes.fromhex("0F 00 FA 00"))
    # -2.0 A -> -250 = 0xFF06 (two's complement, little-endian)
    assert c4.rpdo1_frame(3, 0x000F, c4.amps_to_permille(-2.0, 8.0)) == (0x203, bytes.fromhex("0F 00 06 FF"))
    assert c4.decode_rpdo1(bytes.fromhex("06 00 06 FF")) == (c4.CW_SHUTDOWN, -250)


def test_tpdo_hand_worked():
    data = bytes.fromhex("37 12 18 FC FF FF 83 FF")   # 0x1237, -1000, -125
    sw, vel, tq = c4.decode_tpdo1(data)
    assert (sw, vel, tq) == (0x1237, -1000, -125)
    assert c4.state_of(sw) == c4.OPERATION_ENABLED
    assert c4.raw_to_velocity(vel, VF) == pytest.approx(-0.1)
    assert c4.permille_to_amps(tq, 8.0) == pytest.approx(-1.0)
    assert c4.tpdo1_frame(5, 0x1237, -1000, -125) == (0x185, data)


def test_service_frames_hand_worked():
    assert c4.sync_frame() == (0x080, b"")
    assert c4.nmt_frame(c4.NMT_START, 3) == (0x000, b"\x01\x03")
    assert c4.nmt_frame(c4.NMT_ENTER_PRE_OPERATIONAL, 0) == (0x000, b"\x80\x00")
    assert c4.heartbeat_frame(3, c4.NMT_OPERATIONAL) == (0x703, b"\x05")
    assert c4.decode_heartbeat(b"\x85") == c4.NMT_OPERATIONAL      # toggle bit ignored
    assert c4.emcy_frame(3, 0x2310, 0x03) == (0x083, bytes.fromhex("10 23 03 00 00 00 00 00"))
    assert c4.consumer_heartbeat_entry(0x7F, 250) == 0x007F00FA
    assert c4.mapping_entry(0x606C, 0, 32) == 0x606C0020


@pytest.mark.parametrize("sw, state", [
    (0x0000, c4.NOT_READY_TO_SWITCH_ON), (0x0250, c4.SWITCH_ON_DISABLED), (0x0231, c4.READY_TO_SWITCH_ON),
    (0x0233, c4.SWITCHED_ON), (0x1237, c4.OPERATION_ENABLED), (0x0218, c4.FAULT),
    (0x020F, c4.FAULT_REACTION_ACTIVE), (0x0217, c4.QUICK_STOP_ACTIVE), (0x0001, c4.UNKNOWN),
])
def test_statusword_states(sw, state):
    assert c4.state_of(sw) == state


def test_statusword_table_matches_canopen_p402_exhaustively():
    assert c4.SW_MASKS == tuple((s, m, v) for s, (m, v) in State402.SW_MASK.items())
    for sw in range(0x10000):
        expected = next((s for s, (m, v) in State402.SW_MASK.items() if sw & m == v), c4.UNKNOWN)
        assert c4.state_of(sw) == expected, hex(sw)
    for state, sw in c4.STATUSWORD_OF_STATE.items():
        assert c4.state_of(sw) == state


def test_controlwords_match_canopen_p402():
    assert (c4.CW_SHUTDOWN, c4.CW_SWITCH_ON, c4.CW_ENABLE_OPERATION, c4.CW_DISABLE_VOLTAGE,
            c4.CW_QUICK_STOP, c4.CW_FAULT_RESET) == (
        State402.CW_SHUTDOWN, State402.CW_SWITCH_ON, State402.CW_OPERATION_ENABLED,
        State402.CW_DISABLE_VOLTAGE, State402.CW_QUICK_STOP, State402.CW_SWITCH_ON_DISABLED)
    automatic = {"START", c4.NOT_READY_TO_SWITCH_ON, c4.FAULT_REACTION_ACTIVE}
    for (src, dst), cw in State402.TRANSITIONTABLE.items():
        if src not in automatic:
            assert c4.drive_transition(src, cw, 0x0000) == dst, (src, dst, hex(cw))
    for src in (c4.SWITCH_ON_DISABLED, c4.READY_TO_SWITCH_ON, c4.SWITCHED_ON, c4.QUICK_STOP_ACTIVE, c4.FAULT):
        nxt = State402.next_state_indirect(src)
        assert c4.next_controlword(src) == State402.TRANSITIONTABLE[(src, nxt)]
    # no fault reset without a rising edge of bit 7; enable does nothing in SWITCH ON DISABLED
    assert c4.drive_transition(c4.FAULT, 0x80, 0x80) == c4.FAULT
    assert c4.drive_transition(c4.SWITCH_ON_DISABLED, 0x0F, 0x00) == c4.SWITCH_ON_DISABLED


@given(st.integers(0, 0xFFFF), st.integers(c4.INT16_MIN, c4.INT16_MAX), st.integers(1, 127))
def test_rpdo_round_trip(cw, tq, node):
    cob, data = c4.rpdo1_frame(node, cw, tq)
    assert cob == 0x200 + node and len(data) == 4
    assert c4.decode_rpdo1(data) == (cw, tq)


@given(st.integers(0, 0xFFFF), st.integers(c4.INT32_MIN, c4.INT32_MAX), st.integers(c4.INT16_MIN, c4.INT16_MAX))
def test_tpdo_round_trip(sw, vel, tq):
    data = c4.encode_tpdo1(sw, vel, tq)
    assert len(data) == 8 and c4.decode_tpdo1(data) == (sw, vel, tq)


@given(st.floats(-300.0, 300.0), st.floats(0.5, 50.0))
def test_current_round_trip_within_half_a_step(amps, rated):
    p = c4.amps_to_permille(amps, rated)
    if c4.INT16_MIN < p < c4.INT16_MAX:
        assert abs(c4.permille_to_amps(p, rated) - amps) <= rated / 2000 * (1 + 1e-9)
    else:
        assert abs(amps * 1000 / rated) >= 32767.5 - 1e-6          # clipped, never wrapped


@given(st.floats(-1e5, 1e5), st.sampled_from([1e-4, 1e-3, 0.0104719755]))
def test_velocity_round_trip(omega, factor):
    raw = c4.velocity_to_raw(omega, factor)
    back = c4.raw_to_velocity(raw, factor)
    if c4.INT32_MIN < raw < c4.INT32_MAX:
        assert abs(back - omega) <= factor / 2 * (1 + 1e-9)
    else:
        assert math.isnan(back)                                   # saturated is no measurement


@given(st.integers(0, 0xFFFF), st.integers(0, 0xFF), st.binary(max_size=5))
def test_emcy_round_trip(code, reg, vendor):
    cob, data = c4.emcy_frame(7, code, reg, vendor)
    assert cob == 0x87 and len(data) == 8
    assert c4.decode_emcy(data) == (code, reg, vendor.ljust(5, b"\0"))


def test_codec_rejects_wrong_lengths_and_non_finite():
    with pytest.raises(ValueError):
        c4.decode_tpdo1(b"\0" * 5)
    with pytest.raises(ValueError):
        c4.decode_rpdo1(b"\0" * 8)
    with pytest.raises(ValueError):
        c4.amps_to_permille(math.nan, 8.0)
    with pytest.raises(ValueError):
        c4.rpdo1_frame(0, 0, 0)
    assert c4.amps_to_permille(1e9, 8.0) == c4.INT16_MAX


def test_startup_writes_reconfigure_pdos_the_cia301_way():
    w = c4.startup_sdo_writes(drives(3)[0], 0x7F, 250)
    idx = {(i, s): k for k, (i, s, _) in enumerate(w)}
    assert w[idx[(0x6060, 0)]][2] == 10 and w[idx[(0x6075, 0)]][2] == 8000
    # disable (bit 31), clear count, map, set count, enable
    seq = [v for i, s, v in w if i in (0x1800, 0x1A00)]
    assert seq == [0x80000183, 1, 0, 0x60410010, 0x606C0020, 0x60770010, 3, 0x183]
    seq = [v for i, s, v in w if i in (0x1400, 0x1600)]
    assert seq == [0x80000203, 0xFF, 0, 0x60400010, 0x60710010, 2, 0x203]
    assert (0x1016, 1, 0x007F00FA) in w and (0x1017, 0, 50) in w


def test_eds_loads_with_required_objects():
    od = canopen.import_od(str(EDS), 3)
    types = {0x6040: 0x6, 0x6041: 0x6, 0x6060: 0x2, 0x6061: 0x2, 0x6071: 0x3, 0x6077: 0x3,
             0x606C: 0x4, 0x6075: 0x7, 0x6072: 0x6, 0x1017: 0x6, 0x1000: 0x7, 0x1001: 0x5}
    for index, dtype in types.items():
        assert od.get_variable(index).data_type == dtype, hex(index)
    assert od.get_variable(0x1016, 1).data_type == 0x7
    assert od.get_variable(0x1400, 1).default == 0x203 and od.get_variable(0x1800, 1).default == 0x183
    for index in (0x1600, 0x1A00):
        assert all(od.get_variable(index, s) is not None for s in range(9))


# =========================================================================== driver <-> virtual drives
def test_startup_configures_and_activate_enables_every_drive(configured):
    rig = configured
    vds = rig.vds
    for w in WHEELS:
        # configure(): started (NMT operational), configured, but no power
        assert vds.state(w) == c4.SWITCH_ON_DISABLED and vds.nmt_state(w) == "OPERATIONAL"
        assert vds.od_value(w, 0x6060) == 10 and vds.od_value(w, 0x6061) == 10
        assert vds.od_value(w, 0x6075) == 8000
        assert [vds.od_value(w, 0x1A00, s) for s in range(4)] == [3, 0x60410010, 0x606C0020, 0x60770010]
        assert vds.od_value(w, 0x1800, 2) == 1
        assert vds.od_value(w, 0x1016, 1) == (0x7F << 16) | 250
        assert vds.od_value(w, 0x1017) == 50
        assert vds.od_value(w, 0x6007) == c4.ABORT_QUICK_STOP                 # the drive's own safety
        assert vds.od_value(w, 0x605A) == c4.QUICK_STOP_TO_DISABLED
    r = rig.cycle({}, n=3)
    assert not r.enabled and not rig.drv.enabled
    assert all(x.health.state is Freshness.FRESH for x in r)
    r = rig.activate()
    for w in WHEELS:
        assert vds.state(w) == c4.OPERATION_ENABLED and vds.nmt_state(w) == "OPERATIONAL"
    assert r.enabled and rig.drv.enabled
    assert all(x.health.state is Freshness.FRESH for x in r)


def test_no_enable_operation_controlword_until_activate(configured, channel):
    """configure() starts the drives without power: every RPDO carries controlword 0 until
    activate(); only then do the writes walk the drives to OPERATION ENABLED."""
    rig = configured
    spy = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    rpdo_cobs = {c4.node_cob_id(c4.COB_RPDO1, d.node_id): d.wheel for d in rig.vds.cfg.drives}

    def rpdo_controlwords():
        cws = []
        while (msg := spy.recv(0.0)) is not None:
            if msg.arbitration_id in rpdo_cobs:
                cws.append(c4.decode_rpdo1(msg.data)[0])
        return cws

    try:
        rig.cycle({w: 2.0 for w in WHEELS}, n=20)
        before = rpdo_controlwords()
        assert len(before) == 20 * len(WHEELS)
        assert c4.CW_ENABLE_OPERATION not in before and set(before) == {c4.CW_DISABLE_VOLTAGE}
        r = rig.drv.poll(rig.t)
        assert not r.enabled and all(x.state != c4.OPERATION_ENABLED for x in r)
        assert all(rig.vds.current_A(w) == 0.0 for w in WHEELS)
        rig.activate({w: 2.0 for w in WHEELS})
        rig.cycle({w: 2.0 for w in WHEELS}, n=2)
        after = rpdo_controlwords()
        assert c4.CW_ENABLE_OPERATION in after
        assert all(rig.vds.current_A(w) == pytest.approx(2.0) for w in WHEELS)
    finally:
        spy.shutdown()


def test_currents_arrive_and_speeds_come_back(rig):
    cmd = {"fl": 2.0, "fr": -1.5, "rl": 0.3141, "rr": -3.9999}
    r = rig.cycle(cmd, n=5)
    for w, amps in cmd.items():
        assert abs(rig.vds.current_A(w) - amps) <= STEP_A / 2 + 1e-12
        assert abs(r[w].current_A - amps) <= STEP_A / 2 + 1e-12          # torque actual
        # the TPDO polled at t was sampled at SYNC t - h
        assert r[w].omega == pytest.approx(rig.speeds_at(rig.t - H)[w], abs=VF / 2 + 1e-12)
        assert r[w].t == pytest.approx(rig.t) and r[w].health.fresh
    # a sequence in wheel order works the same; NaN is sent as 0 A and counted
    # (the activation cycles sent {}: count from here)
    c0 = rig.drv.counters()
    r = rig.cycle([1.0, math.nan, -1.0], n=2)
    assert [rig.vds.current_A(w) for w in WHEELS] == pytest.approx([1.0, 0.0, -1.0, 0.0])
    c1 = rig.drv.counters()
    assert c1["nan_commands"] - c0["nan_commands"] == 2
    assert c1["missing_commands"] - c0["missing_commands"] == 2


def test_watchdog_cuts_current_when_writes_stop(rig):
    rig.cycle({w: 2.0 for w in WHEELS}, n=5)
    t_last = rig.t - H
    rig.vds.service(t_last + 0.045)
    assert rig.vds.current_A("fl") == pytest.approx(2.0)                # within cfg.watchdog_ms
    rig.vds.service(t_last + 0.055)
    assert all(rig.vds.current_A(w) == 0.0 and rig.vds.state(w) == c4.FAULT for w in WHEELS)
    r = rig.drv.poll(t_last + 0.06)
    for x in r:
        assert x.health.state is Freshness.INVALID
        assert "EMCY 0x8250" in x.health.cause and x.health.errors == 1
    # writes resume: a faulted drive is held off, not silently re-enabled
    r = rig.cycle({w: 2.0 for w in WHEELS}, n=5)
    assert not r.enabled and all(rig.vds.current_A(w) == 0.0 for w in WHEELS)
    assert "drive in FAULT" in r["fl"].health.cause


def test_drive_stops_when_runtime_heartbeat_stops(rig, buses):
    rig.cycle({w: 2.0 for w in WHEELS}, n=2)        # the runtime's heartbeat went out at t=0
    # keep SYNC + RPDOs coming (no watchdog trip), but without the driver's heartbeat
    for _ in range(60):
        buses[0].send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        for d in rig.vds.cfg.drives:
            cob, data = c4.rpdo1_frame(d.node_id, c4.CW_ENABLE_OPERATION, 250)
            buses[0].send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
        rig.vds.service(rig.t)
        if rig.t < 0.24:
            assert rig.vds.current_A("fl") == pytest.approx(2.0)
        rig.t += H
    # the reaction configure() asked for: 0x6007 quick stop, 0x605A ending SWITCH ON DISABLED
    assert all(rig.vds.current_A(w) == 0.0 and rig.vds.state(w) == c4.SWITCH_ON_DISABLED for w in WHEELS)
    assert all(rig.vds.drives[w].error_code == c4.EMCY_HEARTBEAT for w in WHEELS)


N_FAULT = 40        # cycles (= SYNCs sent) with the fault injected

# what the driver reports of each fault: the drive's own word (INVALID) or an observation
# (FRESH, with its counts) that the supervisor's rules judge (stale, stuck, corrupt)
FAULT_CASES = [
    ("dropout", {}, Freshness.FRESH, ""),
    ("no_heartbeat", {}, Freshness.INVALID, "heartbeat missing"),
    ("bus_error", {"fraction": 1.0}, Freshness.INVALID, "heartbeat missing"),
    ("out_of_range", {}, Freshness.INVALID, "EMCY 0x2310"),
    ("out_of_range", {"mode": "saturate"}, Freshness.INVALID, "INT32 limit"),
    ("stuck", {}, Freshness.FRESH, ""),
    ("corrupt", {}, Freshness.FRESH, f"garbled TPDO discarded (DLC 5 != 8, {N_FAULT} since open)"),
    ("corrupt", {"fraction": 0.5, "dlc": 3}, Freshness.FRESH, ""),
    ("offset", {"omega_rad_s": 1.0}, Freshness.FRESH, ""),
]


@pytest.mark.parametrize("kind, params, freshness, cause", FAULT_CASES, ids=lambda v: str(v)[:20])
def test_fault_kinds_are_reported_and_never_invent_values(rig, kind, params, freshness, cause):
    def varying(t):                                  # a changing command
        return {w: 1.0 + 0.5 * math.sin(20 * t) for w in WHEELS}

    r0 = rig.cycle(varying, n=10)
    assert r0.enabled and r0["rl"].syncs_unanswered == 0
    t_inject = rig.t
    tpdo0 = rig.drv.counters()["rl.tpdo"]
    rig.vds.inject(kind, "rl", **params)
    r = rig.cycle(varying, n=N_FAULT)
    x = r["rl"]
    assert x.health.state is freshness, x.health.cause
    assert cause in x.health.cause
    valid = rig.drv.counters()["rl.tpdo"] - tpdo0
    offset = params.get("omega_rad_s", 0.0)
    if kind in ("dropout", "bus_error") or kind == "corrupt" and not params:
        # no valid TPDO1 since the injection: every SYNC sent since is unanswered, the last
        # real value is kept with its time
        assert valid == 0 and x.syncs_unanswered == N_FAULT and x.t <= t_inject
    else:
        # the garbled answers since the latest valid one (each SYNC gets one frame)
        assert x.syncs_unanswered <= x.health.bad_frames if kind == "corrupt" else x.syncs_unanswered == 0
    if kind == "out_of_range" and params.get("mode") == "saturate":
        assert math.isnan(x.omega)
    else:
        assert rig.measured("rl", x.omega, offset), (x.omega, kind)
    if kind == "out_of_range" and not params:
        assert x.state == c4.FAULT and rig.vds.current_A("rl") == 0.0
    if kind == "stuck":                              # the same payload over and over: judged by `stuck`
        assert valid == N_FAULT and x.omega == r0["rl"].omega and x.current_A == r0["rl"].current_A
    if kind == "corrupt":                            # each SYNC answered by one frame, valid or garbled
        assert x.health.bad_frames + valid == N_FAULT and x.health.bad_frames >= 5
        # a note while the latest TPDO1 was garbled, which is exactly when a SYNC is unanswered
        assert ("DLC 3 != 8" in x.health.cause or "DLC 5 != 8" in x.health.cause) == (x.syncs_unanswered > 0)
    else:
        assert x.health.bad_frames == 0
    if kind == "bus_error":                          # counted and stamped; the other drives are fine
        assert rig.drv.error_frames > 0 and r.bus.errors == rig.drv.error_frames
        assert r.bus.state is Freshness.FRESH and r.bus.cause == "bus error: error frame on the bus"
        assert r.bus_error_t == rig.t                # the final poll drained the latest error frame
    else:
        assert r.bus.errors == 0 and r.bus_error_t == -math.inf and r.bus.cause == ""
    assert all(r[w].health.fresh and r[w].syncs_unanswered == 0 for w in ("fl", "fr", "rr")), \
        [r[w].health.cause for w in WHEELS]
    assert r.enabled is (freshness is Freshness.FRESH)
    # clear the fault, deactivate and activate again (the supervisor's FAULT, reset and ARM;
    # fault reset where needed): everything comes back
    rig.vds.clear(kind)
    rig.drv.deactivate(rig.t)
    rig.drv.activate(rig.t)
    for _ in range(60):
        r = rig.cycle(varying)
        if r.enabled:
            break
    assert r.enabled, [(y.state, y.health.cause) for y in r]
    rig.cycle(varying)                               # ready: the next write carries torque
    assert abs(rig.vds.current_A("rl") - varying(rig.t - H)["rl"]) <= STEP_A / 2 + 1e-12


def test_deactivate_leaves_drives_off_until_activate(rig):
    rig.cycle({w: 2.0 for w in WHEELS}, n=5)
    rig.drv.deactivate(rig.t)
    rig.vds.service(rig.t)
    for w in WHEELS:
        assert rig.vds.state(w) == c4.SWITCH_ON_DISABLED and rig.vds.current_A(w) == 0.0
        assert rig.vds.nmt_state(w) == "PRE-OPERATIONAL"
    r = rig.cycle({w: 2.0 for w in WHEELS}, n=40)                 # writes keep them off
    assert not r.enabled and all(rig.vds.current_A(w) == 0.0 for w in WHEELS)
    assert "NMT state PRE-OPERATIONAL" in r["fl"].health.cause
    rig.drv.activate(rig.t)
    r = rig.cycle({w: 2.0 for w in WHEELS}, n=15)
    assert r.enabled and all(rig.vds.current_A(w) == pytest.approx(2.0) for w in WHEELS)


def test_an_isolated_drive_is_quick_stopped_and_disabled_while_the_others_run(rig):
    """The supervisor's RECONFIGURED (docs/safety.md, "Drive outages"): one drive held off,
    the others keep their current; the next activation enables it again."""
    rig.cycle({w: 2.0 for w in WHEELS}, n=3)
    rig.drv.isolate("fl", rig.t)
    r = rig.cycle({w: 2.0 for w in WHEELS}, n=10)
    assert rig.vds.state("fl") == c4.SWITCH_ON_DISABLED and rig.vds.current_A("fl") == 0.0
    assert all(rig.vds.current_A(w) == pytest.approx(2.0) for w in ("fr", "rl", "rr"))
    assert not r.enabled and not r["fl"].enabled and r["fr"].enabled
    rig.drv.deactivate(rig.t)
    rig.vds.service(rig.t)
    rig.drv.activate(rig.t)
    r = rig.cycle({w: 2.0 for w in WHEELS}, n=15)
    assert r.enabled and rig.vds.current_A("fl") == pytest.approx(2.0)


def test_send_failures_are_counted_not_raised(rig, buses, monkeypatch):
    rig.cycle({}, n=3)

    def broken(msg, timeout=None):
        raise can.CanOperationError("Transmit buffer full")

    monkeypatch.setattr(buses[0], "send", broken)
    rig.drv.write({w: 1.0 for w in WHEELS}, rig.t)
    r = rig.drv.poll(rig.t)
    assert rig.drv.send_errors == 5 and "Transmit buffer full" in rig.drv.last_bus_error
    # reported, not judged: a count, the latest cause and its time (the supervisor decides)
    assert r.bus.state is Freshness.FRESH and r.bus.errors == 5 and r.bus_error_t == rig.t
    assert r.bus.cause == "bus error: send of 0x%03X failed: Transmit buffer full" % (0x200 + 4)
    assert all(x.health.fresh and "bus error" not in x.health.cause for x in r)


def test_poll_survives_garbage_frames(rig, buses):
    rng = random.Random(1)
    rig.cycle({}, n=2)
    for _ in range(2000):
        cob = rng.choice([0x80 + 1, 0x180 + 2, 0x700 + 3, 0x580 + 4, rng.randrange(0x800)])
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
        buses[1].send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
    r = rig.drv.poll(rig.t)
    assert rig.drv.counters()["rx_frames"] >= 2000
    assert all(r[w].health.bad_frames > 0 for w in ("fl", "fr", "rl"))


def test_missing_drive_names_the_node(buses, channel):
    # the missing node (9, fl) is configured first: the short SDO timeout applies to its
    # first SDO only, never to the ~25 SDOs the present node (1, fr) answers from a thread
    present = CanBus(interface="virtual", channel=channel,
                     drives=(Drive(wheel="fr", node_id=1, rated_current_A=RATED, velocity_factor=VF),))
    vds = VirtualDriveSet(present, buses[1])
    drv = DriveBus(can_cfg(channel, ids=(9, 1)), buses[0], sdo_timeout_s=0.05)
    t0 = time.monotonic()
    with pytest.raises(DeviceInitError, match=r"node 9 \(fl\).*no SDO answer"):
        open_lockstep(drv, vds)
    assert time.monotonic() - t0 < 2.0 and not drv.is_configured
    buses[0].send(can.Message(arbitration_id=0x80, data=b""))      # a passed-in bus stays usable
    drv.close()


def test_drive_stuck_in_fault_names_node_and_state(buses, channel):
    """configure() no longer powers the drives, so a drive that faults as soon as it is
    powered shows up after activate(): never enabled, reported with its node and state."""
    cfg = can_cfg(channel, ids=(5,))
    vds = VirtualDriveSet(cfg, buses[1])
    vds.inject("out_of_range")                                      # overcurrent as soon as powered
    drv = DriveBus(cfg, buses[0], period_s=H, enable_timeout_s=0.2, sdo_timeout_s=SDO_TIMEOUT_S)
    open_lockstep(drv, vds)
    try:
        t = 0.0
        for k in range(43):
            if k == 3:
                drv.activate(t)
            drv.poll(t)
            drv.write({"fl": 1.0}, t)
            vds.service(t)
            t += H
        r = drv.poll(t)
        x = r["fl"]
        assert not r.enabled and not drv.enabled
        assert x.node_id == 5 and x.state == c4.FAULT and vds.state("fl") == c4.FAULT
        assert x.health.state is Freshness.INVALID and "drive in FAULT" in x.health.cause
        assert "EMCY 0x2310" in x.health.cause and vds.current_A("fl") == 0.0
    finally:
        drv.close()


def test_bus_open_failure_and_config_checks(channel):
    cfg = CanBus(interface="no-such-interface", channel="x", drives=drives(1))
    with pytest.raises(DeviceInitError, match="can no-such-interface:x"):
        DriveBus(cfg).configure()
    with pytest.raises(ConfigError, match="heartbeat_timeout_factor"):
        DriveBus(can_cfg(channel, heartbeat_timeout_factor=1.0))
    with pytest.raises(ConfigError, match="runtime_node_id"):
        DriveBus(can_cfg(channel), runtime_node_id=3)


def test_owned_bus_open_close_idempotent(buses, channel):
    vds = VirtualDriveSet(can_cfg(channel), buses[1])
    drv = DriveBus(can_cfg(channel), sdo_timeout_s=SDO_TIMEOUT_S)   # creates its own virtual bus in configure()
    drv.close()                                 # never configured: fine
    open_lockstep(drv, vds)
    own = drv._bus
    assert drv.is_configured and own is not buses[0]
    drv.close()
    drv.close()
    assert not drv.is_configured and own._is_shutdown
    vds.service(1.0)
    assert all(vds.state(w) == c4.SWITCH_ON_DISABLED for w in WHEELS)   # close() disabled them
    r = drv.poll(1.0)
    drv.write([1.0] * 4, 1.0)                   # closed: nothing sent, nothing raised
    assert all(x.health.state is Freshness.INVALID and x.health.cause == "driver not configured" for x in r)


def test_synchronous_rpdo_acts_at_next_sync(rig, buses):
    rig.cycle({w: 1.0 for w in WHEELS}, n=3)
    node = rig.vds.drives["fl"].node
    node.sdo.download(0x1400, 2, b"\x01")                             # RPDO1 type 1 (synchronous)
    cob, data = c4.rpdo1_frame(1, c4.CW_ENABLE_OPERATION, 500)
    buses[0].send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
    rig.vds.service(rig.t)
    assert rig.vds.current_A("fl") == pytest.approx(1.0)
    buses[0].send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
    rig.vds.service(rig.t)
    assert rig.vds.current_A("fl") == pytest.approx(4.0)


def test_unconfigured_tpdo_mapping_shows_up_as_garbled(rig):
    """A drive left with its default mapping (statusword only) sends 2-byte TPDOs."""
    node = rig.vds.drives["rr"].node
    node.sdo.download(0x1A00, 0, b"\x01")
    r = rig.cycle({}, n=10)
    assert r["rr"].health.state is Freshness.FRESH and r["rr"].syncs_unanswered == 10
    assert r["rr"].health.bad_frames == 10
    assert "DLC 2 != 8" in r["rr"].health.cause and r["fl"].health.fresh and r["fl"].health.cause == ""


# test_realtime_mode writes from this (normally scheduled) test thread: the machine's
# scheduling is not what it checks, so the drives' RPDO watchdog is the real-time tests'
# stated stall (tests/e2e.py REALTIME_STALL_S = 0.3 s), not the shipped 50 ms
REALTIME_WATCHDOG_MS = 300


def test_realtime_mode(channel):
    """The virtual drives serving from their own thread in real time: the driver enables
    them, the commanded current reaches them, and when the writes stop their watchdog cuts it."""
    a = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    b = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    cfg = can_cfg(channel, watchdog_ms=REALTIME_WATCHDOG_MS)
    watchdog_s = cfg.watchdog_ms / 1000
    vds = VirtualDriveSet(cfg, b)
    drv = DriveBus(cfg, a, period_s=H, sdo_timeout_s=SDO_TIMEOUT_S)
    vds.start_realtime()
    try:
        drv.configure()
        drv.activate(time.monotonic())
        for w in WHEELS:
            vds.set_wheel_speed(w, BASE_SPEEDS[w])
        state = {"last": None, "gap": 0.0}

        def cycle_until(done, timeout: float):
            """Poll and write -1.25 A every period until ``done(r)``; the last readings, or
            None if ``timeout`` passed first."""
            deadline = time.monotonic() + timeout
            t_next = time.monotonic()
            while True:
                now = time.monotonic()
                r = drv.poll(now)
                drv.write({w: -1.25 for w in WHEELS}, now)
                if state["last"] is not None:
                    state["gap"] = max(state["gap"], now - state["last"])
                state["last"] = now
                if done(r):
                    return r
                if now > deadline:
                    return None
                t_next += H
                time.sleep(max(0.0, t_next - time.monotonic()))

        def spoiled(what: str):
            pytest.fail(f"{what} (longest gap between writes {state['gap'] * 1e3:.0f} ms, "
                        f"drive watchdog {watchdog_s * 1e3:.0f} ms)")

        k = {"n": 0}

        def enabled(r):
            k["n"] += 1
            return k["n"] > 10 and r.enabled

        r = cycle_until(enabled, 5.0)
        if r is None:
            spoiled(f"not enabled within 5 s: {[x.health.cause for x in drv.poll(time.monotonic())]}")
        # the drive thread applies the current when it handles the RPDOs: cycle until it has
        r = cycle_until(lambda r: all(vds.current_A(w) == pytest.approx(-1.25, abs=STEP_A / 2)
                                      for w in WHEELS), 2.0)
        if r is None:
            spoiled(f"currents {[vds.current_A(w) for w in WHEELS]} A, not -1.25 A within 2 s")
        assert r["rl"].omega == pytest.approx(BASE_SPEEDS["rl"], abs=VF)
        # writes stop: converters cut current (the drives' watchdog, cfg.watchdog_ms)
        deadline = time.monotonic() + 2.0
        while not all(vds.current_A(w) == 0.0 for w in WHEELS):
            assert time.monotonic() < deadline, [vds.current_A(w) for w in WHEELS]
            time.sleep(0.005)
    finally:
        vds.stop()
        drv.close()
        a.shutdown()
        b.shutdown()


# =========================================================================== independent peer
def _peer_402(node: canopen.LocalNode) -> None:
    """Minimal 402 behaviour for a plain canopen LocalNode, from canopen's own p402 tables."""
    state = {"s": "SWITCH ON DISABLED"}

    def put_sw() -> None:
        node.data_store.setdefault(0x6041, {})[0] = State402.SW_MASK[state["s"]][1].to_bytes(2, "little")

    def on_write(index, subindex, od, data):
        if index == 0x6040:
            cw = int.from_bytes(data, "little")
            for (src, dst), code in State402.TRANSITIONTABLE.items():
                if src == state["s"] and code == cw:
                    state["s"] = dst
                    break
            put_sw()
        elif index == 0x6060:
            node.data_store.setdefault(0x6061, {})[0] = bytes(data)

    node.add_write_callback(on_write)
    put_sw()


def test_startup_against_canopen_localnode(buses, channel):
    cfg = can_cfg(channel, ids=(1, 2))
    net = canopen.Network(buses[1])
    net.NOTIFIER_CYCLE = 0.01
    net.connect()
    peers = []
    try:
        for d in cfg.drives:
            node = canopen.LocalNode(d.node_id, canopen.import_od(str(EDS), d.node_id))
            _peer_402(node)
            net.add_node(node)
            peers.append(node)
        drv = DriveBus(cfg, buses[0], period_s=H, sdo_timeout_s=SDO_TIMEOUT_S)
        drv.configure()
        try:
            deadline = time.monotonic() + 5.0     # the peer's notifier thread handles the NMT start
            while any(n.nmt.state != "OPERATIONAL" for n in peers) and time.monotonic() < deadline:
                time.sleep(0.005)
            for node in peers:
                assert node.nmt.state == "OPERATIONAL"
                assert node.sdo[0x6060].raw == 10 and node.sdo[0x6075].raw == 8000
                assert [node.sdo[0x1A00][s].raw for s in range(4)] == [3, 0x60410010, 0x606C0020, 0x60770010]
                assert node.sdo[0x1800][1].raw == 0x180 + node.id and node.sdo[0x1800][2].raw == 1
                assert node.sdo[0x1016][1].raw == 0x007F00FA and node.sdo[0x1017].raw == 50
                # configure() leaves the power stage off (enabling is activate()'s job)
                assert c4.state_of(node.sdo[0x6041].raw) == c4.SWITCH_ON_DISABLED
            # canopen's LocalNode produces the heartbeat itself (python-can periodic task)
            drv.poll(time.monotonic())
            deadline = time.monotonic() + 5.0
            while True:
                time.sleep(0.01)
                r = drv.poll(time.monotonic())
                counters = drv.counters()
                if all(counters[f"{x.wheel}.heartbeat"] >= 2 for x in r) or time.monotonic() > deadline:
                    break
            for x in r:
                assert x.nmt_state == c4.NMT_OPERATIONAL and counters[f"{x.wheel}.heartbeat"] >= 2
                assert x.health.state is Freshness.FRESH and x.health.cause == "no TPDO received yet"
                assert math.isnan(x.t) and x.syncs_unanswered == 0     # no SYNC sent, none answered
        finally:
            drv.close()
        deadline = time.monotonic() + 5.0          # the peer's notifier thread handles the NMT
        while any(n.nmt.state != "PRE-OPERATIONAL" for n in peers) and time.monotonic() < deadline:
            time.sleep(0.005)
        assert all(node.nmt.state == "PRE-OPERATIONAL" for node in peers)
    finally:
        for node in peers:
            node.nmt.stop_heartbeat()
        net.notifier.stop(1.0)


def test_virtual_wheel_speeds_set_together_or_refused(buses, channel):
    vds = VirtualDriveSet(can_cfg(channel), buses[1])
    vds.set_wheel_speeds([BASE_SPEEDS[w] for w in WHEELS])
    assert [vds.drives[w].omega for w in WHEELS] == [BASE_SPEEDS[w] for w in WHEELS]
    with pytest.raises(ValueError, match="wheel speed of rl is nan"):
        vds.set_wheel_speeds([1.0, 2.0, math.nan, 4.0])
    with pytest.raises(ValueError, match="wheel speed of fr is inf"):
        vds.set_wheel_speed("fr", math.inf)
    part = VirtualDriveSet(can_cfg(channel, ids=(1,)), buses[1])
    with pytest.raises(KeyError, match="no virtual drive for wheel 'fr'"):
        part.set_wheel_speeds([1.0, 2.0, 3.0, 4.0])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(steps=st.lists(st.sampled_from(("write", "service", "poll")), min_size=1, max_size=25))
def test_unanswered_counts_the_syncs_sent_not_the_time(configured, steps):
    """The count is one per SYNC the runtime sent and 0 again with each valid TPDO1 drained;
    polls that send nothing (a runtime that is late) never raise it, whatever time passes.
    Model: every SYNC the drives were served is answered by one TPDO1 per drive."""
    rig = configured
    rig.drv.poll(rig.t)
    rig.vds.service(rig.t)
    base = rig.drv.poll(rig.t)["fl"].syncs_unanswered        # everything served and drained
    count, syncs_at_drives, tpdos_on_wire = base, 0, 0
    for step in steps:
        rig.t += H * 3                                       # time passes; it is not what counts
        if step == "write":
            rig.drv.write({}, rig.t)
            count, syncs_at_drives = count + 1, syncs_at_drives + 1
        elif step == "service":
            rig.vds.service(rig.t)
            tpdos_on_wire, syncs_at_drives = tpdos_on_wire + syncs_at_drives, 0
        else:
            r = rig.drv.poll(rig.t)
            if tpdos_on_wire:
                count, tpdos_on_wire = 0, 0
            assert [x.syncs_unanswered for x in r] == [count] * 4, steps
