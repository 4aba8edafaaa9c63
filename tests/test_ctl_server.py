"""The control socket and `rig ctl` against a CtlServer on a tmp socket, with a real
ControlLoop (fake devices, real-time clock) in a thread taking the commands from the
mailbox, as the runtime process would; the loop's events and status reach the server as
the sidecar would pass them."""

from __future__ import annotations

import dataclasses
import json
import os
import stat
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from rig_runtime import schema
from rig_runtime.app import cli
from rig_runtime.app.ctl_server import CtlError, CtlServer, default_ctl_path, request
from rig_runtime.clock import LockstepClock
from rig_runtime.loop import ControlLoop, log_columns
from rig_runtime.mailbox import SIZE, Mailbox
from rig_runtime.safety import State

from .test_ctl_loop import FakeDevices, MemRecorder


@dataclasses.dataclass(frozen=True)
class Info:                     # the fields of rig_runtime.sidecar.LogInfo the server reads
    path: str
    columns: tuple
    attrs: dict


class Forward(MemRecorder):
    """The loop's recorder: rows and events go to the server as the sidecar passes them."""

    def __init__(self, server):
        super().__init__()
        self.server = server

    def append(self, row):
        self.server.rows(np.asarray([row]))
        return True

    def event(self, t, kind, device="", check="", value=float("nan"), limit=float("nan"), message=""):
        super().event(t, kind, device, check, value, limit, message)
        self.server.event((t, kind, device, check, value, limit, message))


@pytest.fixture
def live(cfg, tmp_path):
    """A CtlServer at tmp/ctl/ctl.sock and a loop running (RUNNING, y_ref 0) until stopped."""
    buf = bytearray(SIZE)
    # lockstep time, paced by a short sleep per cycle: the loop runs beside the server's
    # thread without deadline misses, whatever the machine's load
    dev = FakeDevices(cfg)
    columns = log_columns(cfg, dev.channels(), dev.extra_columns)
    info = Info(str(tmp_path / "run.h5"), tuple(columns), {"config": json.dumps(schema.to_dict(cfg))})
    server = CtlServer(info, tmp_path / "ctl" / "ctl.sock", Mailbox(memoryview(buf)), timeout_s=5.0)
    rec = Forward(server)
    loop = ControlLoop(cfg, dev, LockstepClock(advance=lambda t: time.sleep(0.0005)), recorder=rec,
                       mailbox=Mailbox(memoryview(buf)))

    def status(lp):
        server.status({"state": lp.supervisor.state.name, "t_run": None, "controlled": list(cfg.controlled),
                       "gains": lp.gains(), "faults": []})

    out = {}
    th = threading.Thread(target=lambda: out.setdefault("result", loop.run(600.0, status=status, status_period_s=0.0)), daemon=True)
    th.start()
    try:
        while loop.supervisor.state is not State.RUNNING and th.is_alive():
            th.join(0.01)
        yield server, loop, rec, out, th
    finally:
        loop.stop_requested = True
        th.join(30)
        server.close()


