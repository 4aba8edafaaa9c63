"""Clocks and real-time settings: the real-time clock releases on time and never early,
the lockstep clock advances the simulation, helper threads drop out of SCHED_FIFO."""

import os
import threading

import pytest

from rig_runtime.clock import LockstepClock, RealtimeClock, as_background_thread, helper_cpus


def test_realtime_clock_never_releases_early():
    clock = RealtimeClock(200e-6)
    t0 = clock.now()
    for k in range(1, 21):
        t = clock.wait_until(t0 + k * 0.002)
        assert t >= t0 + k * 0.002


def test_lockstep_clock_advances_the_simulation():
    seen = []
    clock = LockstepClock(advance=seen.append)      # returns None: release on time
    assert clock.now() == 0.0
    assert clock.wait_until(0.005) == 0.005 and clock.wait_until(0.005) == 0.005
    assert clock.now() == 0.005 and seen == [0.005]     # advanced once per new time
    assert clock.wait_until(0.003) == 0.005 and seen == [0.005]     # time never goes back
    assert clock.wait_until(0.010) == 0.010 and clock.now() == 0.010 and seen == [0.005, 0.010]
    assert not hasattr(clock, "spend")
    assert LockstepClock(t0=1.0).wait_until(1.5) == 1.5      # without a simulation


def test_lockstep_clock_stall_releases_late():
    """``advance(t)`` may return a later release time: the runtime wakes up late (a stall)."""
    seen = []
    stalls = {0.010: 0.0235, 0.030: 0.029}        # one stall, and one "earlier" answer (ignored)

    def advance(t):
        seen.append(t)
        return stalls.get(t)

    clock = LockstepClock(advance=advance)
    assert clock.wait_until(0.005) == 0.005
    assert clock.wait_until(0.010) == 0.0235 and clock.now() == 0.0235    # released late
    assert clock.wait_until(0.015) == 0.0235 and clock.wait_until(0.020) == 0.0235   # missed releases
    assert seen == [0.005, 0.010]                 # no advance for a time already passed
    assert clock.wait_until(0.025) == 0.025 and clock.now() == 0.025
    assert clock.wait_until(0.030) == 0.030       # a release time before t is not a stall
    assert seen == [0.005, 0.010, 0.025, 0.030]


def test_helper_threads_leave_sched_fifo():
    """A thread created by a SCHED_FIFO thread inherits FIFO; as_background_thread undoes it."""
    result = {}

    def fifo_parent():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except (OSError, AttributeError) as e:
            result["skip"] = str(e)
            return

        def child():
            result["inherited"] = os.sched_getscheduler(0)
            result["ok"] = as_background_thread()
            result["after"] = os.sched_getscheduler(0)
        t = threading.Thread(target=child)
        t.start()
        t.join()
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))

    t = threading.Thread(target=fifo_parent)
    t.start()
    t.join()
    if "skip" in result:
        pytest.skip(f"SCHED_FIFO not permitted here: {result['skip']}")
    assert result["inherited"] == os.SCHED_FIFO
    assert result["ok"] and result["after"] == os.SCHED_OTHER
    assert os.sched_getscheduler(0) == os.SCHED_OTHER      # the test's own thread untouched


def test_helper_cpus_are_the_ones_the_loop_is_not_pinned_to():
    from rig_runtime.config import Realtime
    n = os.cpu_count() or 1
    assert helper_cpus(Realtime()) is None                           # not pinned: share
    assert helper_cpus(Realtime(cpu_affinity=tuple(range(n)))) is None   # nothing left
    if n >= 2:
        assert helper_cpus(Realtime(cpu_affinity=(0,))) == tuple(range(1, n))


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs")
def test_the_recording_sidecar_runs_where_it_is_told(tmp_path):
    from rig_runtime.recorder import Recorder
    mine = os.sched_getaffinity(0)
    cpu = max(mine)
    rec = Recorder(tmp_path / "a.h5", ["t"], attrs={}, cpus=(cpu,))
    rec.open()
    try:
        assert os.sched_getaffinity(rec.process.pid) == {cpu}
        assert os.sched_getaffinity(0) == mine                          # the caller stays
    finally:
        rec.close()
