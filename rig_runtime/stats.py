"""Cycle timing statistics: release lateness and work time per cycle, deadline misses.

Distributions are kept as fixed-size histograms (0.1 µs bins up to 10 ms; the rare larger
values are kept exactly), so a run of any length holds the same memory — a ten-minute run
must not grow the process — and each cycle costs one integer increment per quantity.
Percentiles are exact to the bin width.
"""

from __future__ import annotations

from array import array

import numpy as np

BIN_S = 1e-7                 # histogram resolution: 0.1 µs
N_BINS = 100_000             # 0 … 10 ms in the histogram; beyond, the values themselves


class TimingHistogram:
    """A distribution of non-negative durations in seconds (negative ones count as 0)."""

    __slots__ = ("counts", "over", "n", "max", "last")

    def __init__(self) -> None:
        self.counts = array("q", bytes(8 * N_BINS))     # zeroed and touched now, not in the loop
        self.over = array("d")
        self.n = 0
        self.max = 0.0
        self.last = 0.0

    def add(self, x: float) -> None:
        self.last = x
        self.n += 1
        if x > self.max:
            self.max = x
        i = int(x * 1e7) if x > 0.0 else 0
        if i < N_BINS:
            self.counts[i] += 1
        else:
            self.over.append(x)

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile in seconds (bin centre; 0 when empty)."""
        if self.n == 0:
            return 0.0
        rank = max(1, int(np.ceil(q / 100.0 * self.n)))          # the rank-th smallest value
        cum = np.cumsum(np.frombuffer(self.counts, dtype=np.int64))
        in_hist = int(cum[-1])
        if rank <= in_hist:
            i = int(np.searchsorted(cum, rank))
            return min((i + 0.5) * BIN_S, self.max)
        return float(np.sort(np.frombuffer(self.over, dtype=float))[rank - in_hist - 1])

    def distribution_us(self) -> dict:
        return {"p50": self.percentile(50) * 1e6, "p99": self.percentile(99) * 1e6,
                "p999": self.percentile(99.9) * 1e6, "max": self.max * 1e6}


class CycleStats:
    """Release lateness and work time of every cycle, deadline misses and overrun bursts."""

    def __init__(self) -> None:
        self.lateness = TimingHistogram()
        self.work = TimingHistogram()
        self.deadline_misses = 0
        self.skipped_periods = 0
        self.consecutive_misses = 0
        self.overrun_periods = 0      # periods lost in the current burst of misses (missed + skipped)

    def update(self, lateness_s: float, work_s: float, missed: bool, skipped: int) -> None:
        self.lateness.add(lateness_s)
        self.work.add(work_s)
        if missed:
            self.deadline_misses += 1
            self.consecutive_misses += 1
            self.skipped_periods += skipped
            self.overrun_periods += 1 + skipped
        else:
            self.consecutive_misses = 0
            self.overrun_periods = 0

    @property
    def cycles(self) -> int:
        return self.work.n

    def summary(self) -> dict:
        return {"release_lateness_us": self.lateness.distribution_us(),
                "cycle_work_us": self.work.distribution_us(),
                "deadline_misses": self.deadline_misses,
                "skipped_periods": self.skipped_periods,
                "cycles": self.work.n}