def rig(capsys, *argv):
    code = cli.main(["ctl", *argv])
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def test_set_status_refusals_and_stop(live, capsys):
    server, loop, rec, out, th = live
    sock = str(server.path)
    assert stat.S_IMODE(os.stat(server.path.parent).st_mode) == 0o700
    assert stat.S_IMODE(os.lstat(server.path).st_mode) == 0o600

    code, o, e = rig(capsys, "--socket", sock, "set", "K_P_y", "4")
    assert (code, o, e) == (0, "K_P_y 3 -> 4\n", "")
    assert loop.gains()["K_P_y"] == 4.0 and server.gains["K_P_y"] == 4.0
    assert ("operator", "controller", "K_P_y", 4.0, 3.0, "K_P_y 3 -> 4") in [ev[1:] for ev in rec.events]

    code, o, e = rig(capsys, "--socket", sock, "status")
    assert code == 0 and "state RUNNING" in o and "K_P_y 4" in o

    refusals = [
        (("set", "K_P_y", "7"), "K_P_y = 7 is outside its bounds [1, 6] (controller.tuning)"),
        (("set", "u_max", "8"), "u_max is a limit: limits cannot be changed while running"),
        (("set", "y_max", "0.1"), "y_max is a limit: limits cannot be changed while running"),
        (("set", "K_Q", "1"), "unknown name 'K_Q'"),
        (("set", "K_P_y", "x"), "set K_P_y: 'x' is not a number"),
        (("reset-fault",), "no latched fault (state RUNNING)"),
    ]
    for argv, text in refusals:
        code, o, e = rig(capsys, "--socket", sock, *argv)
        assert code == 2 and o == "" and e.count("\n") == 1 and e.startswith("rig ctl: error: ") and text in e, (argv, e)

    # a destabilising value: each step within bounds, the last makes the sampled loop unstable
    for name, v in (("K_P_y", "1"), ("K_P_psi", "80")):
        assert rig(capsys, "--socket", sock, "set", name, v)[0] == 0
    code, o, e = rig(capsys, "--socket", sock, "set", "K_I_y", "18")
    assert code == 2 and "K_I_y = 18 would make the sampled closed loop unstable" in e
    assert loop.gains() == {"K_P_y": 1.0, "K_I_y": 9.0, "K_P_psi": 80.0, "K_D_psi": 5.0,
                            "T_f_psi": loop.cfg.controller.pipd.T_f_psi}

    code, o, e = rig(capsys, "--socket", sock, "stop")
    assert code == 0 and o == "stop requested in RUNNING\n"
    th.join(30)
    assert out["result"].final_state == "IDLE"
    assert "RUNNING -> STOPPING: stop requested (rig ctl)" in [ev[6] for ev in rec.events]


def test_json_output(live, capsys):
    server, *_ = live
    code, o, e = rig(capsys, "--socket", str(server.path), "--json", "status")
    ans = json.loads(o)
    assert code == 0 and ans["ok"] and ans["status"]["state"] == "RUNNING" and "rear_u_unsat" in ans["row"]


