"""Live terminal panel: rendering is a pure function of row, status and events."""

from __future__ import annotations

import io
import math

from rich.console import Console

from rig_runtime.app.panel import LivePanel, render
from tests.test_telemetry import STATUS, LogInfo, columns, make_rows


def text_of(renderable, width=140) -> str:
    console = Console(record=True, width=width, file=io.StringIO(), color_system=None)
    console.print(renderable)
    return console.export_text()


def row_dict(cols, **values):
    block = make_rows(cols, 1)
    row = dict(zip(cols, block[0].tolist()))
    row.update(values)
    return row


def test_render_shows_state_times_carrier_devices_timing():
    cols = columns(controlled=("rear",))
    row = row_dict(cols, t_run=12.5, y_ref=0.002, y_r=0.0015, psi_ar=-0.004, rear_psi_ref=-0.003,
                   rear_u_cmd=1.25, rear_u_lim=1.2, rear_e_y=0.0005)
    out = text_of(render(row, STATUS, ()))
    assert "RUNNING" in out
    assert "elapsed 0:12.5" in out and "remaining 0:-2.5" not in out
    assert "remaining -" not in out
    assert "of 0:10.0" in out                       # duration from the status
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("rear"))
    for cell in ("2.00", "1.50", "0.50", "-3.00", "-4.00", "1.250", "1.200"):
        assert cell in line, (cell, line)
    assert not any(ln.strip().startswith("front") for ln in out.splitlines())   # not controlled
    dev = next(ln for ln in out.splitlines() if ln.strip().startswith("rl"))
    assert "stale" in dev and "7" in dev and "no sample" in dev
    assert "faults: none" in out
    work = next(ln for ln in out.splitlines() if "cycle work" in ln)
    assert work.split()[-4:] == ["50.0", "45.0", "90.0", "300.0"]
    late = next(ln for ln in out.splitlines() if "lateness" in ln)
    assert late.split()[-4:] == ["5.0", "4.0", "30.0", "80.0"]
    assert "deadline misses 2" in out and "skipped periods 1" in out and "overrun" not in out
    bf = next(ln for ln in out.splitlines() if ln.strip().startswith("b_f"))
    assert bf.split()[:5] == ["b_f", "laser", "fresh", "2.1", "3"] and bf.split()[5:7] == ["-", "-"]
    assert "recorder rows 200 ok" in out
    assert next(ln for ln in out.splitlines() if ln.startswith("lasers")).split() == ["lasers", "frames", "1000",
                                                                                      "bad", "3"]


def test_remaining_time_counts_down_and_open_ended_runs():
    cols = columns()
    row = row_dict(cols, t_run=4.0)
    assert "remaining 0:06.0 of 0:10.0" in text_of(render(row, STATUS, ()))
    open_ended = dict(STATUS, duration_s=None)
    assert "remaining - (until stopped)" in text_of(render(row, open_ended, ()))
    # the duration from the log's attributes when the status has none
    assert "remaining 1:56.0 of 2:00.0" in text_of(render(row, open_ended, (), duration_s=120.0))
    assert "remaining - (until stopped)" in text_of(render(row, open_ended, (), duration_s=math.inf))


def test_faults_with_their_cause():
    cols = columns()
    row = row_dict(cols, state=4.0)
    status = dict(STATUS, state="FAULT", faults=[
        {"t_run": 3.25, "device": "laser b_f", "check": "stale", "value": 0.031, "limit": 0.02,
         "message": "sample 31 ms old"}])
    out = text_of(render(row, status, ()))
    assert "FAULT" in out
    assert "t=3.250 s laser b_f stale: sample 31 ms old (value 0.031, limit 0.02)" in out
    # before a snapshot lists them: from the fault events
    ev = (105.0, "fault", "drive rl", "watchdog", math.nan, math.nan, "no heartbeat")
    out = text_of(render(row, {}, [(104.0, "state", "", "", math.nan, math.nan, "ARMED -> RUNNING"), ev]))
    assert "drive rl watchdog: no heartbeat" in out and "ARMED -> RUNNING" not in out


