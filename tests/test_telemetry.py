"""UDP telemetry output: datagrams as PlotJuggler's UDP server (JSON parser) reads them."""

from __future__ import annotations

import errno
import importlib.util
import json
import math
import platform
import socket
import subprocess
import sys
from dataclasses import dataclass, field

import numpy as np
import pytest

from rig_runtime.app import telemetry
from rig_runtime.app.telemetry import MAX_DATAGRAM, RowSignals, UdpTelemetry, parse_udp_url
from rig_runtime.config import LASER_ROLES, WHEELS
from rig_runtime.devices import FT_COMPONENTS
from rig_runtime.errors import ConfigError
from rig_runtime.control import PIPDLaw
from rig_runtime.loop import CYCLE_FIELDS, MEASUREMENT_FIELDS
from rig_runtime.safety import State

RECV_TIMEOUT_S = 2.0


@dataclass(frozen=True)
class LogInfo:
    """Stand-in for rig_runtime.sidecar.LogInfo (same fields) until the sidecar lands."""

    path: str
    columns: tuple[str, ...]
    attrs: dict = field(default_factory=dict)


def columns(controlled=("rear",), ft=("ft_rl", "ft_rr")) -> tuple[str, ...]:
    """A row layout as rig_runtime.loop.row_spec builds it."""
    cols = list(CYCLE_FIELDS)
    for r in LASER_ROLES:
        cols += [r, f"{r}_age"]
    for w in WHEELS:
        cols += [f"omega_{w}", f"omega_{w}_age"]
    cols += [f"{n}_{c}" for n in ft for c in FT_COMPONENTS]
    cols += list(MEASUREMENT_FIELDS)
    for c in controlled:
        cols += [f"{c}_{f}" for f in PIPDLaw.SIGNALS] + [f"{c}_u_cmd", f"{c}_u_lim"]
    cols += [f"i_{w}" for w in WHEELS]
    return tuple(cols)


def make_rows(cols, n, t0=100.0, h=0.005, state=State.RUNNING) -> np.ndarray:
    """n rows where every column holds a distinct value derived from its index and row."""
    block = np.empty((n, len(cols)))
    for j in range(len(cols)):
        block[:, j] = (j + 1) * 1e-3 + np.arange(n) * 1e-6
    ix = {c: j for j, c in enumerate(cols)}
    block[:, ix["t"]] = t0 + np.arange(n) * h
    block[:, ix["t_run"]] = np.arange(n) * h
    block[:, ix["state"]] = float(state)
    return block


STATUS = {
    "t": 101.0, "t_run": 1.0, "duration_s": 10.0, "state": "RUNNING", "controlled": ["rear"],
    "faults": [],
    "devices": [{"name": "b_f", "kind": "laser", "state": "fresh", "cause": "", "value": 0.1, "age_s": 0.0021,
                 "bad_frames": 3},                       # as rig_runtime.app.live.snapshot gives it
                {"name": "rl", "kind": "wheel", "state": "stale", "cause": "no sample", "bad_frames": 0,
                 "timeouts": 7, "errors": 2}],
    "counters": {"lasers": {"frames": 1000, "bad": 3}},
    "timing": {"cycles": 200, "lateness_us": {"last": 5.0, "p50": 4.0, "p99": 30.0, "max": 80.0},
               "work_us": {"last": 50.0, "p50": 45.0, "p99": 90.0, "max": 300.0},
               "deadline_misses": 2, "skipped_periods": 1},
    "recorder": {"rows": 200, "healthy": True, "error": ""},
}


@pytest.fixture
def receiver():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(RECV_TIMEOUT_S)
    yield s
    s.close()


def receive(sock, n) -> list[bytes]:
    out = []
    for i in range(n):
        try:
            out.append(sock.recv(65536))
        except socket.timeout:
            pytest.fail(f"datagram {i + 1} of {n} not received within {RECV_TIMEOUT_S} s "
                        f"on 127.0.0.1:{sock.getsockname()[1]}")
    return out


