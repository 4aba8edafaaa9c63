"""Timing statistics: fixed-size histograms give exact (to the bin width) nearest-rank
percentiles, keep large values exactly, do not grow with the run, and count a sliding
window when asked (``rig sim``'s status)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rig_runtime.stats import BIN_S, CycleStats, Histogram


def test_hand_checked_percentiles():
    h = Histogram()
    for us in (10, 20, 30, 40, 50, 60, 70, 80, 90, 100):
        h.add(us * 1e-6)
    # nearest rank: p50 of ten values is the 5th smallest, p99 the 10th
    assert abs(h.percentile(50) - 50e-6) <= BIN_S
    assert abs(h.percentile(99) - 100e-6) <= BIN_S
    assert h.max == 100 * 1e-6 and h.n == 10


def test_large_values_are_kept_exactly_and_negative_counts_as_zero():
    h = Histogram()
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
    h = Histogram()
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


def test_coarse_bins_and_summary():
    h = Histogram(bin_s=1e-5, max_s=0.2)
    xs = np.random.default_rng(1).exponential(0.3e-3, 20000)
    for x in xs:
        h.add(float(x))
    d = h.summary(1e3)
    assert d["n"] == xs.size and d["max"] == pytest.approx(xs.max() * 1e3)
    for q, key in ((50, "p50"), (99, "p99"), (99.9, "p999")):
        assert d[key] == pytest.approx(np.percentile(xs, q) * 1e3, abs=0.011)   # 10 µs bins
    assert Histogram().summary() == {"n": 0, "p50": None, "p99": None, "p999": None, "max": None}
    c = h.copy()
    h.add(1.0)                                # beyond max_s: kept exactly, not in the copy
    assert c.summary(1e3) == d and h.summary()["max"] == 1.0 and h.percentile(100) == 1.0


def test_window_counts_the_current_and_the_previous_window_only():
    w = Histogram(bin_s=1e-5, max_s=0.2, window_s=1.0)
    w.add(5.0, 0.0)
    w.add(0.001, 1.5)                         # a new window: the first one still counts
    assert w.summary()["n"] == 2 and w.summary()["max"] == 5.0
    w.add(0.001, 2.6)                         # and now it is gone
    assert w.summary()["n"] == 2 and w.summary()["max"] == pytest.approx(0.001)
    assert w.percentile(100) == pytest.approx(0.001, abs=1e-5)


def test_a_reader_never_breaks_the_writer_nor_sees_half_a_sample():
    """rig sim's plant thread adds while its status thread reads (issue 29: a reader's
    buffer view made the writer's ``over.append`` raise BufferError, and a count without
    its sample made the reader index past the end)."""
    import threading
    h = Histogram(bin_s=1e-5, max_s=0.001, window_s=0.05)    # most samples beyond max_s: kept exactly
    errors: list[BaseException] = []
    done = threading.Event()
    n_add = 60_000

    def write():
        try:
            for k in range(n_add):
                h.add(0.0005 + 0.001 * (k % 7), k * 1e-5)
        except BaseException as e:      # noqa: BLE001 - the assertion below names it
            errors.append(e)
        finally:
            done.set()

    th = threading.Thread(target=write)
    th.start()
    reads = 0
    try:
        while not done.is_set() or reads == 0:
            s = h.summary(1e3)
            assert s["n"] == 0 or s["p50"] <= s["p99"] <= s["p999"] <= s["max"]
            reads += 1
    finally:
        th.join()
    assert errors == [] and reads > 0
    assert h.summary()["max"] == pytest.approx(0.0065)
