"""The lockstep fast paths of the simulator: ``LaserGroup`` writes exactly the bytes of
``VirtualLaser.emit_until`` and waits until the kernel delivered them; ``LockstepBus``
keeps python-can's bus contract; the virtual drives' outbox keeps frame order."""

from __future__ import annotations

import fcntl
import os
import struct
import termios
import threading

import can
import numpy as np
import pytest

from rig_runtime.config import LaserDevice
from sim_backend.lockstep_bus import LockstepBus
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
