"""``rig sim`` — the simulated rig served in its own process — and ``rig run`` against it.

1. The SLCAN adapter alone: python-can's own ``slcan`` client <-> adapter <-> virtual bus
   (bridge mode), or devices served by the adapter's own thread (direct mode); the CAN
   responder (adapter + virtual drives) in this process or in a child process.
2. End to end: ``rig sim`` in one subprocess, ``rig run --config <generated>`` in another.
3. Signals: SIGINT/SIGTERM stop ``rig run`` cleanly (the simulated drives end at zero
   current, disabled); after SIGKILL the simulated converters' own watchdog cuts the current.
4. A scenario's fault injection acts at its scenario time (``rig sim --scenario``).

Times in the simulator's status are ``time.monotonic()``, system-wide on Linux, so they are
compared with this process's clock directly.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import threading
import time

import can
import numpy as np
import pytest

from rig_runtime import config, schema
from rig_runtime.app.export import read_log
from sim_backend.launcher import start_sim_process
from sim_backend.realtime_sim import RealtimeSim
from sim_backend.slcan import SlcanAdapter, encode_frame, parse_frame

from .e2e import realtime_config, realtime_sim_config

WHEELS = ("fl", "fr", "rl", "rr")
_CFG = config.load()
H_S = _CFG.controller.h
STATUS_PERIOD_S = 0.05


def rig_run_cmd(*args: str) -> list[str]:
    """The unmodified `rig run` (``python -m rig_runtime`` is the ``rig`` command)."""
    return [sys.executable, "-m", "rig_runtime", "run", *args]


# ============================================================================ 1. SLCAN adapter
@pytest.fixture
def slcan_pair():
    chan = f"slcan-test-{os.getpid()}-{time.monotonic_ns()}"
    adapter_bus = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    far = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    adapter = SlcanAdapter(adapter_bus).start()
    yield adapter, far
    adapter.close()
    adapter_bus.shutdown()
    far.shutdown()


def _recv(bus, timeout=2.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        m = bus.recv(0.05)
        if m is not None:
            return m
    return None


def _until(cond, what: str, timeout: float = 2.0) -> None:
    """Poll ``cond()`` until true (the adapter's threads act asynchronously); fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f"{what}: not within {timeout} s"
        time.sleep(0.005)


def _readable(fd) -> bool:
    return bool(select.select([fd], [], [], 0)[0])


def test_slcan_python_can_client_both_ways(slcan_pair):
    adapter, far = slcan_pair
    client = can.Bus(interface="slcan", channel=adapter.port_name, bitrate=1_000_000, sleep_after_open=0)
    try:
        deadline = time.monotonic() + 2.0
        while not adapter.is_open and time.monotonic() < deadline:     # the adapter reads on its thread
            time.sleep(0.005)
        assert adapter.is_open and adapter.bitrate == 1_000_000
        assert client.get_version(2.0) == (10, 13)
        assert client.get_serial_number(2.0) == "RIG0"
        frames = []
        for ext in (False, True):
            for dlc in range(9):
                cid = (0x1ABCDE00 + dlc) if ext else (0x700 + dlc)
                frames.append(can.Message(arbitration_id=cid, is_extended_id=ext, data=bytes(range(0xF0, 0xF0 + dlc))))
        frames.append(can.Message(arbitration_id=0x123, is_extended_id=False, is_remote_frame=True, dlc=4))
        frames.append(can.Message(arbitration_id=0x1234567, is_extended_id=True, is_remote_frame=True, dlc=0))
        for m in frames:
            # host -> bus
            client.send(m, timeout=0)
            r = _recv(far)
            assert r is not None, m
            assert (r.arbitration_id, r.is_extended_id, r.is_remote_frame, r.dlc) == \
                   (m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.dlc)
            assert bytes(r.data) == bytes(m.data)
            # bus -> host
            far.send(m)
            r = _recv(client)
            assert r is not None, m
            assert (r.arbitration_id, r.is_extended_id, r.is_remote_frame, r.dlc) == \
                   (m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.dlc)
            assert bytes(r.data) == bytes(m.data)
        # a burst from the bus arrives complete and in order; recv(0) drains without acks in between
        burst = [can.Message(arbitration_id=0x181 + i % 4, is_extended_id=False, data=i.to_bytes(8, "little"))
                 for i in range(50)]
        for m in burst:
            far.send(m)
        got, deadline = [], time.monotonic() + 3.0
        while len(got) < len(burst) and time.monotonic() < deadline:
            m = client.recv(0.05)
            if m is not None:
                got.append(m)
        assert [bytes(m.data) for m in got] == [bytes(m.data) for m in burst]
        # sends at the runtime's rate leave no acknowledgement lines behind: recv(0) sees nothing
        for _ in range(20):
            client.send(can.Message(arbitration_id=0x80, is_extended_id=False), timeout=0)
        n = 0
        while _recv(far) is not None:
            n += 1
            if n == 20:
                break
        assert n == 20
        assert client.recv(0.1) is None
    finally:
        client.shutdown()
    deadline = time.monotonic() + 2.0
    while adapter.is_open and time.monotonic() < deadline:
        time.sleep(0.005)
    assert not adapter.is_open                 # python-can sends C at shutdown
    far.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x01"))
    _until(lambda: adapter.counters["closed_dropped"] >= 1, "a frame while closed dropped")
    assert adapter.counters["bad_commands"] == 0


def _raw_exchange(fd, text: bytes, expect_bytes: int, timeout=2.0) -> bytes:
    os.write(fd, text)
    out = b""
    deadline = time.monotonic() + timeout
    while len(out) < expect_bytes and time.monotonic() < deadline:
        r, _, _ = select.select([fd], [], [], 0.05)
        if r:
            out += os.read(fd, 4096)
    return out


def test_slcan_protocol_details(slcan_pair):
    adapter, far = slcan_pair
    import tty
    fd = os.open(adapter.port_name, os.O_RDWR | os.O_NOCTTY)
    try:
        tty.setraw(fd)
        assert _raw_exchange(fd, b"t1230\r", 1) == b"\x07"           # not open: refused
        assert _raw_exchange(fd, b"S8\r", 1) == b"\r"
        assert _raw_exchange(fd, b"S77\r", 1) == b"\x07"             # unknown bit rate
        assert _raw_exchange(fd, b"O\r", 1) == b"\r"
        assert _raw_exchange(fd, b"S6\r", 1) == b"\x07"              # bit rate only while closed
        assert _raw_exchange(fd, b"t12321122\r", 1, timeout=0.2) == b""   # no ack for transmit
        m = _recv(far)
        assert (m.arbitration_id, bytes(m.data)) == (0x123, b"\x11\x22")
        assert _raw_exchange(fd, b"t1232112\r", 1) == b"\x07"         # data shorter than the DLC
        assert _raw_exchange(fd, b"t8000\r", 1) == b"\x07"            # 11-bit id out of range
        assert _raw_exchange(fd, b"F\r", 4) == b"F00\r"
        far.send(can.Message(is_error_frame=True, arbitration_id=0, dlc=0))
        _until(lambda: adapter.counters["error_frames"] == 1, "the error frame seen by the adapter")
        assert _raw_exchange(fd, b"F\r", 4) == b"F80\r"              # bus error seen, then cleared
        assert _raw_exchange(fd, b"F\r", 4) == b"F00\r"
        assert _raw_exchange(fd, b"V\r", 6) == b"V1013\r"
        assert _raw_exchange(fd, b"?\r", 1) == b"\x07"
        # frames while closed are dropped; what the host left unread is discarded when it opens again
        assert _raw_exchange(fd, b"C\r", 1) == b"\r"
        far.send(can.Message(arbitration_id=0x701, is_extended_id=False, data=b"\x05"))
        _until(lambda: adapter.counters["closed_dropped"] == 1, "0x701 dropped while closed")
        assert _raw_exchange(fd, b"O\r", 1) == b"\r"
        far.send(can.Message(arbitration_id=0x702, is_extended_id=False, data=b"\x05"))   # left unread
        _until(lambda: _readable(fd), "0x702 written to the host")
        opens = adapter.counters["opens"]
        os.write(fd, b"C\rO\r")
        _until(lambda: adapter.counters["opens"] == opens + 1 and _readable(fd), "the reopen answered")
        far.send(can.Message(arbitration_id=0x1FFFFFFF, is_extended_id=True, data=b""))
        out = _raw_exchange(fd, b"", 12)
        assert out == b"\rT1FFFFFFF0\r", out
        assert adapter.counters["closed_dropped"] == 1
    finally:
        os.close(fd)


def test_slcan_codec_roundtrip():
    for m in (can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"\x00" * 8),
              can.Message(arbitration_id=0, is_extended_id=True, data=b""),
              can.Message(arbitration_id=0x10, is_extended_id=False, is_remote_frame=True, dlc=8)):
        line = encode_frame(m)
        r = parse_frame(line[:-1])
        assert (r.arbitration_id, r.is_extended_id, r.is_remote_frame, r.dlc, bytes(r.data)) == \
               (m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.dlc, bytes(m.data))
    assert encode_frame(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\xab"), 0x1234) == b"t1811AB1234\r"
    for bad in (b"t12", b"t12391122", b"t123x", b"T1234567", b"t12G0", b"r1231FF"):
        assert parse_frame(bad) is None


def test_slcan_direct_mode_answers_in_the_reading_thread():
    """Direct mode: the devices behind the adapter are served by the thread that read the
    host's frames; what they send meanwhile goes to the host in one write."""
    seen: list = []
    written: list = []

    def service(t):
        while (m := adapter.device_bus.recv(0.0)) is not None:
            seen.append((m.arbitration_id, threading.get_ident()))
            if m.arbitration_id == 0x080:                 # SYNC -> two "TPDOs"
                for node in (1, 2):
                    adapter.device_bus.send(can.Message(arbitration_id=0x180 + node, is_extended_id=False,
                                                        data=bytes([node] * 8)))

    adapter = SlcanAdapter(None, service=service, on_host_frames=lambda msgs, t: written.append(len(msgs)))
    adapter.start()
    client = can.Bus(interface="slcan", channel=adapter.port_name, bitrate=1_000_000, sleep_after_open=0)
    try:
        deadline = time.monotonic() + 2.0
        while not adapter.is_open and time.monotonic() < deadline:
            time.sleep(0.005)
        assert adapter.is_open and adapter.bitrate == 1_000_000
        client.send(can.Message(arbitration_id=0x080, is_extended_id=False, data=b""), timeout=0)
        got = [_recv(client), _recv(client)]
        assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(0x181, b"\x01" * 8), (0x182, b"\x02" * 8)]
        deadline = time.monotonic() + 2.0                       # the callback runs after the write:
        while not written and time.monotonic() < deadline:     # the client may read first
            time.sleep(0.005)
        assert written == [2]                                   # both TPDOs in one write
        assert [cid for cid, _ in seen] == [0x080]
        assert seen[0][1] == adapter._threads[0].ident          # served by the adapter's own thread
        assert adapter.counters["bad_commands"] == 0
    finally:
        client.shutdown()
        adapter.close()
    assert adapter.device_bus is not None


