"""What ended a run first, and a second stop signal (issue 29), in lockstep: the summary's
``ended_by`` names the first cause; a signal that came after the run had ended (in FAULT, or
at its end) is not reported as the operator stop that ended it."""

import dataclasses
import signal

import pytest

from rig_runtime import config
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.app.signals import StopSignals
from rig_runtime.scenario import load_scenario

STEP = load_scenario("single-step")


def test_a_second_signal_goes_to_the_repeat_listeners_only():
    s = StopSignals()
    heard = []
    first, again = (lambda: heard.append("stop")), (lambda: heard.append("again"))
    s.on_stop(first)
    s.on_repeat(again)
    s._on_signal(signal.SIGINT, None)
    assert heard == ["stop"] and s.name == "SIGINT" and s.repeats == 0
    s._on_signal(signal.SIGTERM, None)
    assert heard == ["stop", "again"] and s.name == "SIGINT" and s.repeats == 1
    s.forget(again)
    s._on_signal(signal.SIGINT, None)
    assert heard == ["stop", "again"] and s.repeats == 2


def _signal_when(stops: StopSignals, when):
    """A prepare hook: deliver SIGINT (as the handler would) when ``when(devices, now)``."""
    def prepare(sim, devices, clock):
        poll, close = devices.poll, devices.close

        def polled(now):
            if not stops.requested and when("poll", now):
                stops._on_signal(signal.SIGINT, None)
            return poll(now)

        def closed():
            if not stops.requested and when("close", None):
                stops._on_signal(signal.SIGINT, None)
            return close()
        devices.poll, devices.close = polled, closed
    return prepare


def test_the_duration_ended_the_run_and_no_sidecar_process_was_started(tmp_path, monkeypatch):
    """A lockstep run without live outputs writes its log in its own process (issue 26):
    no interpreter is started for the recorder."""
    import subprocess
    popen = subprocess.Popen

    def no_sidecar(cmd, *a, **kw):
        assert "rig_runtime.sidecar" not in " ".join(map(str, cmd)), f"a sidecar process was started: {cmd}"
        return popen(cmd, *a, **kw)
    monkeypatch.setattr(subprocess, "Popen", no_sidecar)
    summary, code = run_lockstep(config.load(), STEP, tmp_path / "d.h5", duration_s=0.3)
    assert code == 0 and summary["ended_by"] == "duration reached" and "stopped_by" not in summary
    assert summary["recorder"]["healthy"] and summary["recorder"]["rows"] == summary["cycles"] > 0


def test_a_signal_while_running_ended_the_run(tmp_path):
    stops = StopSignals()
    summary, code = run_lockstep(config.load(), STEP, tmp_path / "s.h5", duration_s=5.0, stops=stops,
                                 prepare=_signal_when(stops, lambda where, now: where == "poll" and now > 1.5))
    assert code == 0 and summary["final_state"] == "IDLE"
    assert summary["ended_by"] == "SIGINT" and summary["stopped_by"] == "SIGINT" and "late_stop" not in summary


def test_a_signal_after_the_fault_did_not_end_the_run(tmp_path):
    """The run ends in FAULT; the signal arrives while the devices close: the summary says
    the fault ended it, and the exit code is the fault's."""
    cfg = config.load()
    cfg = dataclasses.replace(cfg, limits=dataclasses.replace(cfg.limits, y_max=0.001))
    stops = StopSignals()
    summary, code = run_lockstep(cfg, STEP, tmp_path / "f.h5", duration_s=6.0, stops=stops,
                                 prepare=_signal_when(stops, lambda where, now: where == "close"))
    assert stops.requested
    assert code == 3 and summary["final_state"] == "FAULT", summary
    assert summary["ended_by"].startswith("fault: geometry y_limit"), summary["ended_by"]
    assert "stopped_by" not in summary and summary["late_stop"] == "SIGINT"
    assert summary["recorder"]["closed"] and summary["recorder"]["left_running"] == ""
