"""FT 300 codec, driver (every poller: process, thread, inline) and virtual sensors — over
real Modbus TCP/RTU on this machine, in real time. The inline poller on a lockstep clock:
``tests/test_ft_inline.py``."""

from __future__ import annotations

import asyncio
import math
import multiprocessing
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from multiprocessing import shared_memory

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.client import ModbusTcpClient
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from rig_runtime.hardware import Freshness
from drivers.ft300 import FTSensorSet
from drivers.ft_codec import AXES, REG_COUNT, REG_START, Wrench, registers_from_wrench, wrench_from_registers
from drivers.ft_modbus import decode_read_response, encode_read_request, frame_length
from drivers.ft_poll import Published
from drivers.ft_process import SLOT_SIZE, SlotReader, SlotWriter, _make_pub
from rig_runtime.config import FTBus, FTSensor
from rig_runtime.errors import ConfigError, DeviceInitError
from sim_backend.virtual_ft import VirtualFTServer

# The open (configure) makes three blocking reads per sensor, each answered by the server's
# thread within TIMEOUT_S; that thread's scheduling on a loaded machine is not what these
# tests check, so TIMEOUT_S is 0.25 s (the shipped 0.1 s lost opens to 0.1 s stalls) — still
# short enough for the tests of dropouts, staleness and bad frames to see many timeouts.
TIMEOUT_S = 0.25
# For the tests that count no timeout or one connect: TIMEOUT_S lets a reply the server's
# thread sends 0.1 s late (a loaded machine) count as a timeout and reconnect. The short
# one stays for the tests of dropouts and bad frames.
PATIENT = {"timeout_s": 1.0}
W_LEFT = Wrench(fx=-12.34, fy=0.5, fz=9.81, mx=-0.25, my=-0.5, mz=1.5)
# the same wrench, encoded by hand: -1234 -> 65536-1234 = 64302, -250 -> 65286, -500 -> 65036
REGS_LEFT = [64302, 50, 981, 65286, 65036, 1500]


POLLERS = ("process", "thread", "inline")


def bus(*names: str, poll_hz: float = 100.0, timeout_s: float = TIMEOUT_S, poller: str = "process",
        **kw) -> FTBus:
    sensors = kw.pop("sensors", None) or tuple(FTSensor(name=n) for n in names)
    return FTBus(poller=poller, poll_hz=poll_hz, timeout_s=timeout_s, sensors=sensors)


def wait_for(pred, timeout: float = 5.0, step: float = 0.005):
    """Poll ``pred()`` until it returns something truthy; fail after ``timeout``."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if (v := pred()):
            return v
        time.sleep(step)
    pytest.fail(f"condition not reached within {timeout} s")


def close_to(a: Wrench, b: Wrench, tol: float = 1e-9) -> bool:
    return all(abs(x - y) <= tol for x, y in zip(a.as_tuple(), b.as_tuple()))


def quiet_port() -> int:
    """A free TCP port outside the kernel's ephemeral range, for a server a test closes
    while the driver reconnects: a connect() to a closed ephemeral port can be given that
    same port as its source (a TCP self-connect, about 1 in 28 000 attempts), which "answers"
    the driver and keeps the port from the server reopened there."""
    with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
        lo, hi = map(int, f.read().split())
    outside = [p for p in range(10_000, 65_536) if not lo <= p <= hi]
    for port in random.sample(outside, min(200, len(outside))):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    pytest.fail(f"no free port outside the ephemeral range {lo}-{hi}")


@pytest.fixture
def server():
    srv = VirtualFTServer(["left", "right"]).start()
    srv.set_wrench("left", W_LEFT)
    srv.set_wrench("right", Wrench(fz=100.0))
    yield srv
    srv.close()


def _running(server, poller: str, **kw):
    d = FTSensorSet(bus("left", "right", poller=poller, **kw), server.endpoints)
    d.configure()               # each read answered within timeout_s (TIMEOUT_S: the stated tolerance)
    # inline: the reads at open have no time on the caller's clock (t = -inf until polled)
    wait_for(lambda: all(r.health.fresh and r.t > -math.inf for r in d.poll(time.monotonic()).values()))
    return d


@pytest.fixture(params=POLLERS)
def driver(server, request):
    """The driver polling in real time: in its own process (default), in threads, or inline
    (in the ``poll(time.monotonic())`` calls of the test; the server answers from its thread).
    Short timeout (TIMEOUT_S): for dropouts and bad frames."""
    d = _running(server, request.param)
    yield d
    d.close()


@pytest.fixture(params=POLLERS)
def patient_driver(server, request):
    """``driver`` with a 1 s timeout (PATIENT): for the tests that count
    no timeout, where a late reply of the server's thread must not count as one."""
    d = _running(server, request.param, **PATIENT)
    yield d
    d.close()


def ft_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("ft-poll")]


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:                                    # a zombie is dead too
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


