"""Cycle timing statistics: fixed-size histograms give exact (to 0.1 µs) nearest-rank
percentiles, keep large values exactly, and do not grow with the run."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rig_runtime.stats import BIN_S, CycleStats, TimingHistogram


def test_hand_checked_percentiles():
    h = TimingHistogram()
    for us in (10, 20, 30, 40, 50, 60, 70, 80, 90, 100):
        h.add(us * 1e-6)
    # nearest rank: p50 of ten values is the 5th smallest, p99 the 10th
    assert abs(h.percentile(50) - 50e-6) <= BIN_S
    assert abs(h.percentile(99) - 100e-6) <= BIN_S
    assert h.max == 100 * 1e-6 and h.n == 10


def test_large_values_are_kept_exactly_and_negative_counts_as_zero():
    h = TimingHistogram()
    h.add(-1e-6)
    h.add(0.25)               # 250 ms: beyond the histogram
    h.add(0.02)
    assert h.percentile(1) <= BIN_S
    assert h.percentile(100) == 0.25 and h.percentile(66) == 0.02
    s = CycleStats()
    s.update(0.0, 0.004, False, 0)
    s.update(0.001, 0.012, True, 2)
    out = s.summary()
    assert out["cycles"] == 2 and out["deadline_misses"] == 1 and out["skipped_periods"] == 2
    assert out["cycle_work_us"]["max"] == 12000.0 and s.overrun_periods == 3


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(0.0, 0.03), min_size=1, max_size=300), st.sampled_from([50.0, 99.0, 99.9]))
def test_matches_numpy_nearest_rank(xs, q):
    h = TimingHistogram()
    for x in xs:
        h.add(x)
    want = float(np.percentile(np.array(xs), q, method="inverted_cdf"))
    assert abs(h.percentile(q) - want) <= BIN_S


def test_memory_does_not_grow_with_the_run():
    s = CycleStats()
    before = len(s.lateness.counts), len(s.work.counts)
    for k in range(50_000):
        s.update(1e-6 * (k % 900), 1e-4, False, 0)
    assert (len(s.lateness.counts), len(s.work.counts)) == before
    assert len(s.lateness.over) == 0 and s.cycles == 50_000
