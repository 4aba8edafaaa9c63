"""Foxglove output: a WebSocket client sees the advertised channels and the rows; a log
exports to an MCAP file with the same topics. Skipped without the foxglove extra."""

from __future__ import annotations

import importlib.util
import json
import math
import struct
import sys
import time

import h5py
import numpy as np
import pytest

from rig_runtime.errors import ConfigError
from tests.test_telemetry import STATUS, LogInfo, columns, make_rows

from rig_runtime.app.foxglove_out import FoxgloveServer, export_mcap, parse_address

needs_sdk = pytest.mark.skipif(importlib.util.find_spec("foxglove") is None,
                               reason="foxglove-sdk not installed (the foxglove extra)")

RECV_TIMEOUT_S = 2.0
SUBSCRIBE_TIMEOUT_S = 15.0                # a guard: the messages usually flow within ~0.1 s
SUBPROTOCOL = "foxglove.sdk.v1"           # what foxglove-sdk's server speaks (successor of foxglove.websocket.v1)
ROW_TOPICS = {"/rig/state", "/rig/front", "/rig/rear", "/rig/timing", "/rig/currents"}
ALL_TOPICS = ROW_TOPICS | {"/rig/health", "/rig/events"}


def recv_json(ws, op: str) -> dict:
    """The next text message with this op (others skipped)."""
    for _ in range(50):
        try:
            m = ws.recv(timeout=RECV_TIMEOUT_S)
        except TimeoutError:
            pytest.fail(f"no '{op}' message from the Foxglove server within {RECV_TIMEOUT_S} s")
        if isinstance(m, str) and json.loads(m).get("op") == op:
            return json.loads(m)
    pytest.fail(f"no '{op}' message among the first 50")


@needs_sdk
def test_websocket_client_sees_channels_and_rows():
    ws_client = pytest.importorskip("websockets.sync.client", reason="websockets not installed")
    cols = columns()
    ix = {c: j for j, c in enumerate(cols)}
    out = FoxgloveServer(LogInfo("run.h5", cols), port=0)
    try:
        assert out.port > 0
        uri = f"ws://127.0.0.1:{out.port}"
        with ws_client.connect(uri, subprotocols=[SUBPROTOCOL, "foxglove.websocket.v1"],
                               open_timeout=RECV_TIMEOUT_S) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            assert recv_json(ws, "serverInfo")["name"] == "rig-runtime"
            channels = {c["topic"]: c for c in recv_json(ws, "advertise")["channels"]}
            assert ALL_TOPICS <= set(channels), sorted(channels)
            rear = channels["/rig/rear"]
            assert rear["encoding"] == "json" and rear["schemaEncoding"] == "jsonschema"
            props = json.loads(rear["schema"])["properties"]
            assert {"timestamp", "y", "psi", "dpsi", "delta_omega", "u"} <= set(props)
            assert channels["/rig/events"]["schemaName"] == "foxglove.Log"
            subs = {1: "/rig/rear", 2: "/rig/state", 3: "/rig/health"}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": channels[topic]["id"]} for i, topic in subs.items()]}))
            # the subscription takes effect asynchronously: feed rows until messages arrive
            got: dict[int, dict] = {}
            block = make_rows(cols, 1)
            deadline = time.monotonic() + SUBSCRIBE_TIMEOUT_S
            k = -1
            while time.monotonic() < deadline:
                k += 1
                block[0, ix["t"]] = 100.0 + k * 0.005
                out.rows(block)
                out.status(dict(STATUS, t=100.0 + k * 0.005))
                try:
                    m = ws.recv(timeout=0.01)
                except TimeoutError:
                    continue
                if isinstance(m, bytes):
                    assert m[0] == 0x01                     # MessageData
                    sub, log_time = struct.unpack_from("<IQ", m, 1)
                    msg = json.loads(m[13:])
                    assert log_time == round(msg["timestamp"] * 1e9)
                    got[sub] = msg
                if len(got) == len(subs):
                    break
            assert set(got) == set(subs), \
                f"within {SUBSCRIBE_TIMEOUT_S} s, messages only for subscriptions {sorted(got)} of {sorted(subs)}"
            assert got[1]["y"] == block[0, ix["y_r"]] and got[1]["u"] == block[0, ix["rear_u_cmd"]]
            assert got[2]["name"] == "RUNNING" and got[2]["code"] == 2
            assert got[3]["devices"]["rl"]["state"] == 1
    finally:
        out.close()


def write_log(path, cols, block, events):
    """A log in the documented layout (docs/log-format.md)."""
    with h5py.File(path, "w") as f:
        f.attrs["columns"] = list(cols)
        f.attrs["log_format"] = "rig-runtime-log"
        f.attrs["log_format_version"] = 1
        g = f.create_group("cycles")
        g.attrs["columns"] = list(cols)
        for j, c in enumerate(cols):
            d = g.create_dataset(c, data=block[:, j])
            d.attrs["index"] = j
        e = f.create_group("events")
        s = h5py.string_dtype("utf-8")
        for k, name in enumerate(("t", "kind", "device", "check", "value", "limit", "message")):
            vals = [ev[k] for ev in events]
            e.create_dataset(name, data=np.array(vals, dtype=object if isinstance(vals[0], str) else np.float64),
                             dtype=s if isinstance(vals[0], str) else np.float64)