# --------------------------------------------------------------------------- codec
def test_codec_hand_worked_values():
    assert registers_from_wrench(W_LEFT) == REGS_LEFT
    assert registers_from_wrench(Wrench(fx=-12.34))[0] == 64302
    assert registers_from_wrench(Wrench(mz=1.5))[5] == 1500
    assert wrench_from_registers(REGS_LEFT) == W_LEFT
    assert wrench_from_registers([0x8000, 0x7FFF, 0xFFFF, 0x8000, 0x7FFF, 0xFFFF]) == Wrench(
        fx=-327.68, fy=327.67, fz=-0.01, mx=-32.768, my=32.767, mz=-0.001)


def test_codec_saturates_and_rounds():
    regs = registers_from_wrench(Wrench(fx=1e6, fy=-1e6, fz=math.inf, mx=40.0, my=-math.inf, mz=0.0004))
    assert regs == [32767, 32768, 32767, 32767, 32768, 0]
    assert registers_from_wrench(Wrench(fx=327.674, mx=-32.7684))[0::3] == [32767, 32768]
    assert registers_from_wrench(Wrench(fx=0.016))[0] == 2
    with pytest.raises(ValueError):
        registers_from_wrench(Wrench(fz=math.nan))


def test_codec_rejects_bad_register_blocks():
    with pytest.raises(ValueError, match="6 registers"):
        wrench_from_registers([0] * 5)
    with pytest.raises(ValueError, match="65536"):
        wrench_from_registers([0, 0, 0, 0, 0, 65536])


forces = st.floats(-327.68, 327.67)
moments = st.floats(-32.768, 32.767)


@settings(max_examples=300, deadline=None)
@given(st.tuples(forces, forces, forces, moments, moments, moments))
def test_codec_round_trip_within_half_a_count(values):
    w = Wrench(*values)
    back = wrench_from_registers(registers_from_wrench(w))
    for x, y, lsb in zip(w.as_tuple(), back.as_tuple(), (0.01,) * 3 + (0.001,) * 3):
        assert abs(x - y) <= lsb / 2 + 1e-12


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(0, 0xFFFF), min_size=6, max_size=6))
def test_codec_registers_survive_decode_encode(regs):
    assert registers_from_wrench(wrench_from_registers(regs)) == regs


def test_codec_flags_registers_at_the_int16_limits_as_saturated():
    # worked by hand: 32767 counts = +327.67 N / +32.767 N·m, 0x8000 = -32768 counts =
    # -327.68 N / -32.768 N·m; one count inside (32766, 0x8001 = -32767) is a measurement
    assert wrench_from_registers([0, 0, 32767, 0, 0, 0]).saturation == "Fz saturated at +327.67 N (int16 limit)"
    assert wrench_from_registers([0x8000, 0, 0, 0, 0, 0]).saturation == "Fx saturated at -327.68 N (int16 limit)"
    assert wrench_from_registers([0, 0, 0, 0, 0x7FFF, 0]).saturation == "My saturated at +32.767 N·m (int16 limit)"
    w = wrench_from_registers([0, 0x8000, 32767, 0x8000, 0, 0])
    assert (w.fy, w.fz, w.mx) == (-327.68, 327.67, -32.768)     # the value is still decoded …
    assert w.saturation == ("Fy saturated at -327.68 N, Fz saturated at +327.67 N, "
                            "Mx saturated at -32.768 N·m (int16 limit)")   # … and flagged
    assert wrench_from_registers([32766, 0x8001, 32766, 0x8001, 32766, 0x8001]).saturation == ""
    assert wrench_from_registers(REGS_LEFT).saturation == ""
    # what the simulated sensor encodes at or beyond the range is flagged once decoded
    assert wrench_from_registers(registers_from_wrench(Wrench(fz=480.0))).saturation.startswith("Fz saturated at +327.67 N")


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(0, 0xFFFF), min_size=6, max_size=6))
def test_codec_saturation_names_exactly_the_axes_at_a_limit(regs):
    text = wrench_from_registers(regs).saturation
    at_limit = [a for a, r in zip(AXES, regs) if r in (0x7FFF, 0x8000)]
    assert bool(text) == bool(at_limit)
    assert [a for a in AXES if f"{a} saturated" in text] == at_limit


@settings(max_examples=300, deadline=None)
@given(st.tuples(forces, forces, forces, moments, moments, moments))
def test_codec_values_inside_the_range_are_not_saturated(values):
    w = Wrench(*values)
    regs = registers_from_wrench(w)
    assert (wrench_from_registers(regs).saturation == "") == all(r not in (0x7FFF, 0x8000) for r in regs)
    inner = Wrench(*(max(-327.66, min(327.66, v)) for v in values[:3]),
                   *(max(-32.766, min(32.766, v)) for v in values[3:]))
    assert inner.saturation == "" and wrench_from_registers(registers_from_wrench(inner)).saturation == ""


