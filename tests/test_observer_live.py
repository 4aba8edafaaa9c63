"""DEGRADED in the live views: the panel's header, carrier table and the why line, and the
UDP telemetry's (and so Foxglove's) carrier fields ``y_hat`` and ``degraded`` — rendered and
sent from rows with the observer's columns (as ``loop.log_columns`` lays them out)."""

from __future__ import annotations

import json

import pytest

from rig_runtime.app.panel import render
from rig_runtime.app.telemetry import MAX_DATAGRAM, UdpTelemetry
from rig_runtime.observer import LOG_FIELDS
from tests.test_panel import text_of
from tests.test_telemetry import STATUS, LogInfo, columns, make_rows, receive, receiver  # noqa: F401

WHY = ("DEGRADED: b_r stale (no valid value for 25 ms); rear carrier(s) on the observer's estimate, "
       "u_max 2.5 A, y_max 5 mm, at most 15 s")


def _cols(controlled=("rear",)):
    return columns(controlled=controlled) + tuple(f"{c}_obs_{f}" for c in controlled for f in LOG_FIELDS)


def _row(cols, **values):
    block = make_rows(cols, 1)
    row = dict(zip(cols, block[0].tolist()))
    row.update(values)
    return row


def test_panel_shows_the_degraded_carrier_and_why():
    cols = _cols()
    row = _row(cols, rear_obs_degraded=1.0, rear_obs_y_hat=0.00123, y_r=0.0021)
    events = [(10.0, "state", "", "", 0.0, 0.0, "ARMED -> RUNNING"), (18.0, "degraded", "", "", 0.0, 0.0, WHY)]
    out = text_of(render(row, STATUS, events), width=200)
    head = out.splitlines()[0]
    assert "RUNNING" in head and "DEGRADED: rear on ŷ" in head
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("rear"))
    assert "1.23" in line and "2.10" in line and "ŷ DEGRADED" in line
    assert any(ln.startswith("DEGRADED (rear on the observer's estimate): " + WHY[:40]) for ln in out.splitlines())


def test_panel_without_degradation_says_the_lane_is_on_y():
    cols = _cols()
    out = text_of(render(_row(cols, rear_obs_degraded=0.0), STATUS, ()), width=200)
    assert "DEGRADED" not in out
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("rear"))
    assert line.split()[-1] == "y"
    # a log without an observer: no estimate, no mode
    out = text_of(render(_row(columns()), STATUS, ()), width=200)
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("rear"))
    assert "DEGRADED" not in out and line.split()[-1] == "-"


def test_telemetry_carries_the_estimate_and_degraded(receiver):  # noqa: F811
    cols = _cols(("front", "rear"))
    ix = {c: j for j, c in enumerate(cols)}
    block = make_rows(cols, 2)
    block[:, ix["rear_obs_degraded"]] = (0.0, 1.0)
    block[:, ix["front_obs_degraded"]] = 0.0
    out = UdpTelemetry(LogInfo("x.h5", cols), "127.0.0.1", receiver.getsockname()[1])
    try:
        assert out.dropped_fields == []          # both carriers observed: still within one datagram
        out.rows(block)
        msgs = [json.loads(d) for d in receive(receiver, 2)]
    finally:
        out.close()
    for k, msg in enumerate(msgs):
        assert msg["rear"]["degraded"] == block[k, ix["rear_obs_degraded"]]
        assert msg["rear"]["y_hat"] == pytest.approx(block[k, ix["rear_obs_y_hat"]])
        assert msg["front"]["degraded"] == 0.0 and "y_hat" in msg["front"]
    assert msgs[1]["rear"]["degraded"] == 1.0
    assert len(json.dumps(msgs[1])) <= MAX_DATAGRAM


def test_telemetry_without_an_observer_has_no_estimate(receiver):  # noqa: F811
    cols = columns()
    out = UdpTelemetry(LogInfo("x.h5", cols), "127.0.0.1", receiver.getsockname()[1])
    try:
        out.rows(make_rows(cols, 1))
        (msg,) = [json.loads(d) for d in receive(receiver, 1)]
    finally:
        out.close()
    assert "y_hat" not in msg["rear"] and "degraded" not in msg["rear"]
