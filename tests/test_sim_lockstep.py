"""The lockstep simulator: ``LaserGroup`` writes exactly the bytes of
``VirtualLaser.emit_until`` and waits until the kernel delivered them; ``LockstepBus``
keeps python-can's bus contract; the virtual drives' outbox keeps frame order; and
``SimulatedRig`` driven only through ``advance(t)`` and its transports is deterministic
for a seed, starts scenario time when the drives are enabled, stalls the runtime's
release, and refuses a scenario fault on a device it does not have."""

from __future__ import annotations

import dataclasses
import fcntl
import math
import os
import struct
import termios
import threading

import can
import numpy as np
import pytest

from rig_runtime.clock import LockstepClock
from rig_runtime.config import WHEELS, LaserDevice
from rig_runtime.errors import ConfigError
from rig_runtime.scenario import Disturbance, FaultInjection, Scenario
from sim_backend.lockstep_bus import LockstepBus
from sim_backend.rig import SimulatedRig
from sim_backend.virtual_drive import VirtualDriveSet
from sim_backend.virtual_laser import LaserGroup, VirtualLaser

H = 0.005


def _laser_cfgs() -> list[LaserDevice]:
    return [LaserDevice(role=r, port="sim", measuring_range_mm=mr, offset_mm=off, output_rate_hz=1000)
            for r, mr, off in (("b_f", 50, 45), ("b_r", 50, 45), ("s_fl", 25, 25), ("s_fr", 25, 25))]


class _Pair:
    """The same lasers twice: one set emitted one by one, one through a LaserGroup; the
    slave ends drained like the runtime does."""

    def __init__(self, opts: list[dict]):
        cfgs = _laser_cfgs()
        self.ref = [VirtualLaser(c, seed=i, **o) for i, (c, o) in enumerate(zip(cfgs, opts))]
        self.grp = [VirtualLaser(c, seed=i, **o) for i, (c, o) in enumerate(zip(cfgs, opts))]
        self.group = LaserGroup(self.grp)
        self.fds = [[os.open(v.port_name, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY) for v in vs]
                    for vs in (self.ref, self.grp)]
        self.got = [[bytearray() for _ in cfgs] for _ in range(2)]

    def both(self):
        return zip(self.ref, self.grp)

    def cycle(self, t: float) -> None:
        for v in self.ref:
            v.emit_until(t)
        self.group.emit(t)
        self.group.wait()
        for side in range(2):
            for i, fd in enumerate(self.fds[side]):
                self.got[side][i] += _read(fd)

    def close(self) -> None:
        for fds in self.fds:
            for fd in fds:
                os.close(fd)
        for v in self.ref + self.grp:
            v.close()


def _read(fd: int) -> bytes:
    try:
        return os.read(fd, 65536)
    except BlockingIOError:
        return b""


def _queued(fd: int) -> int:
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]


def _assert_same(p: _Pair) -> None:
    assert p.got[0] == p.got[1]
    for a, b in p.both():
        assert (a.frames_sent, a.frames_suppressed, a.frames_corrupted, a.bytes_written, a.bytes_dropped,
                a._last_x, a._sampled, a._released) == \
               (b.frames_sent, b.frames_suppressed, b.frames_corrupted, b.bytes_written, b.bytes_dropped,
                b._last_x, b._sampled, b._released)