def test_no_run_listening(tmp_path, capsys):
    p = tmp_path / "nobody.sock"
    code, o, e = rig(capsys, "--socket", str(p), "status")
    assert (code, o, e) == (2, "", f"rig ctl: error: no run is listening at {p}\n")
    r = subprocess.run([sys.executable, "-m", "rig_runtime", "ctl", "--socket", str(p), "stop"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr == f"rig ctl: error: no run is listening at {p}\n"


def info_of(cfg, tmp_path):
    return Info(str(tmp_path / "run.h5"), ("t",), {"config": json.dumps(schema.to_dict(cfg))})


def test_a_live_server_is_not_replaced_and_a_stale_socket_is(cfg, tmp_path):
    path = tmp_path / "ctl" / "ctl.sock"
    a = CtlServer(info_of(cfg, tmp_path), path, None)
    try:
        with pytest.raises(CtlError, match=f"another run is listening at {path}"):
            CtlServer(info_of(cfg, tmp_path), path, None)
        assert request(path, {"cmd": "stop"})["message"].startswith("this run takes no commands")
    finally:
        a.close()
    assert not path.exists()
    import socket
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(path))               # a socket file nobody listens on (a run that was killed)
    s.close()
    b = CtlServer(info_of(cfg, tmp_path), path, None)
    try:
        assert request(path, {"cmd": "status"})["ok"]
    finally:
        b.close()


def test_directory_open_to_others_or_not_a_socket_is_refused(cfg, tmp_path):
    d = tmp_path / "open"
    d.mkdir(mode=0o755)
    os.chmod(d, 0o755)
    with pytest.raises(CtlError, match="open to other users .*0700"):
        CtlServer(info_of(cfg, tmp_path), d / "ctl.sock", None)
    p = tmp_path / "priv"
    p.mkdir(mode=0o700)
    (p / "ctl.sock").write_text("not a socket")
    with pytest.raises(CtlError, match="exists and is not a socket"):
        CtlServer(info_of(cfg, tmp_path), p / "ctl.sock", None)


def test_no_answer_from_the_loop(cfg, tmp_path):
    buf = bytearray(SIZE)
    server = CtlServer(info_of(cfg, tmp_path), tmp_path / "c" / "ctl.sock", Mailbox(memoryview(buf)), timeout_s=0.05)
    try:
        ans = server.handle(json.dumps({"cmd": "set", "name": "K_P_y", "value": 4.0}))
        assert not ans["ok"] and "did not answer within 0.05 s" in ans["message"]
        ans = server.handle(json.dumps({"cmd": "set", "name": "K_I_y", "value": 10.0}))
        assert not ans["ok"] and "an earlier change (K_P_y 3 -> 4) got no answer" in ans["message"]
        # the loop applied it after all: its operator event settles what is in force
        server.event((1.0, "operator", "controller", "K_P_y", 4.0, 3.0, "K_P_y 3 -> 4"))
        assert server.gains["K_P_y"] == 4.0
        loop_side = Mailbox(memoryview(buf))
        loop_side.take()

        def answer():
            while True:
                c = loop_side.take()
                if c is not None:
                    loop_side.answer(c.seq, True, f"{c.name} -> {c.value:g}")
                    return

        th = threading.Thread(target=answer)
        th.start()
        server.timeout_s = 5.0
        ans = server.handle(json.dumps({"cmd": "set", "name": "K_I_y", "value": 10.0}))
        th.join()
        assert ans == {"ok": True, "message": "K_I_y -> 10"}
    finally:
        server.close()


@pytest.mark.parametrize("line, text", [
    (b"{bad", "request is not JSON"), (b"[1]", "not a JSON object"), (b'{"cmd": "format"}', "unknown command 'format'"),
    (b'{"cmd": "set", "value": 1}', "set needs a gain name"),
])
def test_malformed_requests(cfg, tmp_path, line, text):
    server = CtlServer(info_of(cfg, tmp_path), tmp_path / "c" / "ctl.sock", None)
    try:
        ans = server.handle(line)
        assert not ans["ok"] and text in ans["message"]
    finally:
        server.close()


def test_default_path(monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/run/user/1000")
    assert str(default_ctl_path()) == "/run/user/1000/rig-runtime/ctl.sock"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert str(default_ctl_path()) == f"/tmp/rig-runtime-{os.getuid()}/ctl.sock"


def test_status_with_numpy_values_and_nan(cfg, tmp_path):
    server = CtlServer(info_of(cfg, tmp_path), tmp_path / "c" / "ctl.sock", None)
    try:
        server.status({"state": "RUNNING", "timing": {"cycles": np.int64(7)}, "t_run": float("nan")})
        server.rows(np.array([[1.5], [2.5]]))
        ans = request(server.path, {"cmd": "status"})
        assert ans["status"] == {"state": "RUNNING", "timing": {"cycles": 7}, "t_run": None}
        assert ans["row"] == {"t": 2.5}
    finally:
        server.close()


def test_an_idle_client_does_not_hold_off_a_stop(cfg, tmp_path):
    """One request per connection, read within a second: a client that connects and says
    nothing (or keeps the connection for a second request) does not block the next one."""
    import socket as _socket
    from rig_runtime.app import ctl_server
    buf = bytearray(SIZE)
    loop_side = Mailbox(memoryview(buf))
    server = CtlServer(info_of(cfg, tmp_path), tmp_path / "i" / "ctl.sock", Mailbox(memoryview(buf)), timeout_s=5.0)
    answered = threading.Event()

    def loop():                             # the control loop's side: answer what arrives
        while not answered.is_set():
            cmd = loop_side.take()
            if cmd is not None:
                loop_side.answer(cmd.seq, True, "stop requested in RUNNING")
            time.sleep(0.001)

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    idle = _socket.socket(_socket.AF_UNIX, _socket.SOCK_STREAM)
    try:
        idle.connect(str(server.path))                      # connects, sends nothing
        ans = request(server.path, {"cmd": "stop"}, timeout_s=ctl_server.REQUEST_READ_S + 3.0)   # < the 10 s an idle client held it before
        assert ans["ok"] and ans["message"] == "stop requested in RUNNING"
        two = _socket.socket(_socket.AF_UNIX, _socket.SOCK_STREAM)
        with two:
            two.connect(str(server.path))
            two.sendall(b'{"cmd": "stop"}\n{"cmd": "stop"}\n')
            f = two.makefile("rb")
            assert json.loads(f.readline())["ok"]
            assert f.readline() == b""                      # one answer, then the server closed
    finally:
        answered.set()
        idle.close()
        server.close()
