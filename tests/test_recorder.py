"""Recorder: lossless round trip, never blocking the loop, failures leave a readable file."""

import errno
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import h5py
import numpy as np
import pytest

from rig_runtime import logfile as logmod
from rig_runtime import sidecar
from rig_runtime.logfile import LogFile
from rig_runtime.errors import DeviceInitError
from rig_runtime.app.export import events_path_for, read_log, to_csv
from rig_runtime.recorder import Recorder

from .conftest import ROOT

COLS = ["t", "state", "y_ref", "y", "psi", "u_cmd", "u_limited", "b_f", "b_f_age"]   # not alphabetical
ATTRS = {
    "config": json.dumps({"controller": {"h": 0.005}, "note": "ψ in rad"}),
    "software_version": "0.1.0",
    "start_time": "2026-05-09T07:35:25.123+00:00",
    "h": 0.005,
}


def row(i: int) -> tuple:
    return tuple(i * 0.005 if j == 0 else i * 10.0 + j for j in range(len(COLS)))


def feed(rec: Recorder, start: int, stop: int, timeout: float = 10.0) -> None:
    """Append rows start..stop-1 as fast as the writer keeps up (never dropping one)."""
    deadline = time.monotonic() + timeout
    for i in range(start, stop):
        while rec.pending >= rec.buffer_cycles - 1:
            assert time.monotonic() < deadline, "writer did not keep up"
            time.sleep(0.001)
        assert rec.append(row(i)), f"row {i} refused: {rec.error}"


def wait_for(cond, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.005)


@pytest.fixture
def log(tmp_path):
    return tmp_path / "run.h5"