def test_group_writes_the_bytes_of_emit_until_through_faults_and_span_edges():
    p = _Pair([{"noise_std_m": 1e-6}] * 4)
    rng = np.random.default_rng(3)
    faults = {200: ("stuck", 2, {}), 260: (None, 2, {}), 300: ("corrupt", 1, {"p": 0.4}),
              340: ("dropout", 3, {}), 380: (None, 1, {}), 400: (None, 3, {}),
              450: ("offset", 0, {"amount_m": 1e-4}), 480: ("out_of_range", 0, {}), 520: (None, 0, {})}
    try:
        for k in range(1, 1200):       # > 4096 frames: noise blocks refill inside the run
            for a, b in p.both():
                span = a.cfg.measuring_range_mm
                # mostly in the span, some beyond both ends, some within noise of an edge
                rel = rng.choice([rng.uniform(0.0, 1.0), rng.uniform(-0.05, 1.05),
                                  -0.01 + rng.normal(0, 1e-5), 1.01 + rng.normal(0, 1e-5)], p=[0.7, 0.1, 0.1, 0.1])
                d = (a.cfg.offset_mm + rel * span) / 1000.0
                a.set_distance(d)
                b.set_distance(d)
            if k in faults:
                kind, i, kw = faults[k]
                for v in (p.ref[i], p.grp[i]):
                    v.inject(kind, **kw) if kind else v.clear()
            p.cycle(k * H)
        _assert_same(p)
        assert sum(len(g) for g in p.got[1]) == sum(v.bytes_written for v in p.grp) > 0
    finally:
        p.close()


@pytest.mark.parametrize("opts", [
    [{"noise_std_m": 0.0}] * 4,                                          # noise-free
    [{"noise_std_m": 2e-6}, {"noise_std_m": 0.0}, {"noise_std_m": 1e-6, "latency_s": 0.002},
     {"noise_std_m": 1e-6, "quantization_m": 2e-6}],                    # mixed: lean and generic paths
    [{"noise_std_m": 1e-6, "output_rate_hz": 4000.0}] * 2 + [{"noise_std_m": 1e-6}] * 2,   # two rates
])
def test_group_matches_emit_until_for_any_laser_setup(opts):
    p = _Pair(opts)
    try:
        for k in range(1, 300):
            for j, (a, b) in enumerate(p.both()):
                d = (a.cfg.offset_mm + (0.5 + 0.4 * np.sin(0.01 * k + j)) * a.cfg.measuring_range_mm) / 1000.0
                a.set_distance(d)
                b.set_distance(d)
            p.cycle(k * H)
        _assert_same(p)
    finally:
        p.close()


def test_group_nan_distance_raises_like_emit_until():
    p = _Pair([{"noise_std_m": 1e-6}] * 4)
    try:
        p.cycle(H)
        p.ref[1].set_distance(float("nan"))
        p.grp[1].set_distance(float("nan"))
        with pytest.raises(ValueError, match="NaN"):
            p.ref[1].emit_until(2 * H)
        with pytest.raises(ValueError, match="NaN"):
            p.group.emit(2 * H)
    finally:
        p.close()


def test_group_wait_returns_with_every_byte_readable_even_if_the_reader_lags():
    vls = [VirtualLaser(c, noise_std_m=1e-6, seed=i) for i, c in enumerate(_laser_cfgs())]
    group = LaserGroup(vls)
    fds = [os.open(v.port_name, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY) for v in vls]
    try:
        total = [0] * len(vls)
        for k in range(1, 60):
            group.emit(k * H)
            group.wait()
            for i, v in enumerate(vls):
                assert _queued(fds[i]) == v.bytes_written - total[i]
            if k % 3 == 0:                       # the reader drains only every third cycle
                for i, fd in enumerate(fds):
                    total[i] += len(_read(fd))
        assert all(v.delivery_timeouts == 0 for v in vls)
    finally:
        for fd in fds:
            os.close(fd)
        for v in vls:
            v.close()


# --------------------------------------------------------------------------- LockstepBus
@pytest.fixture
def pair():
    a, b = LockstepBus(channel="t-lockstep"), LockstepBus(channel="t-lockstep")
    yield a, b
    a.shutdown()
    b.shutdown()


def test_lockstep_bus_send_snapshots_the_frame(pair):
    a, b = pair
    msg = can.Message(arbitration_id=0x201, data=[1, 2, 3, 4], is_extended_id=False)
    a.send(msg)
    msg.data[0] = 9                                     # the sender reuses its message
    got = b.recv(0.0)
    assert got is not msg and bytes(got.data) == b"\x01\x02\x03\x04"
    assert (got.arbitration_id, got.dlc, got.is_extended_id, got.is_rx) == (0x201, 4, False, True)
    assert a.recv(0.0) is None and b.recv(0.0) is None  # not to itself, nothing more