# --------------------------------------------------------------------------- driver <-> virtual sensors
def test_values_arrive_fresh(server, patient_driver):
    driver = patient_driver

    def all_fresh():
        p = driver.poll(time.monotonic())
        return all(x.health.fresh for x in p.values()) and p

    r = wait_for(all_fresh)
    assert r["left"].wrench == W_LEFT
    assert r["right"].wrench == Wrench(fz=100.0)
    for reading in r.values():
        assert reading.health.state is Freshness.FRESH and reading.health.cause == ""
        assert math.isfinite(reading.t) and reading.t <= time.monotonic()
    server.set_wrench("left", Wrench(fy=-1.0))
    wait_for(lambda: driver.poll(time.monotonic())["left"].wrench == Wrench(fy=-1.0))


def test_dropout_counts_timeouts_keeps_t_and_recovers(server, driver):
    """A silent sensor: timeouts counted, the last sample kept with its time (its age is the
    supervisor's to judge), the state FRESH (the sensor said nothing against it)."""
    server.inject("left", "dropout")
    r = wait_for(lambda: (x := driver.poll(time.monotonic())["left"]).health.timeouts >= 1 and x)
    assert r.wrench == W_LEFT                      # last valid sample kept, with its time
    assert r.health.state is Freshness.FRESH and "timeout" in r.health.cause
    assert r.health.errors == 0 and r.health.bad_frames == 0
    later = wait_for(lambda: (x := driver.poll(time.monotonic())["left"]).health.timeouts >= 3 and x)
    assert later.t == r.t                          # keeps counting; no new sample, the same time
    assert later.health.state is Freshness.FRESH and "timeout" in later.health.cause
    assert driver.poll(time.monotonic())["right"].health.cause == ""       # unaffected
    server.clear("left", "dropout")
    wait_for(lambda: (x := driver.poll(time.monotonic())["left"]).t > r.t and x.health.cause == "")


def _value(h):
    return (h.state, h.cause, h.bad_frames, h.timeouts, h.errors)


def test_health_is_one_value_until_something_changes(server, driver):
    """A new health is built when state, cause or a count changes, else the same object
    is handed out again — through samples, an exception, a dropout's timeouts, recovery."""
    wait_for(lambda: driver.poll(time.monotonic())["left"].health.fresh)
    healths = []

    def sample(n: int) -> None:
        for _ in range(n):
            healths.append(driver.poll(time.monotonic())["left"].health)
            time.sleep(0.001)

    def sample_until(state: Freshness, timeout: float = 3.0) -> None:
        end = time.monotonic() + timeout
        while not healths or healths[-1].state is not state:
            assert time.monotonic() < end, f"{state} not sampled within {timeout} s"
            sample(1)

    sample(50)
    server.inject("left", "out_of_range", code=4)
    sample_until(Freshness.INVALID)                # the next reply, however late it comes
    sample(50)
    server.clear("left")
    server.inject("left", "dropout")
    wait_for(lambda: driver.poll(time.monotonic())["left"].health.timeouts >= 2)
    sample(50)
    server.clear("left")
    wait_for(lambda: driver.poll(time.monotonic())["left"].health.cause == "")
    sample(50)
    same = [a is b for a, b in zip(healths, healths[1:])]
    assert all((a is b) == (_value(a) == _value(b)) for a, b in zip(healths, healths[1:]))
    assert any(same) and not all(same)
    assert {h.state for h in healths} == {Freshness.FRESH, Freshness.INVALID}
    assert any("timeout" in h.cause for h in healths)


def test_exception_response_is_invalid_with_code(server, patient_driver):
    driver = patient_driver
    server.inject("right", "out_of_range", code=4)
    h = wait_for(lambda: (x := driver.poll(time.monotonic())["right"].health).state is Freshness.INVALID and x)
    assert "exception 4" in h.cause and "device failure" in h.cause
    assert h.errors >= 1 and h.timeouts == 0
    server.inject("right", "out_of_range", code=2)
    wait_for(lambda: "exception 2 (illegal data address)" in driver.poll(time.monotonic())["right"].health.cause)
    server.clear("right")
    wait_for(lambda: driver.poll(time.monotonic())["right"].health.fresh)


def test_saturated_sample_is_invalid_with_axis_and_value_and_recovers(server, patient_driver):
    driver = patient_driver
    server.set_wrench("right", Wrench(fz=480.0, fy=3.0))       # beyond the range: pinned at +32767
    r = wait_for(lambda: (x := driver.poll(time.monotonic())["right"]).health.state is Freshness.INVALID and x)
    assert r.health.cause == "Fz saturated at +327.67 N (int16 limit)"
    assert r.wrench == Wrench(fz=327.67, fy=3.0)                # passed on, flagged
    assert r.health.errors >= 1 and r.health.timeouts == r.health.bad_frames == 0
    n = driver.counters()["right.samples"]
    wait_for(lambda: driver.poll(time.monotonic())["right"].health.errors >= r.health.errors + 2)
    assert driver.counters()["right.samples"] == n            # counted in errors, not in samples
    assert driver.poll(time.monotonic())["left"].health.fresh
    server.set_wrench("right", Wrench(fz=-2.0))
    h = wait_for(lambda: (x := driver.poll(time.monotonic())["right"].health).fresh and x)
    assert h.cause == "" and driver.poll(time.monotonic())["right"].wrench == Wrench(fz=-2.0)