class _Feeder:
    """The runtime's part of the cycle — poll, then write the currents — every period on a
    thread of its own, so that the drives stay fed (their RPDO watchdog is 50 ms) while the
    test asks the simulator for its status. Its latest reading, its cycle count and the
    largest gap between two of its cycles (a stall of this process, not of the simulator)."""

    def __init__(self, db, currents: dict, h: float):
        self.db, self.currents, self.h = db, currents, h
        self.cycles = 0
        self.max_gap = 0.0
        self.last = None
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="feeder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t_prev = None
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                self.last = self.db.poll(now)
                self.db.write(self.currents, now)
                if t_prev is not None:
                    self.max_gap = max(self.max_gap, now - t_prev)
                t_prev = now
                self.cycles += 1
                time.sleep(self.h)
        except BaseException as e:  # noqa: BLE001 - raised in the test's thread by stop()
            self.error = e

    def wait(self, cond, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            assert self.error is None and self._thread.is_alive(), f"the feeding thread ended: {self.error!r}"
            assert time.monotonic() < deadline, f"{what}: not within {timeout} s"
            time.sleep(0.005)

    def halt(self) -> None:
        """Stop after the cycle under way."""
        self._stop.set()
        self._thread.join(10.0)

    def stop(self):
        """Stop after the cycle under way; its reading."""
        self.halt()
        assert not self._thread.is_alive(), "the feeding thread did not end"
        if self.error is not None:
            raise self.error
        return self.last


# The drives are fed by a thread of this (normally scheduled) test process while the test asks
# for the status: what the machine's scheduling does to that thread is not what this test
# checks, so it states the tolerance it needs — the real-time tests' config (tests/e2e.py
# realtime_sim_config: the drives' RPDO watchdog 300 ms rather than the shipped 50 ms), and
# 2 s for an SDO answer while configuring (the driver's default is 0.3 s; test_canopen402 alike).
FEEDER_WATCHDOG_MS = 300
FEEDER_SDO_TIMEOUT_S = 2.0


@pytest.mark.parametrize("mode", ["process", "thread"])
def test_can_responder_serves_the_drives(mode, tmp_path):
    """RealtimeSim with the CAN responder in a child process or on a thread of its own: the
    runtime's drive driver (over rig_slcan) starts the drives, every SYNC gets its TPDOs,
    the commanded currents reach the plant side, an NMT stop ends the session."""
    from drivers.canopen402 import DriveBus
    cfg = config.load(realtime_sim_config(tmp_path))
    assert cfg.devices.can.watchdog_ms == FEEDER_WATCHDOG_MS
    h = cfg.controller.h
    feeder = None
    with RealtimeSim(cfg, seed=0, can_responder=mode) as rt:
        cc = cfg.devices.can
        bus = can.Bus(interface="rig_slcan", channel=rt.can_port, bitrate=cc.bitrate)
        db = DriveBus(cc, bus=bus, period_s=h, sdo_timeout_s=FEEDER_SDO_TIMEOUT_S)
        try:
            db.configure()
            t_activate = time.monotonic()
            db.activate(t_activate)   # the following writes walk the drives to OPERATION ENABLED
            feeder = _Feeder(db, {"fl": 1.0, "fr": -1.0, "rl": 0.0, "rr": 0.5}, h)
            feeder.wait(lambda: rt.session_active, 5.0, "the session started (every drive enabled)")
            t_session, n0 = time.monotonic(), feeder.cycles
            feeder.wait(lambda: feeder.cycles - n0 >= 60 and time.monotonic() - t_activate >= 0.5, 10.0,
                        "60 cycles in the session")
            # a snapshot from the session (the child's reply; ResponderProcess.snapshot would
            # give the previous one, from before any SYNC, after 0.5 s without a reply)
            st: dict = {}

            def fresh() -> bool:
                nonlocal st
                st = rt.status()
                return all((st["drives"].get(w, {}).get("last_sync_t") or 0.0) > t_session for w in WHEELS)

            feeder.wait(fresh, 5.0, "a status snapshot from the session")
            assert st["can_responder"]["mode"] == mode and st["error"] == ""
            assert (mode == "process") == (st["can_responder"]["pid"] != os.getpid())
            assert st["session"]["active"] and st["session"]["count"] == 1
            assert st["currents"]["fl"] == pytest.approx(1.0, abs=0.01)
            assert st["currents"]["rr"] == pytest.approx(0.5, abs=0.01)
            assert rt.can.currents[0] == pytest.approx(1.0, abs=0.01)          # what the plant integrates
            assert all(st["drives"][w]["state"] == "OPERATION ENABLED" for w in WHEELS), st["drives"]
            lat = st["session_stats"]["tpdo_latency_ms"]
            assert lat["n"] > 50 and lat["max"] < 100
            r = feeder.stop()               # the reading of its last cycle
            assert all(x.health.state.value == "fresh" for x in r), r
        finally:
            if feeder is not None:
                feeder.halt()
            db.close()                      # deactivates first
            bus.shutdown()
        deadline = time.monotonic() + 2.0
        while (rt.session_active or any(v != 0.0 for v in st["currents"].values())) and time.monotonic() < deadline:
            time.sleep(0.01)
            st = rt.status()                # the child's reply (the previous one if it is late)
        assert not rt.session_active
        assert all(v == 0.0 for v in st["currents"].values()), st["currents"]


def test_session_starts_when_every_drive_is_enabled_not_at_the_first_sync():
    """Scenario time in ``rig sim`` starts when the runtime has enabled every drive (at its
    ARM): an NMT start and SYNCs and RPDOs from a runtime that keeps the drives disabled
    start nothing; the enable does, and the session ends with the runtime's safe stop (NMT
    pre-operational)."""
    from drivers.canopen402 import DriveBus
    cfg = config.load()
    h = cfg.controller.h
    with RealtimeSim(cfg, seed=0, can_responder="thread") as rt:
        cc = cfg.devices.can
        bus = can.Bus(interface="rig_slcan", channel=rt.can_port, bitrate=cc.bitrate)
        db = DriveBus(cc, bus=bus, period_s=h)

        def cycles(n: int) -> None:
            for _ in range(n):
                now = time.monotonic()
                db.poll(now)
                db.write({"fl": 0.0, "fr": 0.0, "rl": 0.0, "rr": 0.0}, now)
                time.sleep(h)

        try:
            db.configure()                  # no power: the drives are enabled only at ARM
            deadline = time.monotonic() + 2.0
            while rt.session_active and time.monotonic() < deadline:
                time.sleep(0.01)
            count = rt.status()["session"]["count"]
            assert not rt.session_active
            bus.send(can.Message(arbitration_id=0x000, data=[0x01, 0x00], is_extended_id=False))  # NMT start all
            cycles(40)                      # OPERATIONAL, SYNC + RPDOs every cycle, drives disabled
            st = rt.status()
            assert not st["session"]["active"] and st["session"]["count"] == count
            assert st["session"]["last_sync_t"] is not None
            t_enable = time.monotonic()
            db.activate(t_enable)
            deadline = time.monotonic() + 2.0
            while not db.enabled and time.monotonic() < deadline:
                cycles(1)
            deadline = time.monotonic() + 2.0      # the plant thread picks the session start up
            while not rt.session_active and time.monotonic() < deadline:
                cycles(1)
            st = rt.status()
            assert st["session"]["active"] and st["session"]["count"] == count + 1, st["session"]
            assert st["session"]["t0"] >= t_enable
            assert all(st["drives"][w]["state"] == "OPERATION ENABLED" for w in WHEELS)
        finally:
            db.close()                      # deactivates first
            bus.shutdown()
        deadline = time.monotonic() + 2.0
        while rt.session_active and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not rt.session_active


# ============================================================================ 2./3. processes
# SCHED_FIFO for the simulator and (via the generated config) the runtime, the runtime
# above, when the OS permits (both report and carry on when it does not). Measured on a
# loaded 2-core machine (docs/sim-process.md): without it the runtime faulted on its own
# deadline misses or driver races in 2 of 5 runs of 6 s, with it in none of 5. No CPU
# pinning: each process's helper threads would then compete with its real-time thread
# for one CPU with no time slicing, which measured no better
SIM_RT_ARGS = ["--rt-priority", "50", "--runtime-rt-priority", "80"]


class SharedSim:
    """One `rig sim` (SIM_RT_ARGS) shared by a module's tests, each running its own `rig run`
    session against it; attributes are the SimProcess's. ``run_config``: the generated config
    with the real-time tests' stated tolerance (tests/e2e.py REALTIME_TOLERANCE: the machine's
    scheduling is not what these tests check), the one every `rig run` here uses."""

    def __init__(self, tmp_path_factory, extra_args=()):
        workdir = tmp_path_factory.mktemp("rig-sim")
        self.sim_config = realtime_sim_config(workdir)         # what `rig sim --config` simulates
        self.sp = start_sim_process(config=self.sim_config, extra_args=SIM_RT_ARGS + list(extra_args),
                                    workdir=workdir)
        self.run_config = realtime_config(self.sp.config_path, self.sp.config_path.with_name("rig-run.yaml"))

    def __getattr__(self, name):            # status(), wait_status(), config_path, ports, ...
        return getattr(self.sp, name)

    def close(self) -> None:
        code = self.sp.stop(signal.SIGINT)
        assert code == 0, self.sp.stderr()


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """One `rig sim` for the module; each test runs its own `rig run` session against it."""
    s = SharedSim(tmp_path_factory)
    yield s
    s.close()


def _log_faults(log) -> list[dict]:
    try:
        ev = read_log(log)["events"]
    except Exception:  # noqa: BLE001 - a log killed before its first flush
        return []
    return [{"device": d, "check": c, "message": m}
            for k, d, c, m in zip(ev["kind"], ev["device"], ev["check"], ev["message"]) if k == "fault"]


def _start_run(config_path, tmp_path, name, *extra):
    """`rig run --config config_path` (e.g. a SharedSim's run_config: the stated tolerance),
    with a `rig ctl` socket of its own (the default path is shared with every run of this user)."""
    log = tmp_path / f"{name}.h5"
    cmd = rig_run_cmd("--config", str(config_path), "--scenario", "single-step", "--json", "--log", str(log),
                      "--ctl-socket", str(log.with_suffix(".sock")), *extra)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
    return proc, log


def _kill_and_explain(sim, proc, log, what: str):
    """Kill a `rig run` that misbehaved and fail, with its log's faults and its output."""
    proc.kill()
    out, err = proc.communicate()
    pytest.fail(f"{what}; log faults {_log_faults(log)}\nstdout: {out[-2000:]}\nstderr: {err[-3000:]}")


def _finish(sim, proc, log, timeout) -> dict:
    """Wait for `rig run` to end (exit 0); its JSON summary."""
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        _kill_and_explain(sim, proc, log, f"rig run did not end within {timeout} s")
    try:
        summary = json.loads(out.strip().splitlines()[-1])
    except (IndexError, ValueError):
        pytest.fail(f"rig run exited {proc.returncode} without a JSON summary\nstdout: {out[-2000:]}\nstderr: {err[-3000:]}")
    assert proc.returncode == 0 and summary["final_state"] != "FAULT", \
        f"exit {proc.returncode}, faults {summary['faults']}, timing {summary.get('timing')}\nstderr: {err[-3000:]}"
    return summary


def _wait_running(sim, proc, log, min_session_s=1.6, timeout=20.0) -> dict:
    """Until the runtime is in its session for min_session_s (past the step at 1 s) and the
    rear converters apply current; the status at that moment."""
    deadline = time.monotonic() + timeout
    count0 = sim.status()["session"]["count"]
    st: dict = {}
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            _finish(sim, proc, log, 5)
            pytest.fail(f"rig run ended before it was stopped ({proc.returncode})")
        st = sim.status()
        ses = st["session"]
        if ses["count"] > count0 and not ses["active"]:          # the runtime stopped the drives by itself
            try:
                proc.wait(0.5)                                     # let it end (or show that it hangs)
            except subprocess.TimeoutExpired:
                pass
            if proc.poll() is not None:
                _finish(sim, proc, log, 5)
                pytest.fail(f"rig run ended before it was stopped ({proc.returncode})")
            _kill_and_explain(sim, proc, log, "rig run disabled the drives by itself and did not end")
        if (ses["active"] and ses["t0"] is not None and st["t"] - ses["t0"] > min_session_s
                and abs(st["currents"]["rl"]) > 0.02):
            return st
        time.sleep(0.02)
    _kill_and_explain(sim, proc, log, f"rig run never got RUNNING with current against rig sim; last status {st}")


def test_generated_config_points_at_the_simulator(sim):
    cfg = config.load(sim.config_path)
    assert cfg.devices.can.interface == "rig_slcan" and cfg.devices.can.channel == sim.ports["can"]["channel"]
    assert {l.role: l.port for l in cfg.devices.lasers} == sim.ports["laser"]
    assert {s.name: (s.host, s.port) for s in cfg.devices.ft.sensors} == sim.ports["ft"]
    ref = config.load(sim.sim_config)                    # the same plant, controller, geometry
    assert cfg.plant == ref.plant and cfg.controller == ref.controller and cfg.geometry == ref.geometry
    assert cfg.devices.can.drives == ref.devices.can.drives and cfg.devices.can.watchdog_ms == ref.devices.can.watchdog_ms
    for line in sim.lines[:-1]:
        assert line.split()[0] in ("laser", "can", "ft", "status", "config")
    assert sim.lines[-1] == "ready"
    st = sim.wait_status(lambda s: s["timing"]["steps"] > 10, timeout_s=5.0)
    assert st["error"] == "" and not st["session"]["active"]
    # the SLCAN adapter and the drives answer from a process of their own
    assert st["can_responder"]["mode"] == "process" and st["can_responder"]["pid"] != st["pid"]


def test_generated_config_matches_the_shipped_template(sim, tmp_path):
    """configs/sim-process.yaml documents the generated file: same settings, other ports
    (this module's rig sim simulates configs/sim.yaml with the stated tolerance: the template
    with the same tolerance)."""
    gen = config.load(sim.config_path)
    tpl = config.load(realtime_config(config.CONFIG_DIR / "sim-process.yaml", tmp_path / "template.yaml"))

    def strip(c):
        d = schema.to_dict(c.devices)
        d["can"]["channel"] = d["can"]["eds"] = None
        for l in d["lasers"]:
            l["port"] = None
        for f in d["ft"]["sensors"]:
            f["port"] = None
        return d

    assert strip(gen) == strip(tpl)
    assert (gen.plant, gen.controller, gen.limits, gen.geometry) == (tpl.plant, tpl.controller, tpl.limits, tpl.geometry)
    assert gen.devices.can.interface == tpl.devices.can.interface == "rig_slcan"


@pytest.mark.slow
def test_rig_run_against_rig_sim_tracks_the_step(sim, tmp_path):
    sessions0 = sim.status()["session"]["count"]
    proc, log = _start_run(sim.run_config, tmp_path, "e2e", "--duration", "6")
    summary = _finish(sim, proc, log, 30)
    assert summary["final_state"] == "IDLE", summary
    assert summary["faults"] == [], summary
    assert summary["recorder"]["healthy"] and summary["recorder"]["rows"] > 1000
    d = read_log(log)
    c = d["columns"]
    assert len(c["t"]) == summary["recorder"]["rows"]
    run = c["t_run"] > 0
    t, y, y_ref = c["t_run"][run], c["y_r"][run], c["y_ref"][run]
    assert t[-1] > 5.5
    assert abs(y_ref[-1] - 2.0e-3) < 1e-9
    tail = t > t[-1] - 0.5
    assert abs(float(np.mean(y[tail])) - 2.0e-3) < 0.35e-3, float(np.mean(y[tail]))
    assert float(np.max(y)) < 3.0e-3                       # no wild overshoot
    before = (t > 0.8) & (t < 1.0)
    assert float(np.mean(y[before])) < 1.0e-3               # the 2 mm came from the step, not before it
    st = sim.wait_status(lambda s: not s["session"]["active"], timeout_s=2.0)   # ended by the NMT stop
    assert st["session"]["count"] == sessions0 + 1, st["session"]
    assert all(v == 0.0 for v in st["currents"].values())
    assert st["error"] == ""


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_stops_rig_run_cleanly(sim, tmp_path, sig):
    trips0 = {w: d["watchdog_trips"] for w, d in sim.status()["drives"].items()}
    proc, log = _start_run(sim.run_config, tmp_path, sig.name)
    _wait_running(sim, proc, log)
    proc.send_signal(sig)
    summary = _finish(sim, proc, log, 20)
    t_exit = time.monotonic()
    assert summary["final_state"] == "IDLE" and summary["faults"] == [], summary
    d = read_log(log)
    assert len(d["columns"]["t"]) == summary["recorder"]["rows"] > 0
    assert any("signal" in m for m in d["events"]["message"])
    # the simulated converters: zero current, disabled and pre-operational by the runtime's safe
    # stop — not by their watchdog, and not by their heartbeat consumer (switched off by the
    # runtime before it left: no EMCY 0x8130 once the consumer time has passed)
    can_cfg = config.load(sim.run_config).devices.can
    consumer_s = can_cfg.heartbeat_ms * can_cfg.heartbeat_timeout_factor / 1000.0
    st = sim.wait_status(lambda s: s["t"] > t_exit + consumer_s + STATUS_PERIOD_S, timeout_s=2.0)
    for w in WHEELS:
        dr = st["drives"][w]
        assert dr["current_A"] == 0.0, st
        assert dr["nmt"] == "PRE-OPERATIONAL", st
        assert dr["state"] == "SWITCH ON DISABLED" and dr["error_code"] == 0, (w, st["drives"])
        assert dr["watchdog_trips"] == trips0[w], st


@pytest.mark.slow
def test_sigkill_converter_watchdog_cuts_current(sim, tmp_path):
    trips0 = {w: d["watchdog_trips"] for w, d in sim.status()["drives"].items()}
    proc, log = _start_run(sim.run_config, tmp_path, "sigkill")
    st = _wait_running(sim, proc, log)
    t_kill = time.monotonic()
    proc.send_signal(signal.SIGKILL)
    proc.wait(5)
    faults = _log_faults(log)
    assert faults == [], faults              # it had not faulted (and disabled the drives) before the kill
    watchdog_s = config.load(sim.run_config).devices.can.watchdog_ms / 1000.0     # the stated tolerance's
    powered = [w for w in WHEELS if st["currents"][w] != 0.0]
    assert "rl" in powered and "rr" in powered
    # the status file (rewritten every 50 ms) shows every converter off within the watchdog time
    # (a drive whose last RPDOs the killed runtime did not get to send trips one period earlier;
    # the plant thread notes the current's end at its next step, up to 5 ms after the trip)
    def all_off(s):
        return (s["t"] > t_kill and all(v == 0.0 for v in s["currents"].values())
                and all(d["state"] != "OPERATION ENABLED" for d in s["drives"].values()))

    st = sim.wait_status(all_off, timeout_s=3.0, period_s=0.005)
    t_all_off = st["t"]
    st = sim.wait_status(lambda s: all((s["drives"][w]["t_current_zero"] or 0.0) > t_kill - 0.01 for w in powered),
                         timeout_s=1.0, period_s=0.005)
    margin = 0.25                                 # a loaded 2-core machine
    assert t_all_off - t_kill < watchdog_s + STATUS_PERIOD_S + margin, (t_all_off - t_kill, st)
    for w in WHEELS:
        dr = st["drives"][w]
        assert dr["state"] == "FAULT" and dr["error_code"] == 0x8250, dr          # EMCY RPDO timeout
        assert dr["nmt"] == "OPERATIONAL", dr                                     # nobody told it otherwise
        assert dr["watchdog_trips"] == trips0[w] + 1, dr
    for w in powered:
        dr = st["drives"][w]
        last_cmd = min(dr["last_sync_t"], dr["last_rpdo_t"])
        t_zero = dr["t_current_zero"]                # seen by the plant thread (5 ms resolution)
        assert t_zero is not None and t_zero > t_kill - 0.01, dr
        assert t_zero - last_cmd >= watchdog_s - 0.002, (t_zero - last_cmd, dr)  # not before the timeout
        assert t_zero - t_kill <= watchdog_s + margin, (t_zero - t_kill, dr)


@pytest.mark.slow
def test_scenario_faults_act_in_scenario_time(tmp_path):
    """`rig sim --scenario fault-dropout`: laser b_f falls silent 3 s into the session
    (scenario time starts when the runtime has enabled every drive, about when it goes RUNNING).
    A lost lateral laser a fault (degraded mode ``stop``; sim.yaml observes: DEGRADED)."""
    from .e2e import REALTIME_CEILINGS, REALTIME_TOLERANCE, config_with
    with start_sim_process(config=realtime_sim_config(tmp_path), scenario="fault-dropout", workdir=tmp_path / "sim",
                           extra_args=SIM_RT_ARGS) as sp:
        run_config = config_with(sp.config_path, tmp_path / "rig-run.yaml",      # the stated tolerance
                                 {**REALTIME_TOLERANCE, "degraded.on_lateral_loss": "stop"}, ceilings=REALTIME_CEILINGS)
        log = tmp_path / "dropout.h5"
        proc = subprocess.Popen(rig_run_cmd("--config", str(run_config), "--scenario", "fault-dropout",
                                            "--json", "--log", str(log), "--ctl-socket", str(log.with_suffix(".sock"))),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            pytest.fail(f"rig run did not end\nstderr: {err[-3000:]}")
        try:
            summary = json.loads(out.strip().splitlines()[-1])
        except (IndexError, ValueError):
            pytest.fail(f"rig run exited {proc.returncode} without a JSON summary\nstderr: {err[-3000:]}")
        st = sp.status()
    stale_s = config.load(run_config).limits.stale_periods * H_S
    assert summary["final_state"] == "FAULT", summary
    f = summary["faults"][0]
    assert [(f["device"], f["check"]) for f in summary["faults"]] == [("b_f", "stale")], summary["faults"]
    t_fault = f["t"] - summary["run_started_t"]               # RUNNING time; the session began earlier
    lead = summary["run_started_t"] - st["session"]["t0"]
    # the longest stall the run config lets the loop survive (overrun_burst - 1 periods), and
    # the period in which it is found
    late_max = (config.load(run_config).limits.overrun_burst - 1) * H_S + H_S
    # the session begins when the simulated drives have all reached OPERATION ENABLED (the
    # runtime's ARM enabled them); the runtime goes RUNNING in the cycle whose poll brings
    # their statuswords (the TPDOs answering its next SYNC: a period or two later; measured
    # 9.7 ms), later only by a stall the run config tolerates — of the loop (late_max) or of
    # an input (stale_s). The cycle's time is read before its poll: it precedes the enable
    # only if the simulator enabled the drives (and answered) between the two, i.e. within a
    # stall of the loop the run config tolerates
    assert -late_max <= lead <= 2 * H_S + late_max + stale_s, (lead, late_max, stale_s)
    # b_f's last frame left just before 3 s of the session (1 kHz): stale once older than
    # stale_s, found by the next cycle — up to late_max later
    assert 3.0 - lead + stale_s - 0.002 <= t_fault <= 3.0 - lead + stale_s + late_max, (t_fault, lead, stale_s)