def test_lockstep_bus_send_many_snapshots_in_order(pair):
    a, b = pair
    msgs = [can.Message(arbitration_id=0x80, data=b"", is_extended_id=False),
            can.Message(arbitration_id=0x201, data=[1, 2, 3, 4], is_extended_id=False),
            can.Message(arbitration_id=0x202, data=[5, 6], is_extended_id=False)]
    a.send_many(msgs)
    msgs[1].data[0] = 9
    got = [b.recv(0.0) for _ in range(3)]
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(0x80, b""), (0x201, b"\x01\x02\x03\x04"),
                                                                 (0x202, b"\x05\x06")]
    assert all(g is not m for g, m in zip(got, msgs)) and b.recv(0.0) is None and a.recv(0.0) is None


def test_lockstep_bus_send_owned_and_filters(pair):
    a, b = pair
    msg = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
    a.send_owned(msg)
    assert b.recv(0) is msg
    b.set_filters([{"can_id": 0x700, "can_mask": 0x780, "extended": False}])
    a.send(can.Message(arbitration_id=0x181, data=b"", is_extended_id=False))
    a.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
    got = b.recv(0.5)                # BusABC.recv: skips the non-matching frame within the timeout
    assert got.arbitration_id == 0x701 and b.recv(0.0) is None


def test_lockstep_bus_send_many_owned_hands_over_in_order(pair):
    a, b = pair
    msgs = [can.Message(arbitration_id=0x181 + i, data=bytes([i] * 8), is_extended_id=False) for i in range(4)]
    a.send_many_owned(msgs)
    got = [b.recv(0.0) for _ in range(4)]
    assert all(g is m for g, m in zip(got, msgs))        # the same objects, not copies, in order
    assert len({m.timestamp for m in got}) == 1 and got[0].timestamp > 0 and got[0].channel == "t-lockstep"
    assert b.recv(0.0) is None and a.recv(0.0) is None  # not to the sender itself
    a.shutdown()
    with pytest.raises(can.CanOperationError):
        a.send_many_owned([can.Message(arbitration_id=0x80, data=b"")])


def test_lockstep_bus_blocking_recv_wakes_on_send(pair):
    a, b = pair
    out = []
    th = threading.Thread(target=lambda: out.append(b.recv(5.0)))
    th.start()
    a.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
    th.join(5.0)
    assert out and out[0] is not None and out[0].arbitration_id == 0x80
    assert b.recv(0.01) is None


def test_lockstep_bus_after_shutdown(pair):
    a, _ = pair
    a.shutdown()
    with pytest.raises(can.CanOperationError):
        a.send(can.Message(arbitration_id=0x80, data=b""))
    with pytest.raises(can.CanOperationError):
        a.send_many([can.Message(arbitration_id=0x80, data=b"")])


# --------------------------------------------------------------------------- virtual drives
def test_drive_outbox_holds_frames_in_order_until_release(cfg):
    sim_bus, tap = LockstepBus(channel="t-outbox"), LockstepBus(channel="t-outbox")
    try:
        vds = VirtualDriveSet(cfg.devices.can, sim_bus)
        while tap.recv(0.0) is not None:      # boot-ups
            pass
        vds.hold()
        for d in vds.drives.values():
            vds._tx(0x700 + d.node_id, b"\x05", d)
        assert tap.recv(0.0) is None
        vds.release()
        ids = []
        while (m := tap.recv(0.0)) is not None:
            ids.append(m.arbitration_id)
        assert ids == [0x700 + d.node_id for d in vds.drives.values()]
        vds._tx(0x701, b"\x05", None)                   # not held: sent at once
        assert tap.recv(0.0).arbitration_id == 0x701
    finally:
        sim_bus.shutdown()
        tap.shutdown()