@pytest.mark.parametrize("mode", ["garble", "truncate"])
def test_garbled_frames_are_counted_as_bad_frames(server, driver, mode):
    server.inject("left", "corrupt", mode=mode)
    r = wait_for(lambda: (x := driver.poll(time.monotonic())["left"]).health.bad_frames >= 2 and x)
    assert r.health.errors == 0
    # counted and noted; the state stays FRESH (corruption is the supervisor's to judge) and
    # no sample arrives while every reply is garbled
    assert r.health.state is Freshness.FRESH and ("garbled" in r.health.cause or "truncated" in r.health.cause)
    later = wait_for(lambda: (x := driver.poll(time.monotonic())["left"]).health.bad_frames >= 4 and x)
    assert later.t == r.t and later.health.state is Freshness.FRESH
    server.clear("left", "corrupt")
    wait_for(lambda: (x := driver.poll(time.monotonic())["left"]).t > r.t and x.health.cause == "")


def test_stuck_and_offset_faults_change_what_arrives(server, patient_driver):
    driver = patient_driver
    server.inject("left", "stuck")
    server.set_wrench("left", Wrench())
    n = server.served("left")
    # answered several reads since the change (inline: polled by the driver's poll() calls)
    wait_for(lambda: driver.poll(time.monotonic()) and server.served("left") >= n + 3)
    r = driver.poll(time.monotonic())["left"]
    assert r.wrench == W_LEFT and r.health.fresh
    server.clear("left", "stuck")
    server.inject("left", "offset", fz=2.5, mz=-0.1)
    wait_for(lambda: close_to(driver.poll(time.monotonic())["left"].wrench, Wrench(fz=2.5, mz=-0.1)))


@pytest.mark.parametrize("poller", POLLERS)
def test_poll_never_waits_while_the_device_hangs(server, poller):
    """poll() hands over what was published and returns: it never waits for a reply. Both
    sensors' requests hang (dropout) with a 5 s timeout; a poll that waited for a reply would
    return only when the request timed out, counted in ``health.timeouts``. 2500 polls return
    (normally within ~50 ms) each with the last published sample, and afterwards no request
    has timed out yet: none of them waited. What a poll costs is a measurement
    (benchmarks/ft_inline_cost.py, docs/performance.md), not this test's assertion."""
    cfg = bus("left", "right", timeout_s=5.0, poller=poller)
    with FTSensorSet(cfg, server.endpoints) as d:
        n0 = {n: server.served(n) for n in ("left", "right")}
        server.inject("left", "dropout")
        server.inject("right", "dropout")
        # a request of each sensor read after the injection: swallowed, it hangs (inline: the
        # requests go out in poll())
        wait_for(lambda: d.poll(time.monotonic()) and all(server.served(n) > n0[n] for n in n0))
        before = {n: d.poll(time.monotonic())[n].health.timeouts for n in ("left", "right")}
        polls = [d.poll(time.monotonic()) for _ in range(2500)]
        after = d.poll(time.monotonic())
        assert {n: after[n].health.timeouts for n in ("left", "right")} == before   # still hanging
        published = {"left": W_LEFT, "right": Wrench(fz=100.0)}     # the only values ever served
        assert all(p[n].wrench == w for p in polls for n, w in published.items())
        wait_for(lambda: d.poll(time.monotonic())["left"].health.timeouts > before["left"], timeout=15.0)
        server.close()          # EOF ends the next hanging request: close() need not wait 5 s for it


@pytest.mark.parametrize("poller", POLLERS)
def test_refused_connection_at_open_names_the_endpoint(poller):
    with socket.socket() as holder:
        # bound, never listening: a connect is refused, and the port is never given to a
        # connect() as its source (no self-connect, nobody else binds it meanwhile)
        holder.bind(("127.0.0.1", 0))
        port = holder.getsockname()[1]
        d = FTSensorSet(bus("left", poller=poller), {"left": ("127.0.0.1", port)})
        with pytest.raises(DeviceInitError, match=rf"ft left \(127\.0\.0\.1:{port}\)") as ei:
            d.configure()
    assert isinstance(ei.value.__cause__, ConnectionRefusedError)
    assert not d.is_configured
    assert not multiprocessing.active_children() and not ft_threads()
    d.close()


@pytest.mark.parametrize("poller", POLLERS)
def test_silent_device_at_open_is_an_init_error(server, poller):
    server.inject("right", "dropout")
    d = FTSensorSet(bus("left", "right", poller=poller), server.endpoints)
    with pytest.raises(DeviceInitError, match=r"ft right .*not reachable after 3 requests.*timeout"):
        d.configure()
    assert not ft_threads()
    assert not multiprocessing.active_children()


