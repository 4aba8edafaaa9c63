"""``rig_slcan``: the buffer-reading SLCAN client, against hand-made lines and against the
emulated adapter of ``rig sim`` (which python-can's own slcan client also drives)."""

import time

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.slcan_codec import encode_frame, parse_frame
from sim_backend.slcan import SlcanAdapter


def test_encode_by_hand():
    m = can.Message(arbitration_id=0x203, data=b"\x0f\x00\xfa\x00", is_extended_id=False)
    assert encode_frame(m) == b"t20340F00FA00\r"
    m = can.Message(arbitration_id=0x1ABCDEF0, data=b"\x01", is_extended_id=True)
    assert encode_frame(m) == b"T1ABCDEF0101\r"
    assert encode_frame(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)) == b"t0800\r"
    assert encode_frame(can.Message(arbitration_id=0x123, is_remote_frame=True, dlc=2,
                                    is_extended_id=False)) == b"r1232\r"


def test_decode_rejects_garbage():
    assert parse_frame(b"z") is None and parse_frame(b"") is None
    assert parse_frame(b"t20340F00FA") is None        # dlc 4 but 3 bytes
    assert parse_frame(b"tXYZ0") is None


@given(cid=st.integers(0, 0x7FF), data=st.binary(max_size=8), ext=st.booleans(), ext_id=st.integers(0, 0x1FFFFFFF))
def test_round_trip(cid, data, ext, ext_id):
    m = can.Message(arbitration_id=ext_id if ext else cid, data=data, is_extended_id=ext)
    back = parse_frame(encode_frame(m)[:-1])
    assert (back.arbitration_id, bytes(back.data), back.is_extended_id, back.dlc) == \
        (m.arbitration_id, bytes(m.data), ext, len(data))


def _recv_all(bus, n, timeout=2.0):
    out, end = [], time.monotonic() + timeout
    while len(out) < n and time.monotonic() < end:
        m = bus.recv(0.05)
        if m is not None:
            out.append(m)
    return out


@pytest.fixture
def host_and_peer():
    """``rig_slcan`` on the emulated adapter's pty, and a peer on the adapter's CAN side."""
    chan = f"slcan-test-{time.monotonic_ns()}"
    far = can.Bus(interface="virtual", channel=chan)
    peer = can.Bus(interface="virtual", channel=chan)
    adapter = SlcanAdapter(far)
    adapter.start()
    try:
        bus = can.Bus(interface="rig_slcan", channel=adapter.port_name, bitrate=1_000_000)
        try:
            yield bus, peer
        finally:
            bus.shutdown()
    finally:
        adapter.close()
        far.shutdown()
        peer.shutdown()


def test_against_the_emulated_adapter(host_and_peer):
    bus, peer = host_and_peer
    sent = [can.Message(arbitration_id=0x200 + i, data=bytes(range(i)), is_extended_id=False) for i in range(9)]
    sent.append(can.Message(arbitration_id=0x18FF00AA, data=b"\x01\x02", is_extended_id=True))
    for m in sent:
        bus.send(m)
    got = _recv_all(peer, len(sent))
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(m.arbitration_id, bytes(m.data)) for m in sent]
    for m in sent:
        peer.send(m)
    back = _recv_all(bus, len(sent))
    assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in back] == \
        [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in sent]
    assert bus.recv(0) is None                    # non-blocking when empty


def test_missing_port_is_an_init_error():
    with pytest.raises(can.CanInitializationError, match="/dev/nonexistent-slcan"):
        can.Bus(interface="rig_slcan", channel="/dev/nonexistent-slcan")


def _bare_bus(fd):
    """A SlcanBus reading from ``fd`` without the adapter handshake (parser tests)."""
    import collections

    from drivers.slcan_bus import SlcanBus
    bus = object.__new__(SlcanBus)
    bus._fd, bus._buf, bus._rx, bus.errors = fd, b"", collections.deque(), 0
    bus._inq = bytearray(4)
    return bus


@pytest.fixture
def raw_pty():
    """(master, slave) of a raw pty, the slave non-blocking as pyserial opens it."""
    import os
    import tty
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(slave, False)
    fds = [master, slave]
    yield fds
    for fd in fds:
        if fd >= 0:
            os.close(fd)


def test_an_empty_port_is_not_read(raw_pty, monkeypatch):
    """No read(2) while TIOCINQ says 0 (an empty tty's read waits for the kernel's
    flip-buffer worker), else one read of exactly the bytes it reported."""
    import os
    import select

    import drivers.slcan_bus as slcan_mod
    master, slave = raw_pty
    reads: list[int] = []
    real_read = slcan_mod._os_read

    def watched(fd, n):
        reads.append(n)
        return real_read(fd, n)

    monkeypatch.setattr(slcan_mod, "_os_read", watched)
    bus = _bare_bus(slave)
    assert bus._recv_internal(0) == (None, False) and reads == []
    os.write(master, b"t1810\r")
    assert select.select([slave], [], [], 5.0)[0]     # the kernel moved the bytes to the slave
    msg, _ = bus._recv_internal(0)
    assert reads == [6] and msg.arbitration_id == 0x181 and msg.dlc == 0
    assert bus._recv_internal(0) == (None, False) and reads == [6]


@pytest.mark.parametrize("pending", [b"", b"t1810\r"])
def test_hang_up_is_a_can_operation_error(raw_pty, pending):
    """The adapter end vanishes (pty master closed; a USB adapter unplugged hangs up the
    same way): recv names the hang-up, with or without unread bytes."""
    import os
    import select
    master, slave = raw_pty
    bus = _bare_bus(slave)
    if pending:
        os.write(master, pending)
        assert select.select([slave], [], [], 5.0)[0]
    os.close(master)
    raw_pty[0] = -1
    with pytest.raises(can.CanOperationError, match=r"disconnected \(hang-up on the port\)"):
        bus._recv_internal(0)
    with pytest.raises(can.CanOperationError, match="hang-up"):
        bus._recv_internal(0.01)                      # the waiting form too, without spinning


def test_drain_keeps_split_lines_and_skips_acks_and_garbage():
    import os
    r, w = os.pipe()
    os.set_blocking(r, False)
    bus = _bare_bus(r)
    try:
        os.write(w, b"z\rt18180102030405060708\rZ\rt1" + b"8")      # ack, frame, ack, half a frame
        bus._drain()
        assert [(m.arbitration_id, bytes(m.data)) for m in bus._rx] == [(0x181, bytes(range(1, 9)))]
        os.write(w, b"22AABB\r\atXYZ0\rt2021\r")    # rest of the frame, an error reply, garbage, bad length
        bus._drain()
        assert [(m.arbitration_id, bytes(m.data)) for m in bus._rx][1:] == [(0x182, b"\xaa\xbb")]
        assert bus.errors == 1 and bus._buf == b""
    finally:
        os.close(r)
        os.close(w)


def test_send_many_reaches_the_bus_in_order(host_and_peer):
    bus, peer = host_and_peer
    sent = [can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)] + [
        can.Message(arbitration_id=0x200 + i, data=bytes((i, 0, 0x10, 0)), is_extended_id=False)
        for i in range(1, 5)]
    bus.send_many(sent)
    got = _recv_all(peer, len(sent))
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(m.arbitration_id, bytes(m.data)) for m in sent]