def test_missing_everything_shows_dashes():
    out = text_of(render(None, None, ()))
    assert "rig" in out and "elapsed -" in out
    out = text_of(render({}, {"timing": {}, "devices": [{"name": "b_f"}]}, ()))
    assert "cycle work" in out and "b_f" in out and "deadline misses -" in out and "recorder rows - -" in out
    # lateness and work from the row when the status has no timing yet (s -> µs)
    cols = columns()
    row = row_dict(cols, lateness=25e-6, work=60e-6)
    out = text_of(render(row, {}, ()))
    assert next(ln for ln in out.splitlines() if "cycle work" in ln).split()[2] == "60.0"


def test_both_carriers_when_both_controlled():
    cols = columns(controlled=("front", "rear"))
    out = text_of(render(row_dict(cols), dict(STATUS, controlled=["front", "rear"]), ()))
    assert any(ln.strip().startswith("front") for ln in out.splitlines())
    assert any(ln.strip().startswith("rear") for ln in out.splitlines())


class FakeStream(io.StringIO):
    def __init__(self, tty):
        super().__init__()
        self.tty = tty

    def isatty(self):
        return self.tty


def test_quiet_when_not_a_terminal():
    cols = columns()
    stream = FakeStream(tty=False)
    panel = LivePanel(LogInfo("run.h5", cols), stream=stream)
    panel.rows(make_rows(cols, 3))
    panel.status(STATUS)
    panel.event((1.0, "fault", "x", "y", 1.0, 0.5, "z"))
    panel.close()
    assert not panel.enabled and stream.getvalue() == ""


def test_forced_panel_draws_the_latest_row():
    cols = columns()
    stream = FakeStream(tty=False)
    panel = LivePanel(LogInfo("run.h5", cols, {"duration_s": 10.0}), stream=stream, force=True,
                      refresh_per_second=1)
    block = make_rows(cols, 5)
    panel.rows(block)
    panel.status(STATUS)
    panel.event((101.0, "fault", "laser b_f", "range", 0.5, 0.3, "out of range"))
    panel.close()
    panel.close()                                           # idempotent
    assert panel.enabled
    # the last row of the block is the one shown
    expect = text_of(render(dict(zip(cols, block[-1].tolist())), STATUS, [], duration_s=10.0))
    assert "elapsed 0:00.0" in expect
    shown = stream.getvalue()
    assert "RUNNING" in shown and "cycle work" in shown and "stale" in shown


def test_law_signals_by_the_names_the_law_declares():
    """The control law's table: one column per declared signal in display units, a row per
    controlled carrier; LivePanel takes the declaration from the log's ``law_signals``."""
    import json
    from rig_runtime.control import DecoupledLaw
    from rig_runtime.logformat import LAW_SIGNALS_ATTR
    law = dict(DecoupledLaw.SIGNALS)
    cols = columns(controlled=("front", "rear")) + tuple(f"{c}_{n}" for c in ("front", "rear")
                                                         for n in ("w", "w_cross", "x_I_psi"))
    row = row_dict(cols, front_w=0.0123, front_w_cross=-0.0045, rear_x_I_psi=2.5e-4, rear_u_unsat=0.75)
    out = text_of(render(row, dict(STATUS, controlled=["front", "rear"]), (), law=law), width=200)
    assert "control law" in out
    for head in ("w mrad", "w_cross mrad", "x_I_psi mrad s", "u_unsat A", "de_psi mrad/s"):
        assert head in out, head
    law_lines = out[out.index("control law"):].splitlines()
    front = next(ln for ln in law_lines if ln.strip().startswith("front"))
    rear = next(ln for ln in law_lines if ln.strip().startswith("rear"))
    assert "12.300" in front and "-4.500" in front
    assert "0.250" in rear and "0.750" in rear
    assert "control law" not in text_of(render(row, STATUS, ()))      # nothing declared: no table
    panel = LivePanel(LogInfo("run.h5", cols, {LAW_SIGNALS_ATTR: json.dumps(law)}), stream=io.StringIO())
    assert panel.law == law
