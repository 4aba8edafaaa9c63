"""Recorder: lossless round trip, never blocking the loop, failures leave a readable file."""

import errno
import json
import math
import signal
import subprocess
import sys
import textwrap
import threading
import time
import timeit

import h5py
import numpy as np
import pytest

from rig_runtime import recorder as recmod
from rig_runtime.errors import DeviceInitError
from rig_runtime.export import events_path_for, read_log, to_csv
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


def wait_for(cond, timeout: float = 3.0) -> None:
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


def test_append_never_blocks_when_writer_stalls(log, monkeypatch):
    stall = threading.Event()
    real = Recorder._write_pending

    def stalled(self):
        stall.wait(10)                            # the disk "hangs"
        real(self)

    monkeypatch.setattr(Recorder, "_write_pending", stalled)
    rec = Recorder(log, COLS, attrs={}, buffer_cycles=64, event_capacity=4)
    rec.open()
    try:
        for i in range(64):
            assert rec.append(row(i))
        assert rec.healthy
        t0 = time.perf_counter()
        refused = [rec.append(row(i)) for i in range(64, 164)]
        elapsed = time.perf_counter() - t0
        assert refused == [False] * 100
        assert elapsed < 0.5                      # no waiting on the (10 s) stalled writer
        assert not rec.healthy and "overflow" in rec.error and rec.rows_dropped == 100
        for k in range(10):
            rec.event(k, "operator")              # event ring (capacity 4) overflows, never blocks
        assert rec.events_dropped == 6
    finally:
        stall.set()
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
    fail = threading.Event()
    real = Recorder._store_column

    stored = []

    def store(d, start, data):
        if fail.is_set():
            stored.append(d.name)
            if len(stored) == 3:                  # a batch dies half-way: two columns are
                d.id.set_extent((start + len(data),))   # longer already, this one extended
                raise OSError(errno.ENOSPC, "No space left on device")
        real(d, start, data)

    monkeypatch.setattr(Recorder, "_store_column", staticmethod(store))
    rec = Recorder(log, COLS, attrs={"h": 0.005}, buffer_cycles=4096, flush_s=0.05)
    rec.open()
    feed(rec, 0, 300)
    rec.event(0.5, "state", message="before the failure")
    wait_for(lambda: rec.rows_flushed == 300)
    fail.set()
    feed(rec, 300, 400)
    wait_for(lambda: not rec.healthy)
    assert "write failed" in rec.error and "No space left" in rec.error and "row 300" in rec.error
    assert rec.append(row(400)) is False          # refused at once, nothing more is written
    rec.close()
    assert not rec.healthy
    with h5py.File(log, "r") as f:                # a plain reader opens it
        assert f["/cycles/t"].shape == (300,)
    d = read_log(log)
    assert d["rows"] == 300 and all(len(a) == 300 for a in d["columns"].values())
    np.testing.assert_array_equal(d["columns"]["y"], [row(i)[3] for i in range(300)])
    assert list(d["events"]["message"]) == ["before the failure"]


def test_disk_almost_full_stops_cleanly(log, monkeypatch):
    rec = Recorder(log, COLS, attrs={}, flush_s=0.05, min_free_bytes=10 * 2**20)
    rec.open()
    feed(rec, 0, 200)
    wait_for(lambda: rec.rows_flushed == 200)
    real = recmod.shutil.disk_usage
    monkeypatch.setattr(recmod.shutil, "disk_usage",
                        lambda p: real(p)._replace(free=2**20))        # 1 MiB left
    feed(rec, 200, 250)
    wait_for(lambda: not rec.healthy)
    assert "disk almost full" in rec.error
    rec.close()
    d = read_log(log)
    assert d["rows"] == 200
    np.testing.assert_array_equal(d["columns"]["t"], [row(i)[0] for i in range(200)])
    with pytest.raises(DeviceInitError, match="disk almost full"):   # and no new run starts on it
        Recorder(log.with_name("next.h5"), COLS, attrs={}, min_free_bytes=10 * 2**20).open()
    assert not log.with_name("next.h5").exists()


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
    real = recmod.os.fsync
    monkeypatch.setattr(recmod.os, "fsync", lambda fd: (synced.append(fd), real(fd))[1])
    rec = Recorder(log, COLS, attrs={}, flush_s=0.05)
    rec.open()
    feed(rec, 0, 50)
    wait_for(lambda: rec.rows_flushed == 50)
    rec.close()
    assert synced