# --------------------------------------------------------------------------- the simulated rig
# The runtime reaches SimulatedRig only through its transports (laser ptys, a python-can
# bus, Modbus TCP) and LockstepClock(advance=sim.advance). These tests play the runtime's
# side with the drive driver itself and raw pty reads. F/T sensors are left out: their
# lockstep answers are the virtual F/T server's own business (tests/test_ft300.py).
def _no_ft(cfg):
    return dataclasses.replace(cfg, devices=dataclasses.replace(
        cfg.devices, ft=dataclasses.replace(cfg.devices.ft, sensors=())))


class _Runtime:
    """The runtime's side of every wire, cycle by cycle on the lockstep clock: read every
    laser pty, poll and write the drives (the drive driver over ``sim.runtime_bus()``);
    a tap on the CAN wire records every frame. The drives are configured, enabled by the
    driver's blocking start-up and then disabled again: ``enable_at`` enables them at a
    cycle of their own, as the runtime does at its ARM."""

    def __init__(self, sim: SimulatedRig, cfg, enable_at: int):
        from drivers.canopen402 import DriveBus
        self.sim, self.h, self.enable_at = sim, cfg.controller.h, enable_at
        self.tap = sim.runtime_bus()
        self.db = DriveBus(cfg.devices.can, bus=sim.runtime_bus(), period_s=self.h)
        self.fds = {r: os.open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY) for r, p in sim.laser_ports.items()}
        self.clock = LockstepClock(advance=sim.advance)
        self.laser = {r: [] for r in self.fds}          # bytes read per cycle
        self.frames: list[list[tuple[int, bytes]]] = []  # CAN frames seen per cycle
        self.releases: list[float] = []
        self.db.configure()                     # no power until activate()

    def run(self, cycles: int) -> "_Runtime":
        k = 1
        while k <= cycles:
            t = self.clock.wait_until(k * self.h)
            self.releases.append(t)
            for r, fd in self.fds.items():
                self.laser[r].append(_read_all(fd))
            self.db.poll(t)
            if k == self.enable_at:
                self.db.activate(t)
            a = 0.4 * math.sin(2 * math.pi * 3.0 * t)
            self.db.write({"fl": a, "fr": -a, "rl": 0.5 * a, "rr": -0.5 * a}, t)
            got = []
            while (m := self.tap.recv(0.0)) is not None:
                got.append((m.arbitration_id, bytes(m.data)))
            self.frames.append(got)
            k = max(k + 1, math.floor(t / self.h + 1e-9) + 1)    # periods missed in a stall are skipped
        return self

    def close(self) -> None:
        for fd in self.fds.values():
            os.close(fd)
        self.db.close()


def _read_all(fd: int) -> bytes:
    out = b""
    while chunk := _read(fd):
        out += chunk
    return out


def _scenario(*faults, disturbances=()) -> Scenario:
    return Scenario(name="lockstep-test", duration_s=10.0, faults=tuple(faults), disturbances=tuple(disturbances))


def _run(cfg, scenario, seed, cycles, enable_at=10):
    sim = SimulatedRig(cfg, scenario, seed=seed, wires="kernel")   # the test reads the laser ptys itself
    rt = None
    try:
        rt = _Runtime(sim, cfg, enable_at).run(cycles)
        plant = (sim.plant.y_f, sim.plant.y_r, sim.plant.psi_af, sim.plant.psi_ar)
        return rt, sim.t_run0, plant, {w: sim.drives.state(w) for w in WHEELS}
    finally:
        if rt is not None:
            rt.close()
        sim.close()


def test_lockstep_is_deterministic_for_a_seed_on_every_wire(cfg):
    """Two runs with the same seed: byte for byte the same laser streams, frame for frame
    the same CAN traffic (both directions) in every cycle, the same plant state — through
    a disturbance and faults that draw random numbers (corrupt frames, lost CAN frames)."""
    c = _no_ft(cfg)
    sc = _scenario(FaultInjection(kind="corrupt", device="s_fl", t=0.05, duration_s=0.2, fraction=0.3),
                   FaultInjection(kind="bus_error", device="rl", t=0.1, duration_s=0.05, fraction=0.3),
                   disturbances=[Disturbance(kind="pulse", carrier="rear", t=0.02, duration_s=0.1, F_y=300.0)])
    n = 120
    a, b = _run(c, sc, 7, n), _run(c, sc, 7, n)
    assert a[0].laser == b[0].laser and a[0].frames == b[0].frames
    assert a[1:] == b[1:]
    assert all(len(v) == n for v in a[0].laser.values()) and len(a[0].frames) == n
    assert sum(len(x) for x in a[0].laser["b_f"]) > 0 and sum(len(f) for f in a[0].frames) > 5 * n
    assert not math.isnan(a[1]) and a[3] == {w: "OPERATION ENABLED" for w in WHEELS}   # the scenario ran
    other = _run(c, sc, 8, n)
    assert other[0].laser != a[0].laser             # the seed matters (sensor noise)