def test_datagrams_carry_timestamp_and_nested_fields(receiver):
    cols = columns()
    ix = {c: j for j, c in enumerate(cols)}
    out = UdpTelemetry(LogInfo("run.h5", cols), port=receiver.getsockname()[1])
    out.status(STATUS)
    block = make_rows(cols, 5)
    block[2, ix["y_f"]] = math.nan                    # a missing value is left out, not sent as NaN
    out.rows(block)
    out.close()
    raw = receive(receiver, 5)
    assert out.sent == 5 and out.send_errors == 0
    for k, d in enumerate(raw):
        assert len(d) <= MAX_DATAGRAM
        msg = json.loads(d)                            # strict JSON: NaN would not parse in PlotJuggler
        row = block[k]
        assert isinstance(msg["timestamp"], float) and msg["timestamp"] == row[ix["t"]]
        assert msg["state"] == {"code": 2, "name": "RUNNING"}
        assert msg["rear"]["y"] == row[ix["y_r"]]
        assert msg["rear"]["psi"] == row[ix["psi_ar"]]
        assert msg["rear"]["dpsi"] == row[ix["rear_de_psi"]]
        assert msg["rear"]["delta_omega"] == row[ix["dw_r"]]
        assert msg["rear"]["u"] == row[ix["rear_u_cmd"]]
        assert msg["rear"]["y_ref"] == row[ix["y_ref"]]
        assert "u" not in msg["front"] and "dpsi" not in msg["front"]    # front not controlled
        assert msg["front"]["delta_omega"] == row[ix["dw_f"]]
        assert msg["currents"] == {w: row[ix[f"i_{w}"]] for w in WHEELS}
        assert msg["timing"] == {"lateness": row[ix["lateness"]], "work": row[ix["work"]]}
        assert msg["devices"]["b_f"] == {"state": 0, "bad_frames": 3}
        assert msg["devices"]["rl"]["state"] == 1 and msg["devices"]["rl"]["timeouts"] == 7
        assert msg["health"] == {"deadline_misses": 2, "skipped_periods": 1, "recorder_healthy": 1}
        assert msg["counters"]["lasers"]["frames"] == 1000
    assert "y" not in json.loads(raw[2])["front"]
    assert "y" in json.loads(raw[1])["front"]


def test_every_nth_row_across_blocks(receiver):
    cols = columns()
    out = UdpTelemetry(LogInfo("run.h5", cols), port=receiver.getsockname()[1], every=3)
    block = make_rows(cols, 10)
    out.rows(block[:4])                                # rows 0..3 -> 0, 3
    out.rows(block[4:5])                               # row 4 -> none
    out.rows(block[5:])                                # rows 5..9 -> 6, 9
    raw = receive(receiver, 4)
    out.close()
    assert [json.loads(d)["timestamp"] for d in raw] == [block[k, 0] for k in (0, 3, 6, 9)]
    assert out.sent == 4


def test_oversized_status_is_shortened_never_exceeds_limit(receiver):
    cols = columns(controlled=("front", "rear"))
    out = UdpTelemetry(LogInfo("run.h5", cols), port=receiver.getsockname()[1])
    many = dict(STATUS, devices=[dict(STATUS["devices"][0], name=f"laser_number_{k:03d}") for k in range(60)],
                counters={f"driver{k}": {f"counter{j}": 10 ** 12 for j in range(10)} for k in range(10)})
    out.status(many)
    out.rows(make_rows(cols, 1))
    (d,) = receive(receiver, 1)
    out.close()
    assert len(d) <= MAX_DATAGRAM
    msg = json.loads(d)
    assert out.status_dropped == 1
    assert "counters" not in msg                      # lowest priority went first
    assert msg["rear"]["u"] and msg["front"]["u"]     # the signals are kept
    small = UdpTelemetry(LogInfo("run.h5", cols), port=receiver.getsockname()[1])
    small.status(STATUS)
    assert small.status_dropped == 0
    small.close()