@pytest.mark.parametrize("poller", POLLERS)
def test_close_is_idempotent_and_stops_the_poller(server, poller):
    d = FTSensorSet(bus("left", "right", poller=poller, timeout_s=1.0), server.endpoints)
    d.configure()
    if poller == "thread":
        assert ft_threads() and not multiprocessing.active_children()
    elif poller == "process":
        assert not ft_threads()                   # no Modbus work in this process
        pid = d.poller.process.pid
        assert pid_alive(pid) and d.poller.process.name == "ft-poll"
    else:
        assert not ft_threads() and not multiprocessing.active_children()    # no helper at all
    d.close()
    d.close()
    assert not ft_threads()
    assert not multiprocessing.active_children()
    if poller == "process":
        assert not pid_alive(pid) and d.poller.process is None
    assert set(d.poll(time.monotonic())) == {"left", "right"}   # still answers, never raises
    assert d.poll(time.monotonic())["left"].wrench == W_LEFT    # the last published sample


@pytest.mark.parametrize("poller", POLLERS)
def test_connection_loss_is_reported_and_reconnected(poller):
    srv = VirtualFTServer(["left"], ports={"left": quiet_port()}).start()
    srv.set_wrench("left", W_LEFT)
    endpoint = srv.endpoints["left"]
    # a 1 s timeout: a late reply must not time out and reconnect (disconnects are counted);
    # the loss itself shows at once (EOF, then refused connects)
    with FTSensorSet(bus("left", poller=poller, timeout_s=1.0), srv.endpoints, reconnect_s=0.02) as d:
        wait_for(lambda: driver_health(d).fresh)
        srv.close()
        h = wait_for(lambda: "cannot connect" in (x := driver_health(d)).cause and x)
        assert h.state is Freshness.INVALID and "refused" in h.cause       # the link said so
        c = d.counters()
        assert c["left.disconnects"] == 1 and c["left.connect_failures"] >= 1
        srv2 = VirtualFTServer(["left"], ports={"left": endpoint[1]}).start()
        try:
            srv2.set_wrench("left", Wrench(fx=3.0))
            wait_for(lambda: d.poll(time.monotonic())["left"].wrench == Wrench(fx=3.0))
            wait_for(lambda: driver_health(d).fresh)
        finally:
            srv2.close()


def driver_health(d: FTSensorSet):
    return d.poll(time.monotonic())["left"].health


def test_config_errors_are_caught_before_connecting():
    with pytest.raises(ConfigError, match="distinct sensor names"):
        FTSensorSet(bus(sensors=(FTSensor(name="a"), FTSensor(name="a", port=1))))
    with pytest.raises(ConfigError, match="serial port"):
        FTSensorSet(bus(sensors=(FTSensor(name="a", transport="rtu"),)))
    with pytest.raises(ConfigError, match="unit id"):
        FTSensorSet(bus(sensors=(FTSensor(name="a"), FTSensor(name="b"))))   # same host:port, both unit 9


def test_virtual_server_rejects_unknown_faults(server):
    with pytest.raises(ValueError, match="unknown fault"):
        server.inject("left", "smoke")
    with pytest.raises(TypeError):
        server.inject("left", "dropout", seconds=1)
    with pytest.raises(ValueError):
        server.inject("left", "out_of_range", code=9)
    with pytest.raises(KeyError):
        server.set_wrench("middle", Wrench())


def test_virtual_server_close_frees_ports_and_threads():
    srv = VirtualFTServer(["a", "b"], ports={"a": quiet_port(), "b": quiet_port()}).start()
    endpoints = dict(srv.endpoints)
    srv.close()
    srv.close()
    assert not srv.running
    assert not [t for t in threading.enumerate() if t.name.startswith("virtual-ft")]
    for host, port in endpoints.values():
        with pytest.raises(ConnectionRefusedError):
            socket.create_connection((host, port), timeout=1).close()


# --------------------------------------------------------------------------- the poll process
def test_process_poller_delivers_new_values_within_a_few_periods(server):
    cfg = bus("left", "right", poll_hz=100.0, **PATIENT)
    with FTSensorSet(cfg, server.endpoints) as d:
        r = d.poll(time.monotonic())
        assert r["left"].wrench == W_LEFT and r["left"].health.fresh     # read once by open()
        delays = []
        for k in range(1, 6):
            w = Wrench(fx=float(k), mz=-0.001 * k)
            server.set_wrench("left", w)
            t0 = time.monotonic()
            got = wait_for(lambda w=w: (x := d.poll(time.monotonic())["left"]).wrench == w and x, timeout=5.0)
            delays.append(time.monotonic() - t0)
            assert got.t >= t0 - 0.011 and got.health.fresh and d.counters()["left.samples"] >= 2
        # 100 Hz polling: normally within 1-2 periods (10-20 ms); the median of five leaves
        # room for two stalls of a loaded machine, a poller at a few Hz fails it
        assert sorted(delays)[2] < 0.1, [f"{x * 1e3:.0f} ms" for x in delays]


def test_process_poller_reports_the_counters_and_causes_of_the_child(server):
    with FTSensorSet(bus("left", "right", **PATIENT), server.endpoints, ) as d:
        server.inject("right", "out_of_range", code=6)
        h = wait_for(lambda: (x := d.poll(time.monotonic())["right"].health).state is Freshness.INVALID and x)
        assert h.cause == "Modbus exception 6 (server device busy)" and h.errors >= 1
        c = d.counters()
        assert c["right.connects"] == 1 and c["right.samples"] >= 1
        server.clear("right")
        server.inject("left", "corrupt")
        h = wait_for(lambda: (x := d.poll(time.monotonic())["left"].health).bad_frames >= 2 and x)
        assert "garbled response: byte count 255" in h.cause and h.errors == 0
        assert h.state is Freshness.FRESH               # counted and noted, judged by the supervisor