@needs_sdk
def test_export_mcap_reads_back(tmp_path):
    reader = pytest.importorskip("mcap.reader", reason="mcap reader not installed")
    cols = columns(controlled=("front", "rear"))
    ix = {c: j for j, c in enumerate(cols)}
    block = make_rows(cols, 300)
    block[10, ix["y_f"]] = math.nan
    events = [(100.5, "state", "", "", math.nan, math.nan, "ARMED -> RUNNING"),
              (101.0, "fault", "laser b_f", "stale", 0.031, 0.02, "ψ sample 31 ms old")]
    log = tmp_path / "run.h5"
    write_log(log, cols, block, events)
    out = tmp_path / "run.mcap"
    assert export_mcap(log, out) == 300
    msgs: dict[str, list] = {}
    with open(out, "rb") as fh:
        r = reader.make_reader(fh)
        summary = r.get_summary()
        topics = {c.topic for c in summary.channels.values()}
        assert ALL_TOPICS - {"/rig/health"} <= topics      # a log has no status snapshots
        for schema, channel, message in r.iter_messages(log_time_order=True):
            msgs.setdefault(channel.topic, []).append((schema, channel, message))
    assert all(len(msgs[t]) == 300 for t in ROW_TOPICS), {t: len(v) for t, v in msgs.items()}
    schema, channel, message = msgs["/rig/front"][10]
    assert channel.message_encoding == "json" and schema.encoding == "jsonschema" and schema.name == "rig.Front"
    front = json.loads(message.data)
    assert "y" not in front and front["u"] == block[10, ix["front_u_cmd"]]
    assert message.log_time == round(block[10, ix["t"]] * 1e9)
    schema, _, message = msgs["/rig/events"][1]
    assert schema.name == "foxglove.Log" and message.log_time == round(101.0 * 1e9)
    assert "stale" in message.data.decode("utf-8", "replace")
    with pytest.raises(ConfigError, match="does not exist yet"):
        export_mcap(log, out)


@pytest.mark.parametrize("text, expected", [("8765", ("127.0.0.1", 8765)), ("0.0.0.0:9000", ("0.0.0.0", 9000)),
                                            ("[::1]:8765", ("::1", 8765))])
def test_parse_address(text, expected):
    assert parse_address(text) == expected


@pytest.mark.parametrize("text", ["", "x", "127.0.0.1:", ":8765", "127.0.0.1:70000"])
def test_parse_address_errors(text):
    with pytest.raises(ConfigError, match=r"^--foxglove: expected \[HOST:\]PORT"):
        parse_address(text)


@needs_sdk
def test_port_in_use_is_a_config_error():
    cols = columns()
    first = FoxgloveServer(LogInfo("run.h5", cols), port=0)
    try:
        with pytest.raises(ConfigError, match="--foxglove"):
            FoxgloveServer(LogInfo("run.h5", cols), port=first.port)
    finally:
        first.close()


def test_without_the_sdk_a_config_error_says_how_to_install(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "foxglove", None)          # import foxglove -> ImportError
    with pytest.raises(ConfigError, match=r"pip install 'rig-runtime\[foxglove\]'"):
        FoxgloveServer(LogInfo("run.h5", columns()))
    with pytest.raises(ConfigError, match=r"pip install 'rig-runtime\[foxglove\]'"):
        export_mcap(tmp_path / "run.h5", tmp_path / "run.mcap")


@needs_sdk
def test_export_mcap_has_the_law_signals_topic(tmp_path):
    """The law's signals (the log's ``law_signals``) get a topic per controlled carrier,
    ``/rig/<carrier>_law``, with the law's own names as fields."""
    reader = pytest.importorskip("mcap.reader", reason="mcap reader not installed")
    from rig_runtime.control import DecoupledLaw
    from rig_runtime.logformat import LAW_SIGNALS_ATTR
    law = {n: u for n, u in DecoupledLaw.SIGNALS.items() if n != "x_I_psi"}
    cols = columns(controlled=("front", "rear")) + ("front_w", "front_w_cross", "rear_w", "rear_w_cross")
    ix = {c: j for j, c in enumerate(cols)}
    block = make_rows(cols, 20)
    log = tmp_path / "run.h5"
    write_log(log, cols, block, [(100.5, "state", "", "", math.nan, math.nan, "ARMED -> RUNNING")])
    with h5py.File(log, "a") as f:
        f.attrs[LAW_SIGNALS_ATTR] = json.dumps(law)
    out = tmp_path / "run.mcap"
    assert export_mcap(log, out) == 20
    msgs: dict[str, list] = {}
    with open(out, "rb") as fh:
        for schema, channel, message in reader.make_reader(fh).iter_messages(log_time_order=True):
            msgs.setdefault(channel.topic, []).append((schema, message))
    for carrier in ("front", "rear"):
        schema, message = msgs[f"/rig/{carrier}_law"][7]
        assert schema.name == f"rig.{carrier.capitalize()}Law"
        assert list(json.loads(schema.data)["properties"]) == ["timestamp", *law]
        m = json.loads(message.data)
        assert {n: m[n] for n in law} == {n: block[7, ix[f"{carrier}_{n}"]] for n in law}