def test_round_trip(log):
    rec = Recorder(log, COLS, attrs=ATTRS, buffer_cycles=2048, flush_s=0.2)
    rec.open()
    n = 10_000                                    # several times the ring
    feed(rec, 0, n // 2)
    rec.event(1.25, "state", device="", check="", message="ARMED -> RUNNING")
    rec.event(2.5, "fault", device="laser b_f", check="stale", value=0.031, limit=0.02, message="ψ sample 31 ms old")
    feed(rec, n // 2, n)
    rec.close()
    rec.close()                                   # idempotent
    assert rec.healthy, rec.error
    assert rec.error == "" and rec.rows_written == n and rec.rows_dropped == 0

    # raw layout, as MATLAB h5read('/cycles/t') sees it
    with h5py.File(log, "r") as f:
        t = f["/cycles/t"]
        assert t.dtype == np.float64 and t.ndim == 1 and t.maxshape == (None,) and t.chunks is not None
        assert list(f.attrs["columns"]) == COLS
        assert h5py.check_string_dtype(f.attrs.get_id("config").dtype).encoding == "utf-8"
        assert f["/events/kind"].dtype.kind == "O"

    d = read_log(log)
    assert list(d["columns"]) == COLS and d["rows"] == n
    expect = np.array([row(i) for i in range(n)])
    for j, c in enumerate(COLS):
        np.testing.assert_array_equal(d["columns"][c], expect[:, j])
    ev = d["events"]
    assert list(ev["kind"]) == ["state", "fault"]
    assert list(ev["device"]) == ["", "laser b_f"] and ev["check"][1] == "stale"
    assert ev["message"][1] == "ψ sample 31 ms old"
    np.testing.assert_array_equal(ev["t"], [1.25, 2.5])
    assert math.isnan(ev["value"][0]) and ev["value"][1] == 0.031 and ev["limit"][1] == 0.02
    a = d["attrs"]
    for k, v in ATTRS.items():
        assert a[k] == v
    assert json.loads(a["config"])["note"] == "ψ in rad"
    assert a["columns"] == COLS and a["rows_written"] == n and a["rows_dropped"] == 0
    assert a["recorder_error"] == "" and a["log_format"] == "rig-runtime-log"


def test_append_never_blocks_when_the_sidecar_stalls(log, monkeypatch):
    """The sidecar stopped (SIGSTOP: a hung disk): the ring fills, ``append`` refuses at once
    (a recorder fault), and recording resumes when the sidecar does."""
    rec = Recorder(log, COLS, attrs={}, buffer_cycles=64, event_capacity=4)
    rec.open()
    os.kill(rec.process.pid, signal.SIGSTOP)
    try:
        for i in range(64):
            assert rec.append(row(i))
        assert rec.healthy

        def no_waiting(*a, **kw):
            raise AssertionError("append waited for the sidecar")
        # refused at once: neither the wait for room (when_full="wait") nor any sleep is reached
        with monkeypatch.context() as m:
            m.setattr(Recorder, "_wait_for_room", no_waiting)
            m.setattr(time, "sleep", no_waiting)
            refused = [rec.append(row(i)) for i in range(64, 164)]
        assert refused == [False] * 100
        assert not rec.healthy and "overflow" in rec.error and rec.rows_dropped == 100
        for k in range(10):
            rec.event(k, "operator")              # event ring (capacity 4) overflows, never blocks
        assert rec.events_dropped == 6
    finally:
        os.kill(rec.process.pid, signal.SIGCONT)
    wait_for(lambda: rec.pending == 0)
    for i in range(164, 200):                     # recording resumes once there is room again
        assert rec.append(row(i))
    rec.close()
    d = read_log(log)
    t = d["columns"]["t"]
    np.testing.assert_array_equal(t, [row(i)[0] for i in list(range(64)) + list(range(164, 200))])
    assert len(d["events"]["t"]) == 4
    assert d["attrs"]["rows_dropped"] == 100 and "overflow" in d["attrs"]["recorder_error"]

def test_write_failure_keeps_flushed_data(log, monkeypatch):
    """The log file's failure handling (what the sidecar runs): a batch dying half-way
    leaves the file as the last flush made it, readable by a plain reader."""
    lf = LogFile(log, COLS, {"h": 0.005})
    lf.create()
    block = np.array([row(i) for i in range(300)])
    lf.write(block, [(0.5, "state", "", "", math.nan, math.nan, "before the failure")], flush=True)
    assert lf.rows_flushed == 300 and not lf.error
    real = LogFile.store_column
    stored = []

    def store(d, start, data):
        stored.append(d.name)
        if len(stored) == 3:                      # two columns are longer already, this one extended
            d.id.set_extent((start + len(data),))
            raise OSError(errno.ENOSPC, "No space left on device")
        real(d, start, data)

    monkeypatch.setattr(LogFile, "store_column", staticmethod(store))
    lf.write(np.array([row(i) for i in range(300, 400)]), [], flush=False)
    assert lf.dead and "write failed" in lf.error and "No space left" in lf.error and "row 300" in lf.error
    lf.write(np.array([row(400)]), [], flush=True)      # nothing more is written
    lf.close({})
    with h5py.File(log, "r") as f:                # a plain reader opens it
        assert f["/cycles/t"].shape == (300,)
    d = read_log(log)
    assert d["rows"] == 300 and all(len(a) == 300 for a in d["columns"].values())
    np.testing.assert_array_equal(d["columns"]["y"], [row(i)[3] for i in range(300)])
    assert list(d["events"]["message"]) == ["before the failure"]

def test_disk_almost_full_stops_cleanly(log, monkeypatch):
    lf = LogFile(log, COLS, {}, min_free_bytes=10 * 2**20)
    lf.create()
    lf.write(np.array([row(i) for i in range(200)]), [], flush=True)
    real = logmod.shutil.disk_usage
    monkeypatch.setattr(logmod.shutil, "disk_usage", lambda p: real(p)._replace(free=2**20))   # 1 MiB left
    lf.write(np.array([row(i) for i in range(200, 250)]), [], flush=True)
    assert lf.dead and "disk almost full" in lf.error
    lf.close({})
    d = read_log(log)
    assert d["rows"] == 200
    np.testing.assert_array_equal(d["columns"]["t"], [row(i)[0] for i in range(200)])
    with pytest.raises(DeviceInitError, match="disk almost full"):   # and no new log starts on it
        LogFile(log.with_name("next.h5"), COLS, {}, min_free_bytes=10 * 2**20).create()
    assert not log.with_name("next.h5").exists()


def test_sidecar_write_failure_reaches_the_loop(log):
    """A failure inside the sidecar (here: the log's disk-space margin larger than any disk)
    turns the loop-side recorder unhealthy with the sidecar's cause."""
    rec = Recorder(log, COLS, attrs={}, flush_s=0.05)
    rec.open()
    feed(rec, 0, 50)
    wait_for(lambda: rec.rows_flushed == 50)
    rec.close()
    assert rec.healthy and rec.rows_written == 50
    rec = Recorder(log.with_name("b.h5"), COLS, attrs={}, flush_s=0.05, min_free_bytes=1 << 62)
    with pytest.raises(DeviceInitError, match="disk almost full"):
        rec.open()
    assert not log.with_name("b.h5").exists() and rec.process is None

def test_log_deleted_while_recording_is_a_recorder_fault(log):
    """The file unlinked under a running recorder: noticed at the next flush (unhealthy,
    the cause names it), instead of writing on into a file nobody can open again."""
    rec = Recorder(log, COLS, attrs={}, flush_s=0.05)
    rec.open()
    feed(rec, 0, 100)
    wait_for(lambda: rec.rows_flushed == 100)
    assert rec.healthy
    log.unlink()
    feed(rec, 100, 150)
    wait_for(lambda: not rec.healthy)
    assert "deleted while recording" in rec.error and str(log) in rec.error
    rec.close()


def test_flush_fsyncs_the_file(log, monkeypatch):
    synced = []
    real = logmod.os.fsync
    monkeypatch.setattr(logmod.os, "fsync", lambda fd: (synced.append(fd), real(fd))[1])
    lf = LogFile(log, COLS, {})
    lf.create()
    lf.write(np.array([row(i) for i in range(50)]), [], flush=True)
    lf.close({})
    assert synced and lf.rows_flushed == 50

def test_the_loop_process_gains_no_thread(log):
    """In real time the sidecar process does all file I/O; the recording process keeps its
    threads (the loop's process runs a single thread). Only a lockstep run (when_full="wait")
    may write in its own process."""
    with pytest.raises(ValueError, match="lockstep"):
        Recorder(log, COLS, attrs={}, writer="inline")
    # compared as sets of ids: a thread an earlier test left behind may end meanwhile
    threads = {t.ident for t in threading.enumerate()}
    tasks = set(os.listdir(f"/proc/{os.getpid()}/task"))

    def new_threads() -> tuple[list, set]:
        return ([t.name for t in threading.enumerate() if t.ident not in threads],
                set(os.listdir(f"/proc/{os.getpid()}/task")) - tasks)

    rec = Recorder(log, COLS, attrs={}, buffer_cycles=64, flush_s=0.05)
    rec.open()
    assert new_threads() == ([], set())
    assert rec.process.pid != os.getpid() and rec.process.poll() is None
    for i in range(40):
        assert rec.append(row(i))
    rec.event(0.1, "state", message="x")
    wait_for(lambda: rec.rows_written == 40)
    assert new_threads() == ([], set())               # recording: still none
    rec.close()                                       # the rest, events, flush, attributes
    assert rec.process.poll() == 0
    d = read_log(log)
    np.testing.assert_array_equal(d["columns"]["y"], [row(i)[3] for i in range(40)])
    assert list(d["events"]["message"]) == ["x"] and d["attrs"]["rows_written"] == 40

def test_open_errors_name_the_recorder(tmp_path, log):
    log.write_bytes(b"precious")
    rec = Recorder(log, COLS, attrs={})
    with pytest.raises(DeviceInitError, match=f"recorder {log}.*exists") as e:
        rec.open()
    assert e.value.__cause__ is not None
    assert log.read_bytes() == b"precious"        # never overwritten
    bad = tmp_path / "no" / "such" / "dir" / "run.h5"
    with pytest.raises(DeviceInitError, match=f"recorder {bad}: cannot create") as e:
        Recorder(bad, COLS, attrs={}).open()
    assert isinstance(e.value.__cause__, OSError)


def test_input_validation(log):
    with pytest.raises(ValueError, match="duplicate"):
        Recorder(log, ["t", "y", "t"], attrs={})
    with pytest.raises(ValueError, match="invalid column"):
        Recorder(log, ["t", "a/b"], attrs={})
    with pytest.raises(ValueError, match="reserved"):
        Recorder(log, ["t"], attrs={"columns": "x"})
    with pytest.raises(ValueError, match="writer"):   # a process of its own, or inline (lockstep)
        Recorder(log, ["t"], attrs={}, writer="thread")
    rec = Recorder(log, COLS, attrs={})
    assert rec.append(row(0)) is False and rec.healthy   # refused before open, not a fault
    rec.open()
    with pytest.raises(ValueError, match="expected 9 numbers"):
        rec.append((1.0, 2.0))
    with pytest.raises(ValueError, match="expected 9 numbers"):
        rec.append((None,) + row(0)[1:])
    assert rec.pending == 0                       # a bad row is not half-published
    rec.close()
    rec.close()                                   # idempotent
    assert rec.append(row(0)) is False and rec.healthy   # refused after close, not a fault
    assert read_log(log)["rows"] == 0


def test_flushed_at_least_every_flush_s(log):
    assert Recorder(log, COLS, attrs={}, flush_s=5.0).flush_period == 1.0   # "at least once a second"
    rec = Recorder(log, COLS, attrs={}, flush_s=0.1)
    rec.open()
    stamps = []
    flushed = 0
    t_end = time.monotonic() + 2.0
    i = 0
    while time.monotonic() < t_end:                # a 200 Hz loop, watching what is durable
        rec.append(row(i))
        i += 1
        time.sleep(0.005)
        if rec.rows_flushed > flushed:
            flushed = rec.rows_flushed
            stamps.append(time.monotonic())
    rec.close()
    gaps = np.diff(stamps)
    # flush_s = 0.1 gives ~16 flushes in 2 s; flushing only at the 1 s maximum period would
    # give 2, only when a batch (1024 rows) is full none (at most 400 rows arrive)
    assert len(stamps) >= 6, stamps
    # the typical gap: period + wake-up granularity (+ fsync), far from the 1 s maximum
    assert np.median(gaps) < 0.1 + 2 * sidecar._POLL_S + 0.1, gaps
    # every gap: the same + slack for fsync on a CI disk and a stall of the loaded machine
    # (either process; 0.5 s stalls were seen beside the other session's tests), still
    # below the 1 s maximum period
    assert gaps.max() < 0.1 + 2 * sidecar._POLL_S + 0.7, gaps

READER = textwrap.dedent("""
    import sys, h5py
    with h5py.File(sys.argv[1], "r", locking=False) as f:
        t = f["/cycles/t"][()]
    print(len(t), t[-1] if len(t) else -1)
""")


def test_live_reader_sees_data_within_a_second(log):
    """Another process opening the log while it is being recorded reads every flushed row.
    (That a flush comes within flush_s, at most a second: test_flushed_at_least_every_flush_s.)"""
    rec = Recorder(log, COLS, attrs={})           # default flush_s = 0.5
    rec.open()
    try:
        feed(rec, 0, 500)                          # under a batch (1024 rows): the timed flush writes them
        wait_for(lambda: rec.rows_flushed == 500, timeout=5.0)
        out = subprocess.run([sys.executable, "-c", READER, str(log)], capture_output=True,
                             text=True, timeout=20, cwd=ROOT)
        assert out.returncode == 0, out.stderr
        n, last = out.stdout.split()
        assert int(n) == 500 and float(last) == row(499)[0]
    finally:
        rec.close()


WRITER = textwrap.dedent("""
    import sys, time
    from rig_runtime.recorder import Recorder
    cols = ["t", "y"]
    rec = Recorder(sys.argv[1], cols, attrs={"h": 0.005}, flush_s=0.1)
    rec.open()
    print("sidecar", rec.process.pid, flush=True)
    i = 0
    while True:
        for _ in range(20):
            rec.append((i * 0.005, i * 2.0)); i += 1
        print(rec.rows_flushed, i, flush=True)
        time.sleep(0.01)
""")


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[1][0] == "Z"          # a zombie waiting for its reaper
    except FileNotFoundError:
        return True


def test_killed_process_leaves_every_published_row(log):
    """SIGKILL of the recording process: the sidecar notices, records it as an event and
    closes the log holding every row appended before the kill; then it exits."""
    p = subprocess.Popen([sys.executable, "-c", WRITER, str(log)], stdout=subprocess.PIPE,
                         text=True, cwd=ROOT)
    try:
        kind, pid = p.stdout.readline().split()
        assert kind == "sidecar"
        flushed = appended = 0
        deadline = time.monotonic() + 15
        while flushed < 2000:
            line = p.stdout.readline()
            assert line, "writer process ended"
            flushed, appended = map(int, line.split())
            assert time.monotonic() < deadline
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(10)
    wait_for(lambda: _gone(int(pid)), timeout=15)   # the sidecar closed the log and left
    d = read_log(log)
    n = d["rows"]
    assert n >= appended                           # every row published before the kill
    np.testing.assert_array_equal(d["columns"]["y"], np.arange(n) * 2.0)
    assert "recorder_closed" in d["attrs"]
    ev = d["events"]
    assert list(ev["kind"]) == ["recorder"] and "without closing the log" in ev["message"][0]
    assert ev["t"][0] == d["columns"]["t"][-1]


def test_csv_export(log, tmp_path):
    rec = Recorder(log, ["t", "y", "state"], attrs={})
    rec.open()
    rec.append((0.0, 0.001, 1))
    rec.append((0.005, math.nan, 2))
    rec.append((0.01, -math.inf, 2))
    rec.event(0.005, "fault", device="laser b_f", check="nan", message='value "NaN", sensor off')
    rec.close()
    out = tmp_path / "run.csv"
    assert to_csv(log, out) == 3
    assert out.read_text().splitlines() == ["t [s],y [m],state", "0.0,0.001,ARMED", "0.005,NaN,RUNNING", "0.01,-Inf,RUNNING"]
    ev = events_path_for(out)
    assert ev.name == "run.csv.events.csv"
    assert ev.read_text().splitlines() == [
        "t,kind,device,check,value,limit,message",
        '0.005,fault,laser b_f,nan,NaN,NaN,"value ""NaN"", sensor off"',
    ]
    back = np.genfromtxt(out, delimiter=",", names=True)      # numpy names "y [m]" y_m
    assert back["y_m"][0] == 0.001 and math.isnan(back["y_m"][1])


def test_when_full_wait_loses_nothing(log):
    """``when_full="wait"`` (lockstep runs): a stalled sidecar makes ``append`` wait for
    room instead of dropping; every row arrives and the recorder stays healthy."""
    with pytest.raises(ValueError, match="when_full"):
        Recorder(log, COLS, attrs={}, when_full="block")
    rec = Recorder(log, COLS, attrs={}, buffer_cycles=64, when_full="wait")
    rec.open()
    os.kill(rec.process.pid, signal.SIGSTOP)
    threading.Timer(0.3, os.kill, (rec.process.pid, signal.SIGCONT)).start()
    assert all(rec.append(row(i)) for i in range(200))
    rec.close()
    assert rec.healthy and rec.rows_dropped == 0
    np.testing.assert_array_equal(read_log(log)["columns"]["t"], [row(i)[0] for i in range(200)])


def _rows_and_events(rec: Recorder, n: int) -> None:
    for i in range(n):
        assert rec.append(row(i))
        if i % 50 == 7:
            rec.event(row(i)[0], "operator", device="ctl", check="set", value=float(i), message=f"event {i}")


def test_inline_writer_writes_the_same_log(tmp_path):
    """``writer="inline"`` (a lockstep run: no process per run) drives the same sidecar code in
    this process: the same columns, rows and events as the sidecar process writes, also when
    the ring fills many times over (it drains then) and when the event ring fills."""
    a, b = tmp_path / "sidecar.h5", tmp_path / "inline.h5"
    for path, writer in ((a, "sidecar"), (b, "inline")):
        rec = Recorder(path, COLS, attrs=ATTRS, buffer_cycles=64, event_capacity=2, when_full="wait",
                       writer=writer)
        rec.open()
        assert (rec.process is None) == (writer == "inline")
        _rows_and_events(rec, 1000)
        assert rec.close() is True
        assert rec.healthy and rec.rows_written == 1000 and rec.rows_dropped == rec.events_dropped == 0
    da, db = read_log(a), read_log(b)
    assert list(da["columns"]) == list(db["columns"]) == list(COLS)
    for c in COLS:
        np.testing.assert_array_equal(da["columns"][c], db["columns"][c])
    assert len(da["events"]["t"]) == 20
    for k in da["events"]:
        np.testing.assert_array_equal(np.asarray(da["events"][k]), np.asarray(db["events"][k]), err_msg=k)
    assert db["attrs"]["recorder_closed"] and db["attrs"]["recorder_error"] == ""


def test_inline_writer_refuses_what_it_cannot_do(tmp_path, log):
    with pytest.raises(ValueError, match="inline"):
        Recorder(log, COLS, attrs={}, writer="inline")                       # a real-time run drops, never waits
    with pytest.raises(ValueError, match="inline"):
        Recorder(log, COLS, attrs={}, when_full="wait", writer="inline",
                 outputs=[("rig_runtime.app.telemetry:UdpTelemetry", {})])      # live outputs need the process
    with pytest.raises(ValueError, match="writer"):
        Recorder(log, COLS, attrs={}, writer="thread")
    log.write_bytes(b"")
    rec = Recorder(log, COLS, attrs={}, when_full="wait", writer="inline")
    with pytest.raises(DeviceInitError, match="recorder"):
        rec.open()                                                           # never overwrites a log
    assert log.read_bytes() == b""


def test_close_with_a_bound_leaves_a_stalled_sidecar_to_close_the_log(log):
    """Shutdown with a bound (issue 29): a sidecar that cannot finish (stopped here, as by a
    disk that does not answer) is left running, not killed; once it runs again it closes the
    log with every row it took."""
    rec = Recorder(log, COLS, attrs={}, buffer_cycles=64)
    rec.open()
    for i in range(40):
        assert rec.append(row(i))
    wait_for(lambda: rec.pending == 0)
    pid = rec.process.pid
    os.kill(pid, signal.SIGSTOP)
    try:
        assert rec.close(timeout=0.2) is False
        assert "did not close the log within 0.2 s" in rec.left_running and str(pid) in rec.left_running
        assert rec.process.poll() is None                   # left running, not stopped
    finally:
        os.kill(pid, signal.SIGCONT)
    rec.process.wait(15)
    assert rec.process.returncode == 0
    d = read_log(log)
    np.testing.assert_array_equal(d["columns"]["t"], [row(i)[0] for i in range(40)])
    assert d["attrs"]["recorder_closed"]