def test_killing_the_server_makes_the_process_poller_invalid_with_a_cause():
    srv = VirtualFTServer(["left"], ports={"left": quiet_port()}).start()
    srv.set_wrench("left", W_LEFT)
    with FTSensorSet(bus("left", timeout_s=1.0), srv.endpoints, reconnect_s=0.05, ) as d:
        wait_for(lambda: d.poll(time.monotonic())["left"].health.fresh)
        srv.close()
        r = wait_for(lambda: (x := d.poll(time.monotonic())["left"]).health.state is not Freshness.FRESH and x)
        assert r.health.state is Freshness.INVALID and r.wrench == W_LEFT       # the link is down
        assert "cannot connect" in r.health.cause or "connection lost" in r.health.cause
        assert d.poller.process.is_alive()           # the poller itself keeps trying


def test_a_dead_poll_process_shows_as_invalid_with_its_exit(server):
    with FTSensorSet(bus("left", "right", timeout_s=1.0), server.endpoints, ) as d:
        proc = d.poller.process
        os.kill(proc.pid, signal.SIGKILL)
        h = wait_for(lambda: (x := d.poll(time.monotonic())["left"].health).state is Freshness.INVALID and x)
        assert "poll process exited with code -9" in h.cause
    assert not multiprocessing.active_children()


def test_poll_process_runs_sched_other_even_when_started_from_a_fifo_thread(server):
    out: dict = {}

    def opener() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except (OSError, AttributeError) as exc:
            out["skip"] = repr(exc)
            return
        d = FTSensorSet(bus("left", timeout_s=1.0), {"left": server.endpoints["left"]})
        d.configure()
        out["d"] = d

    t = threading.Thread(target=opener)
    t.start()
    t.join(30)
    if "skip" in out:
        pytest.skip(f"cannot run SCHED_FIFO here: {out['skip']}")
    d = out["d"]
    try:
        assert os.sched_getscheduler(d.poller.process.pid) == os.SCHED_OTHER
    finally:
        d.close()


_ORPHAN_SCRIPT = """
import sys, time
sys.path.insert(0, {root!r})
from rig_runtime.config import FTBus, FTSensor
from drivers.ft300 import FTSensorSet
if __name__ == "__main__":
    d = FTSensorSet(FTBus(poll_hz=50.0, timeout_s=1.0, sensors=(FTSensor(name="left"),)),
                    {{"left": ("127.0.0.1", {port})}})
    d.configure()
    print(d.poller.process.pid, flush=True)
    time.sleep(60)
"""


def test_poll_process_dies_with_its_parent(server, tmp_path):
    script = tmp_path / "parent.py"
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    script.write_text(_ORPHAN_SCRIPT.format(root=root, port=server.endpoints["left"][1]))
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        child = int(parent.stdout.readline())
        assert pid_alive(child)
        parent.kill()                             # no close(), no atexit: only the pipe EOF tells
        parent.wait(5)
        wait_for(lambda: not pid_alive(child), timeout=5.0)
    finally:
        parent.kill()
        parent.wait(5)


# --------------------------------------------------------------------------- shared-memory seqlock
def _pub(v: float, cause: str = "", n: int = 0) -> Published:
    return Published(Wrench(v, v, v, v, v, v), v, cause, None, n, n, n,
                      (("samples", n), ("connects", 1), ("connect_failures", 0), ("disconnects", 0)))


class _Holder:
    def __init__(self) -> None:
        self.pub = None


def _make(w6, *rest):
    return Published(None if w6 is None else Wrench(*w6), *rest)


