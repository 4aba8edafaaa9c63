"""The bare real-time loop: the project's :class:`~rig_runtime.clock.RealtimeClock` (sleep,
then spin to an absolute deadline) at period ``h`` with no work in it — the floor the
runtime's loop cannot beat on this machine. One implementation, used by ``rig latency`` and
``benchmarks/loop_timing.py``.

Wake-up lateness is release time − deadline; a period is missed when the cycle ends after
the next deadline, and the periods it overran are skipped, as the runtime's loop does."""

from __future__ import annotations

import gc
import math

from ..clock import RealtimeClock, next_release
from ..stats import CycleStats


def bare_loop(clock: RealtimeClock, h: float, duration_s: float, phase_s: float | None = None) -> CycleStats:
    """Run ``duration_s / h`` periods with the garbage collector frozen and off (as the
    loop runs); returns the lateness/work histograms and the misses. ``phase_s``: put the
    deadlines at ``phase_s`` modulo ``h`` on the clock (a loop beside on the same CPU whose
    wake-ups are on the grid of ``h`` then never falls into this one's spin)."""
    stats = CycleStats()
    n = int(duration_s / h)
    gc.collect(); gc.freeze(); gc.disable()
    try:
        t0 = clock.now() + h
        if phase_s is not None:
            t0 = (math.floor((t0 - phase_s) / h) + 1) * h + phase_s
        k = 0
        while k < n:
            t_k = t0 + k * h
            t = clock.wait_until(t_k)
            t_done = clock.now()
            missed, k_next = next_release(t0, k, h, t_done)
            stats.update(t - t_k, t_done - t, missed, k_next - k - 1)
            k = k_next
    finally:
        gc.enable(); gc.unfreeze()
    return stats
