"""Shutdown with a bound (issue 29): `rig run` against `rig sim` with its log on a disk whose
writes block. The recording ring fills, the run faults (recorder fault) and the drives go
off; `rig run` then gives the recorder ``recorder.close_timeout_s`` to close the log, leaves
the recording sidecar to close it when the disk answers, says so in one line and exits 3
within the bound plus 1 s of the fault. Once the disk answers, the sidecar closes the log
readable. A second SIGINT during that wait ends `rig run` at once.

The blocking disk: where this process may (root, loop devices) a real ext4 image mounted on
a loop device and frozen with ``fsfreeze`` — what an operator meets; elsewhere a stub that
makes the recording sidecar's ``fsync`` block while a gate file exists (``sitecustomize``
on the sidecar's PYTHONPATH), which blocks the sidecar at its next flush the same way
(``RIG_TEST_BLOCKING_DISK=stub`` picks the stub everywhere). A frozen filesystem blocks
every writer in uninterruptible sleep: the fixture thaws it whatever the test's outcome, but
a test process killed from outside (a timeout) leaves it frozen — ``fsfreeze -u`` the
``mnt`` under the test's tmp_path then."""

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from rig_runtime.app.export import read_log
from sim_backend.launcher import start_sim_process

from .e2e import REALTIME_CEILINGS, REALTIME_TOLERANCE, config_with, realtime_sim_config

BOUND_S = 1.0                 # recorder.close_timeout_s for these runs
RING_CYCLES = 200             # 1 s at 200 Hz: fills soon after the freeze, not on a stall of the loaded machine before it
WHEELS = ("fl", "fr", "rl", "rr")

_STUB = textwrap.dedent('''
    # tests/test_shutdown_e2e.py: in the recording sidecar only, fsync blocks while the gate exists
    import os, sys, time
    _gate = os.environ.get("RIG_TEST_FSYNC_GATE")
    if _gate and sys.argv[:1] == ["-c"] and len(sys.argv) == 3 and "rig-ring-" in sys.argv[2]:
        _fsync = os.fsync
        def fsync(fd):
            while os.path.exists(_gate):
                time.sleep(0.01)
            return _fsync(fd)
        os.fsync = fsync
''')


class BlockingDisk:
    """A log directory whose writes can be made to block and to answer again."""

    def __init__(self, tmp_path: Path):
        self.tmp = tmp_path
        self.real = False
        self.env = dict(os.environ)
        self.dir = tmp_path / "logs"
        real_ok = os.environ.get("RIG_TEST_BLOCKING_DISK", "") != "stub"      # "stub": the stub even as root
        if real_ok and os.geteuid() == 0 and shutil.which("fsfreeze") and shutil.which("mkfs.ext4"):
            img, mnt = tmp_path / "disk.img", tmp_path / "mnt"
            mnt.mkdir()
            with open(img, "wb") as f:
                f.truncate(96 << 20)                  # > the recorder's 32 MiB free-space margin
            ok = subprocess.run(["mkfs.ext4", "-q", "-F", str(img)], capture_output=True).returncode == 0 and \
                subprocess.run(["mount", "-o", "loop", str(img), str(mnt)], capture_output=True).returncode == 0
            if ok:
                self.real, self.mnt, self.dir = True, mnt, mnt / "logs"
        self.dir.mkdir()
        if not self.real:
            stub = tmp_path / "stub"
            stub.mkdir()
            (stub / "sitecustomize.py").write_text(_STUB)
            self.gate = tmp_path / "gate"
            self.env["PYTHONPATH"] = str(stub) + os.pathsep + self.env.get("PYTHONPATH", "")
            self.env["RIG_TEST_FSYNC_GATE"] = str(self.gate)
        self.frozen = False

    @property
    def kind(self) -> str:
        return "ext4 on a loop device, fsfreeze" if self.real else "stubbed fsync in the sidecar"

    def freeze(self) -> None:
        if self.real:
            subprocess.run(["fsfreeze", "-f", str(self.mnt)], check=True)
        else:
            self.gate.touch()
        self.frozen = True

    def thaw(self) -> None:
        if self.frozen:
            if self.real:
                subprocess.run(["fsfreeze", "-u", str(self.mnt)], check=True)
            else:
                self.gate.unlink()
            self.frozen = False

    def close(self) -> None:
        self.thaw()
        if self.real:
            for _ in range(50):                   # the left sidecar may still hold the file a moment
                if subprocess.run(["umount", str(self.mnt)], capture_output=True).returncode == 0:
                    return
                time.sleep(0.1)
            subprocess.run(["umount", "-l", str(self.mnt)], capture_output=True)


@pytest.fixture
def disk(tmp_path):
    d = BlockingDisk(tmp_path)
    yield d
    d.close()


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("rig-sim")
    with start_sim_process(config=realtime_sim_config(workdir), workdir=workdir) as sp:
        yield sp


def _run_config(sim, tmp_path: Path) -> Path:
    return config_with(sim.config_path, tmp_path / "rig-run.yaml",
                       {**REALTIME_TOLERANCE, "recorder.buffer_cycles": RING_CYCLES,
                        "recorder.close_timeout_s": BOUND_S}, ceilings=REALTIME_CEILINGS)


def _start(sim, tmp_path, disk, *extra):
    log = disk.dir / "run.h5"
    cmd = [sys.executable, "-m", "rig_runtime", "run", "--config", str(_run_config(sim, tmp_path)),
           "--scenario", "single-step", "--log", str(log), "--ctl-socket", str(tmp_path / "ctl.sock"), *extra]
    # stderr to a file: a sidecar left to close the log keeps the runtime's stderr open (its own
    # lines go there) until the disk answers; its stdout it does not hold
    err = open(tmp_path / "stderr.txt", "w+")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, stdin=subprocess.DEVNULL,
                            text=True, env=disk.env)
    proc.err_file = err
    return proc, log