def test_seqlock_slot_round_trip_and_rejected_copies():
    shm = shared_memory.SharedMemory(create=True, size=2 * SLOT_SIZE)
    try:
        shm.buf[:] = bytes(2 * SLOT_SIZE)
        holders = (_Holder(), _Holder())
        reader, writer = SlotReader(shm.buf, holders, _make), SlotWriter(shm.buf)
        reader.refresh()
        assert holders[0].pub is None                     # nothing published yet
        p = Published(W_LEFT, 12.5, "ünïcode " + "x" * 400, 4, 1, 2, 3,
                       (("samples", 7), ("connects", 2), ("connect_failures", 1), ("disconnects", 1)),
                       link_down=True)
        writer.write(1, p)
        reader.refresh()
        got = holders[1].pub
        assert got.wrench == W_LEFT and got.t == 12.5 and got.exc_code == 4 and got.link_down is True
        assert (got.timeouts, got.errors, got.bad_frames) == (1, 2, 3) and got.counters == p.counters
        assert got.cause == p.cause.encode()[:240].decode("utf-8", "ignore")
        assert holders[0].pub is None
        # a writer caught mid-write (odd sequence) and a payload that does not match its CRC
        # are both rejected; the previous state stays
        writer.write(1, _pub(1.0))
        shm.buf[SLOT_SIZE] |= 1
        reader.refresh()
        assert holders[1].pub is got and reader.rejected == 1
        shm.buf[SLOT_SIZE] &= 0xFE
        shm.buf[SLOT_SIZE + 40] ^= 0xFF
        reader.refresh()
        assert holders[1].pub is got and reader.rejected == 2
        shm.buf[SLOT_SIZE + 40] ^= 0xFF
        reader.refresh()
        assert holders[1].pub.wrench == Wrench(1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
        assert holders[1].pub.link_down is False
    finally:
        shm.close()
        shm.unlink()


def _hammer(name: str, seconds: float) -> None:
    """Writer process for the torn-read test: every slot write has six equal components."""
    shm = shared_memory.SharedMemory(name=name)
    w = SlotWriter(shm.buf)
    end = time.monotonic() + seconds
    k = 0
    while time.monotonic() < end:
        k += 1
        w.write(0, _pub(float(k), cause="c" * (k % 200), n=k))
    shm.close()


def test_seqlock_reader_never_sees_a_torn_sample_from_another_process():
    shm = shared_memory.SharedMemory(create=True, size=SLOT_SIZE)
    try:
        shm.buf[:] = bytes(SLOT_SIZE)
        proc = multiprocessing.get_context("spawn").Process(target=_hammer, args=(shm.name, 1.0))
        proc.start()
        h = _Holder()
        reader = SlotReader(shm.buf, (h,), _make)
        seen = set()
        while proc.is_alive() or h.pub is None:
            reader.refresh()
            p = h.pub
            if p is not None and p.t not in seen:
                seen.add(p.t)
                k = int(p.t)
                assert p.wrench.as_tuple() == (p.t,) * 6
                assert p.cause == "c" * (k % 200) and p.timeouts == k and p.counters[0] == ("samples", k)
        proc.join(5)
        assert len(seen) > 10
    finally:
        shm.close()
        shm.unlink()


# --------------------------------------------------------------------------- RTU on a pty
@pytest.mark.parametrize("poller", ["process", "thread"])
def test_rtu_over_pty_reads_values_and_counts_crc_errors(poller):
    with VirtualFTServer(["r"], rtu=["r"]) as srv:
        srv.set_wrench("r", W_LEFT)
        cfg = bus(sensors=(FTSensor(name="r", transport="rtu", serial_port=srv.serial_ports["r"]),),
                  poller=poller, poll_hz=20.0, **PATIENT)
        with FTSensorSet(cfg) as d:
            assert d.poll(time.monotonic())["r"].wrench == W_LEFT
            srv.inject("r", "corrupt")              # RTU: CRC inverted
            # pymodbus reads on after a bad CRC until the timeout: one bad frame per timeout_s
            h = wait_for(lambda: (x := d.poll(time.monotonic())["r"].health).bad_frames >= 2 and x,
                         timeout=10.0)
            assert h.timeouts == 0 and h.errors == 0
            srv.clear("r")
            srv.set_wrench("r", Wrench(fy=2.0))
            wait_for(lambda: (x := d.poll(time.monotonic())["r"]).health.fresh and x.wrench == Wrench(fy=2.0),
                     timeout=10.0)


# --------------------------------------------------------------------------- independent peers
class _PlainPymodbusServer:
    """pymodbus's own TCP server with a plain datastore: INT16 values encoded by pymodbus."""

    def __init__(self, signed_counts: list[int], unit_id: int = 9) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.port = asyncio.run_coroutine_threadsafe(self._start(signed_counts, unit_id), self.loop).result(5)

    async def _start(self, counts: list[int], unit_id: int) -> int:
        device = SimDevice(id=unit_id, simdata=[SimData(REG_START, values=counts, datatype=DataType.INT16)])
        self.server = ModbusTcpServer(device, address=("127.0.0.1", 0))
        await self.server.serve_forever(background=True)
        return self.server.transport.sockets[0].getsockname()[1]

    def close(self) -> None:
        asyncio.run_coroutine_threadsafe(self.server.shutdown(), self.loop).result(5)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()


@pytest.mark.parametrize("poller", POLLERS)
def test_driver_reads_a_plain_pymodbus_server(poller):
    peer = _PlainPymodbusServer([-1234, 50, 981, -250, -500, 1500])
    try:
        d = FTSensorSet(bus("left", poller=poller, **PATIENT), {"left": ("127.0.0.1", peer.port)})
        d.configure()
        try:
            assert d.poll(time.monotonic())["left"].wrench == W_LEFT
            h = wait_for(lambda: (x := d.poll(time.monotonic())["left"].health) and d.counters().get("left.samples", 0) >= 3 and x)
            assert h.fresh and h.bad_frames == h.timeouts == h.errors == 0
        finally:
            d.close()
    finally:
        peer.close()


@pytest.mark.parametrize("poller", POLLERS)
def test_a_register_pinned_at_the_int16_limit_of_a_pymodbus_server_is_invalid(poller):
    """pymodbus's own server and datastore, INT16 values encoded by pymodbus: Fz pinned at
    +32767 and Mx at -32768, as a real sensor at its limit answers."""
    peer = _PlainPymodbusServer([-1234, 50, 32767, -32768, -500, 1500])
    try:
        d = FTSensorSet(bus("left", poller=poller, **PATIENT), {"left": ("127.0.0.1", peer.port)})
        d.configure()                       # a saturated sensor answers: the open succeeds
        try:
            r = wait_for(lambda: (x := d.poll(time.monotonic())["left"]).health.errors >= 2 and x)
            assert r.health.state is Freshness.INVALID
            assert r.health.cause == "Fz saturated at +327.67 N, Mx saturated at -32.768 N·m (int16 limit)"
            assert r.health.timeouts == r.health.bad_frames == 0
            assert r.wrench == Wrench(fx=-12.34, fy=0.5, fz=327.67, mx=-32.768, my=-0.5, mz=1.5)
            assert d.counters()["left.samples"] == 0
        finally:
            d.close()
    finally:
        peer.close()


def test_plain_pymodbus_client_reads_the_virtual_server(server):
    host, port = server.endpoints["left"]
    client = ModbusTcpClient(host, port=port, timeout=1)
    assert client.connect()
    try:
        rr = client.read_holding_registers(180, count=6, device_id=9)
        assert not rr.isError()
        assert rr.registers == REGS_LEFT
        signed = client.convert_from_registers(rr.registers, client.DATATYPE.INT16)
        assert signed == [-1234, 50, 981, -250, -500, 1500]
        assert client.read_holding_registers(REG_START, count=REG_COUNT, device_id=9).registers == REGS_LEFT
        assert client.read_holding_registers(182, count=2, device_id=9).registers == REGS_LEFT[2:4]
        # what the server refuses, pymodbus reads as the exception response it is
        assert client.read_holding_registers(100, count=6, device_id=9).exception_code == 2
        assert client.write_register(180, 1, device_id=9).exception_code == 2
        assert client.read_holding_registers(180, count=6, device_id=3).exception_code == 11
        server.inject("left", "out_of_range", code=4)
        rr = client.read_holding_registers(180, count=6, device_id=9)
        assert rr.isError() and rr.exception_code == 4
        server.clear("left")
        assert client.read_holding_registers(180, count=6, device_id=9).registers == REGS_LEFT
    finally:
        client.close()


@pytest.mark.parametrize("poller", POLLERS)
def test_wrong_unit_id_is_an_init_error_like_behind_a_gateway(server, poller):
    cfg = bus(sensors=(FTSensor(name="left", unit_id=5),), poller=poller, **PATIENT)
    d = FTSensorSet(cfg, {"left": server.endpoints["left"]})
    with pytest.raises(DeviceInitError, match=r"ft left .*unit 5 not reachable.*exception 11"):
        d.configure()
    assert not d.is_configured and not multiprocessing.active_children()


def test_modbus_tcp_codec_checks_what_it_decodes():
    req = encode_read_request(0x1234, 9, 180, 6)
    assert req == bytes.fromhex("1234 0000 0006 09 03 00b4 0006")
    reply = bytes.fromhex("1234 0000 000f 09 03 0c") + b"".join(r.to_bytes(2, "big") for r in REGS_LEFT)
    assert frame_length(reply[:5]) is None and frame_length(reply) == len(reply) == 21
    assert decode_read_response(reply, 0x1234, 9, 6) == (tuple(REGS_LEFT), None)
    assert decode_read_response(bytes.fromhex("1234 0000 0003 09 83 04"), 0x1234, 9, 6) == (None, 4)
    with pytest.raises(ValueError, match="transaction id"):
        decode_read_response(reply, 0x1235, 9, 6)
    with pytest.raises(ValueError, match="unit id"):
        decode_read_response(reply, 0x1234, 8, 6)
    with pytest.raises(ValueError, match="byte count 255"):
        decode_read_response(reply[:8] + b"\xff" + reply[9:], 0x1234, 9, 6)
    with pytest.raises(ValueError, match="length field"):
        frame_length(bytes.fromhex("1234 0000 0000"))


def test_the_process_hand_off_carries_the_saturation_of_its_six_floats():
    """The slot carries the six floats, not the saturation text: the parent's Published
    gets it from them again, the text the child's PollCore.sample published."""
    counters = (("samples", 0), ("connects", 1), ("connect_failures", 0), ("disconnects", 0))
    rest = (1.0, "", None, 0, 1, 0, counters, False)
    w = wrench_from_registers([0, 0, 32767, 0, 0, 0])
    p = _make_pub(tuple(w), *rest)
    assert p.saturation == w.saturation == "Fz saturated at +327.67 N (int16 limit)"
    assert _make_pub(W_LEFT.as_tuple(), *rest).saturation == ""
    assert _make_pub(None, *rest).saturation == "" and _make_pub(None, *rest).wrench is None