def test_size_limit_drops_groups_by_priority_at_build(receiver, monkeypatch):
    cols = columns()
    assert [g.key for g in RowSignals(cols).groups] == ["front", "rear", "timing", "currents"]
    out = UdpTelemetry(LogInfo("run.h5", cols), port=receiver.getsockname()[1])
    assert out.dropped_fields == []
    assert len(out._encode(out.signals.worst_case())) < MAX_DATAGRAM // 2   # room for device health
    out.close()
    limit = 420                                        # too small for every group
    monkeypatch.setattr(telemetry, "MAX_DATAGRAM", limit)
    out = UdpTelemetry(LogInfo("run.h5", cols), port=receiver.getsockname()[1])
    assert out.dropped_fields[:2] == ["currents", "timing"]            # lowest priority first
    out.status(STATUS)
    block = make_rows(cols, 1)
    block[0, 1:] = -2.2250738585072014e-308            # every value at its widest text
    block[0, 0] = 1e300
    out.rows(block)
    (d,) = receive(receiver, 1)
    out.close()
    assert len(d) <= limit and "currents" not in json.loads(d) and "state" in json.loads(d)


def test_send_errors_are_counted_not_raised(receiver, monkeypatch):
    cols = columns()
    out = UdpTelemetry(LogInfo("run.h5", cols), port=receiver.getsockname()[1])

    class Refusing:
        def sendto(self, data, addr):
            raise ConnectionRefusedError(errno.ECONNREFUSED, "Connection refused")

        def close(self):
            pass

    real = out._sock
    out._sock = Refusing()
    out.rows(make_rows(cols, 3))
    assert out.send_errors == 3 and out.sent == 0 and "refused" in out.last_error
    out._sock = real
    out.rows(make_rows(cols, 1))
    receive(receiver, 1)
    out.close()
    assert out.sent == 1


def test_localhost_reaches_an_ipv4_listener(receiver):
    cols = columns()
    out = UdpTelemetry(LogInfo("run.h5", cols), host="localhost", port=receiver.getsockname()[1])
    out.rows(make_rows(cols, 1))
    receive(receiver, 1)
    out.close()


def test_nobody_listening_is_not_an_error():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()                                      # nobody listens on this port now
    cols = columns()
    out = UdpTelemetry(LogInfo("run.h5", cols), port=port)
    out.rows(make_rows(cols, 20))                      # must not raise
    assert out.sent + out.send_errors == 20
    out.close()


@pytest.mark.parametrize("url, host, port", [
    ("udp://127.0.0.1:9870", "127.0.0.1", 9870),
    ("udp://localhost:1", "localhost", 1),
    ("udp://[::1]:9870", "::1", 9870),
])
def test_parse_udp_url(url, host, port):
    assert parse_udp_url(url) == (host, port)


@pytest.mark.parametrize("url, says", [
    ("127.0.0.1:9870", "scheme"),
    ("tcp://127.0.0.1:9870", "scheme"),
    ("udp://127.0.0.1", "port is missing"),
    ("udp://127.0.0.1:0", "port is missing"),
    ("udp://127.0.0.1:99999", "out of range"),
    ("udp://127.0.0.1:abc", "udp://HOST:PORT"),
    ("udp://:9870", "host is missing"),
    ("udp://127.0.0.1:9870/x", "nothing may follow"),
    ("", "udp://HOST:PORT"),
])
def test_parse_udp_url_errors_name_the_option(url, says):
    with pytest.raises(ConfigError) as e:
        parse_udp_url(url)
    text = str(e.value)
    assert text.startswith("--telemetry: expected udp://HOST:PORT") and says in text and "\n" not in text


