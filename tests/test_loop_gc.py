"""The loop's garbage collection around a run: a full collection before t0 only where the
releases are deadlines (rig_runtime.loop, rig_runtime.clock.Clock.deadlines)."""

from __future__ import annotations

from rig_runtime import config
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.scenario import load_scenario


def test_a_lockstep_run_skips_the_collection_a_deadline_needs(tmp_path, monkeypatch):
    """The loop collects garbage before t0 only for a clock with deadlines (a full collection
    takes tens of ms in a warm process: a lockstep run has no deadline it protects); the
    collector is disabled during the run either way."""
    import gc
    from rig_runtime import loop
    from rig_runtime.clock import Clock, LockstepClock, RealtimeClock
    assert Clock.deadlines and RealtimeClock().deadlines and not LockstepClock().deadlines
    calls = []

    class Recording:
        def __getattr__(self, name):
            return getattr(gc, name)

        def collect(self, *a):
            calls.append("collect")
            return gc.collect(*a)

        def disable(self):
            calls.append("disable")
            return gc.disable()
    monkeypatch.setattr(loop, "gc", Recording())
    summary, code = run_lockstep(config.load("configs/sim.yaml"), load_scenario("single-step"), tmp_path / "x.h5",
                                 duration_s=0.1)
    assert code == 0 and summary["cycles"] > 0
    assert calls == ["disable"]            # no collection; the collector off for the run