def test_scenario_time_starts_when_every_drive_is_enabled(cfg):
    """Not at start-up, not at the first SYNC: when the last drive reached OPERATION
    ENABLED. A laser dropout 20 ms into the scenario silences b_f from then on."""
    c = _no_ft(cfg)
    h = c.controller.h
    enable_at = 30
    rt, t_run0, _, states = _run(c, _scenario(FaultInjection(kind="dropout", device="b_f", t=0.02)), 0, 60, enable_at)
    assert states == {w: "OPERATION ENABLED" for w in WHEELS}
    # the driver walks the drives over a few cycles; the drives take each cycle's frames at its time
    assert enable_at * h <= t_run0 <= (enable_at + 6) * h, t_run0
    silent_from = round((t_run0 + 0.02) / h)        # the cycle whose release ends the last step with frames
    per_cycle = [len(x) for x in rt.laser["b_f"]]
    assert all(per_cycle[k] > 0 for k in range(silent_from - 1)), per_cycle
    assert all(x == 0 for x in per_cycle[silent_from + 1:]), per_cycle
    assert all(len(x) > 0 for x in rt.laser["b_r"])


def test_stall_releases_late_while_plant_and_drive_timers_run_on(cfg):
    """A ``stall`` fault: advance returns a release 100 ms late; the plant is integrated to
    it, the lasers streamed through it, and the drives' 50 ms watchdog (no SYNC/RPDO
    meanwhile) cut the current and sent its EMCY."""
    c = _no_ft(cfg)
    h = c.controller.h
    rt, t_run0, _, states = _run(c, _scenario(FaultInjection(kind="stall", t=0.03, duration_s=0.1)), 0, 70, 5)
    late = [(k, t) for k, t in enumerate(rt.releases) if t > (k + 1) * h + 1e-9]
    assert late, rt.releases
    k, t = late[0]
    assert t == pytest.approx((k + 1) * h + 0.1) and (k + 1) * h >= t_run0 + 0.03 - 1e-9
    assert len(rt.releases) == 70 - 20                         # the 20 periods of the stall were skipped
    assert len(rt.laser["b_f"][k]) >= 3 * round(0.1 * 1000)      # 100 ms of 1 kHz frames, 3 bytes each
    assert all(s == "FAULT" for s in states.values()), states
    emcy = [d for cid, d in rt.frames[k] if 0x80 < cid <= 0x80 + 127 and d[:2] == b"\x50\x82"]
    assert len(emcy) == 4                                       # EMCY 0x8250 (RPDO timeout) from each drive


@pytest.mark.parametrize("fault, key", [
    (FaultInjection(kind="dropout", device="b_x", t=1.0), "faults[1].device"),
    (FaultInjection(kind="stuck", device="ft_zz", t=1.0), "faults[1].device"),
    (FaultInjection(kind="no_heartbeat", device="s_fl", t=1.0), "faults[1].kind"),
])
def test_a_fault_on_a_device_the_rig_lacks_is_refused_when_built(cfg, fault, key):
    sc = _scenario(FaultInjection(kind="dropout", device="b_f", t=1.0), fault)
    with pytest.raises(ConfigError) as e:
        SimulatedRig(_no_ft(cfg), sc, seed=0)
    msg = str(e.value)
    assert "lockstep-test" in msg and key in msg and repr(fault.device if key.endswith("device") else fault.kind) in msg