def test_one_writer_thread_stores_every_batch(log, monkeypatch):
    """One path: a writer thread does all file I/O (the ``writer="inline"`` option is gone)."""
    threads = set()
    real = Recorder._store_column

    def store(d, start, data):
        threads.add(threading.get_ident())
        real(d, start, data)

    monkeypatch.setattr(Recorder, "_store_column", staticmethod(store))
    with pytest.raises(TypeError):
        Recorder(log, COLS, attrs={}, writer="inline")
    n_threads = threading.active_count()
    rec = Recorder(log, COLS, attrs={}, buffer_cycles=64, flush_s=0.05)
    rec.open()
    assert threading.active_count() == n_threads + 1  # the writer thread
    for i in range(40):
        assert rec.append(row(i))
    rec.event(0.1, "state", message="x")
    wait_for(lambda: rec.rows_written == 40)
    rec.close()                                       # the rest, events, flush, attributes
    assert threading.active_count() == n_threads
    assert len(threads) == 1 and threading.get_ident() not in threads
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
    with pytest.raises(TypeError):                # no writer option any more: one writer thread
        Recorder(log, ["t"], attrs={}, writer="thread")
    rec = Recorder(log, COLS, attrs={})
    with pytest.raises(ValueError, match="expected 9 numbers"):
        rec.append((1.0, 2.0))
    with pytest.raises(ValueError, match="expected 9 numbers"):
        rec.append((None,) + row(0)[1:])
    assert rec.pending == 0                       # a bad row is not half-published
    rec.close()                                   # never opened: nothing to do
    assert rec.append(row(0)) is False and rec.healthy   # refused after close, not a fault


def test_flushed_at_least_every_flush_s(log, monkeypatch):
    assert Recorder(log, COLS, attrs={}, flush_s=5.0).flush_period == 1.0   # "at least once a second"
    stamps = []
    real = Recorder._flush

    def counted(self):
        before = self.flushes
        real(self)
        if self.flushes > before:
            stamps.append(time.monotonic())

    monkeypatch.setattr(Recorder, "_flush", counted)
    rec = Recorder(log, COLS, attrs={}, flush_s=0.1)
    rec.open()
    t_end = time.monotonic() + 1.0
    i = 0
    while time.monotonic() < t_end:                # a 200 Hz loop
        rec.append(row(i))
        i += 1
        time.sleep(0.005)
    rec.close()
    gaps = np.diff(stamps)
    assert len(stamps) >= 6, stamps
    assert gaps.max() < 0.1 + 2 * recmod._POLL_S + 0.15, gaps   # period + wake-up granularity + load slack


READER = textwrap.dedent("""
    import sys, h5py
    with h5py.File(sys.argv[1], "r", locking=False) as f:
        t = f["/cycles/t"][()]
    print(len(t), t[-1] if len(t) else -1)
""")


def test_live_reader_sees_data_within_a_second(log):
    rec = Recorder(log, COLS, attrs={})           # default flush_s = 0.5
    rec.open()
    try:
        feed(rec, 0, 500)
        time.sleep(1.0)
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
    i = 0
    while True:
        for _ in range(20):
            rec.append((i * 0.005, i * 2.0)); i += 1
        time.sleep(0.01)
        print(rec.rows_flushed, flush=True)
""")


def test_killed_process_leaves_flushed_rows(log):
    p = subprocess.Popen([sys.executable, "-c", WRITER, str(log)], stdout=subprocess.PIPE,
                         text=True, cwd=ROOT)
    try:
        flushed = 0
        deadline = time.monotonic() + 15
        while flushed < 2000:
            line = p.stdout.readline()
            assert line, "writer process ended"
            flushed = int(line)
            assert time.monotonic() < deadline
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(10)
    d = read_log(log)                              # no close, no atexit: killed
    n = d["rows"]
    assert n >= flushed
    np.testing.assert_array_equal(d["columns"]["y"], np.arange(n) * 2.0)
    assert "recorder_closed" not in d["attrs"]    # tells a killed run from a closed one


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


def test_append_cost(log):
    cols = [f"c{i}" for i in range(24)]            # about the runtime's row width
    rec = Recorder(log, cols, attrs={}, buffer_cycles=1 << 18)
    rec.open()
    r = tuple(float(i) for i in range(24))
    n = 20_000
    per_call = min(timeit.repeat(lambda: rec.append(r), number=n, repeat=5)) / n
    rec.close()
    print(f"\nRecorder.append, 24 columns: {per_call * 1e6:.2f} µs/call")
    assert rec.healthy and rec.rows_written == 5 * n
    assert per_call < 10e-6                       # a few µs at most (≈0.5 µs measured)
