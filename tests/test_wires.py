"""In-process wires (rig_runtime/wires.py) and the drivers on them: the pyserial ``mem://``
handler (drivers/protocol_mem.py) for the lasers, the in-process Modbus TCP stream for the
F/T sensors. What a pty or a socket would say, the wire says too: bytes in order, a full
buffer refuses, a hang-up is seen once the bytes are read, nothing listening is refused."""

from __future__ import annotations

import dataclasses
import math

import pytest
import serial

from drivers.ft_codec import Wrench
from drivers.ft_pollers import InlinePoller
from drivers.laser import LaserDriver
from drivers.ports import open_port
from rig_runtime import config, wires
from rig_runtime.config import LaserDevice
from rig_runtime.errors import DeviceInitError
from rig_runtime.hardware import Freshness
from sim_backend.virtual_ft import VirtualFTServer
from sim_backend.virtual_laser import VirtualLaser

H = 0.005


# --------------------------------------------------------------------------- the pipes
def test_a_pipe_carries_bytes_in_order_and_refuses_what_does_not_fit():
    p = wires.BytePipe(capacity=5)
    assert p.write(b"abc") == 3 and p.write(b"defg") == 2
    assert p.read(2) == b"ab" and p.read() == b"cde" and p.read() == b""
    p.close()
    assert p.write(b"x") == 0


def test_a_line_hangs_up_after_its_bytes_are_read():
    w = wires.serial_line(wires.unique_name("t"))
    try:
        end = wires.open_line(wires.SCHEME + w.name)
        w.a.write(b"xyz")
        wires.close_line(w)
        assert end.pending() == 3 and end.read() == b"xyz"
        with pytest.raises(ConnectionResetError):
            end.pending()
        with pytest.raises(FileNotFoundError):
            wires.open_line(wires.SCHEME + w.name)      # gone with its device end
    finally:
        wires.close_line(w)


def test_a_stream_answers_as_a_non_blocking_socket():
    ls = wires.listen(wires.unique_name("t"))
    try:
        client = wires.connect(ls.url)
        server = ls.accepted.popleft()
        with pytest.raises(BlockingIOError):
            client.recv(16)
        client.send(b"req")
        assert server.read() == b"req"
        server.write(b"reply")
        assert client.recv(3) == b"rep" and client.recv(16) == b"ly"
        server.close()
        assert client.recv(16) == b""                   # EOF: closed by the peer
        with pytest.raises(BrokenPipeError):
            client.send(b"more")
    finally:
        ls.close()
    with pytest.raises(ConnectionRefusedError):
        wires.connect(ls.url)


def test_wait_readable_returns_at_data_or_timeout():
    w = wires.Wire("t")
    assert w.b.wait_readable(0.01) is False
    w.a.write(b"x")
    assert w.b.wait_readable(0.01) is True


# --------------------------------------------------------------------------- lasers
def _cfg() -> LaserDevice:
    return LaserDevice(role="b_f", port="sim", measuring_range_mm=50.0, offset_mm=45.0, output_rate_hz=4000.0)


def test_pyserial_opens_a_memory_line_by_url():
    vl = VirtualLaser(_cfg(), wire="memory")
    try:
        port = open_port(vl.port_name, baudrate=921600, timeout=0)
        assert port.fd is None and port.in_waiting == 0
        port.close()
    finally:
        vl.close()
    with pytest.raises(serial.SerialException):
        open_port(vl.port_name)                         # the line is gone


def _readings(wire: str) -> list:
    vl = VirtualLaser(_cfg(), noise_std_m=2e-6, seed=3, wire=wire)
    drv = LaserDriver(_cfg(), port=vl.port_name)
    try:
        drv.configure()
        got = []
        for k in range(1, 6):
            vl.set_distance(0.06 + 1e-4 * k)
            vl.emit_until(k * H)
            r = drv.poll(k * H)
            got.append((r.value_m, r.n_values, r.raw_x, drv.last_values))
        return got
    finally:
        drv.close()
        vl.close()


def test_the_driver_reads_the_same_values_over_either_wire():
    """The same seed gives the same readings over a pty and over a memory line."""
    mem = _readings("memory")
    assert [n for _, n, _, _ in mem] == [20] * 5
    assert mem == _readings("pty")


def test_a_memory_line_hung_up_is_a_disconnected_device():
    """As over a pty (tests/test_laser.py::test_device_gone_is_invalid): the next poll says
    the device is gone, and every poll after."""
    vl = VirtualLaser(_cfg(), wire="memory")
    drv = LaserDriver(_cfg(), port=vl.port_name)
    drv.configure()
    try:
        vl.set_distance(0.06)
        vl.emit_until(H)
        assert drv.poll(H).health.fresh
        vl.close()
        r = drv.poll(2 * H)
        assert r.health.state is Freshness.INVALID
        assert "device disconnected (hang-up on the port)" in r.health.cause
        assert math.isnan(r.value_m) and drv.counters()["read_errors"] == 1
    finally:
        drv.close()


def test_a_missing_memory_line_cannot_be_opened():
    drv = LaserDriver(_cfg(), port="mem://no-such-line")
    with pytest.raises(DeviceInitError, match="mem://no-such-line"):
        drv.configure()


# --------------------------------------------------------------------------- F/T
def _ft_bus(names):
    ft = config.load().devices.ft
    return dataclasses.replace(ft, poller="inline", sensors=tuple(s for s in ft.sensors if s.name in names))


def test_the_inline_poller_over_memory_streams():
    """Open-time reads are answered at arrival; then only answer_pending answers, and the
    reply is collected at the next poll; a closed server is a lost connection."""
    names = ("ft_fl", "ft_rr")
    srv = VirtualFTServer(names, stream="memory").start()
    srv.set_wrench("ft_fl", Wrench(1.0, 2.0, 3.0, 0.1, 0.2, 0.3))
    poller = InlinePoller(_ft_bus(names), dict(srv.endpoints), reconnect_s=0.5)
    try:
        poller.start()                                  # blocking open: answered at arrival
        assert all(p.wrench is not None for p in poller.latest(-1.0))
        srv.answer_pending()                            # from now on only here
        srv.set_wrench("ft_fl", Wrench(5.0, 6.0, 7.0, 0.5, 0.6, 0.7))
        poller.latest(0.0)                              # sends the requests
        before = poller.latest(0.001)[0]
        assert before.wrench.fx == pytest.approx(1.0, abs=0.01)   # not answered yet
        assert srv.answer_pending() == 2
        after = poller.latest(0.002)[0]
        assert after.wrench.fx == pytest.approx(5.0, abs=0.01) and after.t == 0.002
        srv.close()
        poller.latest(0.2)                              # a new round: the send finds the wire hung up
        pubs = poller.latest(0.21)
        assert all(p.link_down for p in pubs), [p.cause for p in pubs]
    finally:
        poller.close()
        srv.close()