def _communicate(proc, timeout=None) -> tuple[str, str]:
    out, _ = proc.communicate(timeout=timeout)
    proc.err_file.seek(0)
    return out, proc.err_file.read()


def _wait_powered(sim, proc, timeout=30.0) -> None:
    """Until the runtime has the drives enabled with current on the rear carrier."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            out, err = _communicate(proc)
            pytest.fail(f"rig run ended ({proc.returncode}) before it drove the rig\nstdout {out[-3000:]}\nstderr {err[-3000:]}")
        st = sim.status()
        if st["session"]["active"] and abs(st["currents"]["rl"]) > 0.02:
            return
        time.sleep(0.02)
    proc.kill()
    pytest.fail(f"rig run never drove the rig: {_communicate(proc)}")


def _all_off(st) -> bool:
    return all(v == 0.0 for v in st["currents"].values()) and \
        all(d["state"] != "OPERATION ENABLED" for d in st["drives"].values())


def _watch_until_exit(sim, proc, timeout: float) -> tuple[float | None, float]:
    """Poll rig sim's status (the simulated drives' view of the CAN wire) until `rig run`
    exits: when the drives were first seen all off while `rig run` was still running, and when
    it exited (time.monotonic); ``proc.t_left``: when its "did not close the log" line came."""
    t_off = None
    proc.t_left = None
    deadline = time.monotonic() + timeout
    while proc.poll() is None:
        if proc.t_left is None and "did not close the log" in Path(proc.err_file.name).read_text():
            proc.t_left = time.monotonic()
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"rig run did not exit within {timeout} s: {_communicate(proc)}")
        st = sim.status()
        if t_off is None and proc.poll() is None and _all_off(st):
            t_off = st["t"]
        time.sleep(0.005)
    return t_off, time.monotonic()


@pytest.mark.slow
def test_a_blocked_log_disk_does_not_hold_rig_run(sim, tmp_path, disk):
    proc, log = _start(sim, tmp_path, disk, "--json")
    _wait_powered(sim, proc)
    disk.freeze()
    t_freeze = time.monotonic()
    t_off, t_exit = _watch_until_exit(sim, proc, timeout=30.0)
    out, err = _communicate(proc)
    what = f"[{disk.kind}] exit {proc.returncode}\nstdout {out[-2000:]}\nstderr {err[-3000:]}"
    assert proc.returncode == 3, what
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["final_state"] == "FAULT", what
    fault = summary["faults"][0]
    assert fault["device"] == "recorder" and "overflow" in fault["message"], what
    assert summary["ended_by"].startswith("fault: recorder"), what
    assert summary["recorder"]["closed"] is False and "did not close the log" in summary["recorder"]["left_running"]
    assert "stopped_by" not in summary, what
    lines = [ln for ln in err.splitlines() if "did not close the log" in ln]
    assert len(lines) == 1 and "exiting" in lines[0], what
    # the fault is on the loop clock (time.monotonic, like ours): exit within the bound + 1 s
    timeline = {"fault -> exit": t_exit - fault["t"],
                "fault -> drives seen off": (t_off or math.nan) - fault["t"],
                "fault -> 'exiting' line": (proc.t_left or math.nan) - fault["t"]}
    assert t_exit - fault["t"] < BOUND_S + 1.0, (timeline, what)
    assert fault["t"] > t_freeze, what
    # the drives were off before rig run exited (seen at their end of the wire)
    assert t_off is not None and t_off < t_exit, what
    # the disk answers again: the left sidecar closes the log, readable, with every row it took
    disk.thaw()
    deadline = time.monotonic() + 20.0
    while True:
        try:
            d = read_log(log)
            if d["attrs"].get("recorder_closed"):
                break
        except Exception:  # noqa: BLE001 - not closed yet
            pass
        assert time.monotonic() < deadline, f"the sidecar did not close the log after the thaw; {what}"
        time.sleep(0.1)
    assert len(d["columns"]["t"]) > 0
    assert "overflow" in d["attrs"]["recorder_error"]


@pytest.mark.slow
def test_a_second_sigint_ends_the_wait_at_once(sim, tmp_path, disk):
    """The operator does not wait for the bound: SIGINT stops the run (ramp, drives off),
    the close waits for the frozen disk, a second SIGINT ends `rig run` at once."""
    proc, log = _start(sim, tmp_path, disk)
    _wait_powered(sim, proc)
    disk.freeze()
    time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    # the ramp (0.5 s) and the devices' close, then the wait for the log: the drives off first
    deadline = time.monotonic() + 10.0
    while not _all_off(sim.status()):
        assert proc.poll() is None and time.monotonic() < deadline, _communicate(proc)
        time.sleep(0.005)
    time.sleep(0.2)
    assert proc.poll() is None, _communicate(proc)              # waiting for the frozen disk
    t_sig = time.monotonic()
    proc.send_signal(signal.SIGINT)
    out, err = _communicate(proc, timeout=10)
    t_exit = time.monotonic()
    what = f"[{disk.kind}] exit {proc.returncode}\nstdout {out[-2000:]}\nstderr {err[-3000:]}"
    assert t_exit - t_sig < 0.5, what
    assert "second SIGINT: exiting now (power stages off)" in err, what
    assert "Traceback" not in err, what
    # the first SIGINT ended a run that was RUNNING: its exit code (0), or 3 if the ring filled
    # and the recorder faulted first
    assert proc.returncode in (0, 3), what
    disk.thaw()