def test_bad_options_are_config_errors():
    cols = columns()
    with pytest.raises(ConfigError, match="every"):
        UdpTelemetry(LogInfo("run.h5", cols), every=0)
    with pytest.raises(ConfigError, match="port"):
        UdpTelemetry(LogInfo("run.h5", cols), port=70000)
    with pytest.raises(ConfigError, match="host"):
        UdpTelemetry(LogInfo("run.h5", cols), host="no such host.invalid")


# SO_RCVBUFFORCE (not in Python's socket module): Linux, asm-generic value
_SO_RCVBUFFORCE = 33 if sys.platform == "linux" and platform.machine() in ("x86_64", "aarch64") else None


def _large_receive_buffer(sock: socket.socket, size: int) -> int:
    """A lockstep dry run sends its datagrams in a burst (~200 in ~50 ms here): room for all of
    them even while this process is not scheduled. SO_RCVBUF is capped by net.core.rmem_max
    (often 208 KiB); SO_RCVBUFFORCE, where permitted (CAP_NET_ADMIN), is not. The size granted."""
    for opt in (_SO_RCVBUFFORCE, socket.SO_RCVBUF):
        if opt is None:
            continue
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, size)
        except OSError:
            continue
        if sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) >= size:
            break
    return sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)


FIELDS = {("rear", "u"): "rear_u_cmd", ("rear", "y"): "y_r", ("rear", "psi"): "psi_ar",
          ("rear", "dpsi"): "rear_de_psi", ("front", "delta_omega"): "dw_f", ("front", "y"): "y_f",
          ("currents", "rl"): "i_rl", ("timing", "work"): "work"}


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("rig_runtime.app.live") is None,
                    reason="the recording sidecar (rig_runtime.app.live) is not in this tree yet")
def test_dry_run_streams_telemetry(tmp_path, receiver):
    """`rig dry-run --telemetry udp://...`: a plain socket receives the run's cycles."""
    from rig_runtime.app.export import read_log

    port = receiver.getsockname()[1]
    rcvbuf = _large_receive_buffer(receiver, 4 << 20)
    receiver.settimeout(0.2)
    log = tmp_path / "run.h5"
    proc = subprocess.Popen([sys.executable, "-m", "rig_runtime", "dry-run", "--duration", "1", "--log", str(log),
                             "--telemetry", f"udp://127.0.0.1:{port}", "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    raw: list[bytes] = []
    while True:                                   # read while it runs, then what is left
        try:
            raw.append(receiver.recv(65536))
        except socket.timeout:
            if proc.poll() is not None:
                break
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-2000:]
    assert raw, f"no datagram received on 127.0.0.1:{port}; stderr: {err[-500:]}"
    cols = read_log(log)["columns"]
    row_of = {t: k for k, t in enumerate(cols["t"].tolist())}
    states = set()
    law_rows = 0
    for d in raw:
        assert len(d) <= MAX_DATAGRAM
        msg = json.loads(d)
        assert isinstance(msg["timestamp"], float) and msg["timestamp"] in row_of, msg["timestamp"]
        k = row_of[msg["timestamp"]]
        if "state" not in msg:          # the row's second datagram: the law's signals by the law's names
            assert set(msg) == {"timestamp", "rear_law"} and set(msg["rear_law"]) == set(PIPDLaw.SIGNALS), msg
            assert all(v == cols[f"rear_{n}"][k] for n, v in msg["rear_law"].items()), msg
            law_rows += 1
            continue
        assert msg["state"]["code"] == int(cols["state"][k]) == int(State[msg["state"]["name"]])
        for (group, name), column in FIELDS.items():
            v = cols[column][k]
            if math.isnan(v):
                assert name not in msg[group], (group, name, k)      # no sample yet: left out
            else:
                assert msg[group][name] == v, (group, name, k)
        states.add(msg["state"]["name"])
    lost = f"{len(raw)} of {len(cols['t'])} rows received (receive buffer {rcvbuf} bytes)"
    assert "RUNNING" in states and law_rows, lost
    assert any("devices" in json.loads(d) for d in raw), lost      # the status snapshots reached it
