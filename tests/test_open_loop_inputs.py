"""The open-loop step input (rig_runtime.control.StepSequence) advances an index: each step
is passed once over a sweep of non-decreasing t (the loop's run time), and the value is the
scan's for any t, also when t goes back (a restart after a fault reset)."""

from __future__ import annotations

import random

from hypothesis import given
from hypothesis import strategies as st

from rig_runtime.control import StepSequence


def scan(steps, t: float) -> float:
    """The definition: the value of the last step (sorted) at or before t, 0 before the first."""
    u = 0.0
    for ti, ui in sorted((float(a), float(b)) for a, b in steps):
        if t >= ti:
            u = ui
    return u


def test_a_sweep_passes_each_step_once():
    steps = [(0.5 * k, float(k % 7) - 3.0) for k in range(100)]
    s = StepSequence(steps)
    moves, prev = 0, s._i
    ts = [0.005 * k for k in range(12000)]          # 60 s at the loop's period: past the last step
    for t in ts:
        assert s(t) == scan(steps, t)
        moves += abs(s._i - prev)
        prev = s._i
    assert moves == len(steps)                      # O(1) amortised: no step looked at twice


@given(st.lists(st.tuples(st.floats(0, 100), st.floats(-5, 5)), max_size=12),
       st.lists(st.floats(-10, 110), max_size=40))
def test_any_order_of_t_gives_the_scans_value(steps, ts):
    s = StepSequence(steps)
    for t in ts:
        assert s(t) == scan(steps, t)


def test_back_to_the_start_after_a_restart():
    steps = [(0.0, 0.0), (1.0, 0.7), (2.0, -0.7), (3.0, 0.0)]
    s = StepSequence(steps)
    assert [s(t) for t in (0.0, 1.5, 2.5, 3.5)] == [0.0, 0.7, -0.7, 0.0]
    assert [s(t) for t in (0.0, 1.0, 0.999)] == [0.0, 0.7, 0.0]       # the run time restarted at 0
    random.seed(1)
    for t in sorted(random.uniform(-1, 4) for _ in range(200)):
        assert s(t) == scan(steps, t)


def test_the_loop_calls_the_input_with_a_non_decreasing_run_time(tmp_path, monkeypatch):
    """The precondition of the O(1) step: in a run (no fault reset) the loop's run time never
    goes back between two calls of the open-loop input."""
    from rig_runtime import config
    from rig_runtime.app import runner
    from rig_runtime.app.dryrun import run_lockstep
    from rig_runtime.scenario import load_scenario

    calls = []
    make = runner.open_loop_input

    def recording(ol):
        u = make(ol)

        def call(t):
            calls.append(t)
            return u(t)
        return call
    monkeypatch.setattr(runner, "open_loop_input", recording)
    summary, code = run_lockstep(config.load(), load_scenario("open-loop-steps"), tmp_path / "ol.h5", duration_s=1.0)
    assert code == 0 and len(calls) > 150
    assert all(b >= a for a, b in zip(calls, calls[1:]))
