"""Timing statistics: fixed-size histograms of durations, and the cycle statistics of the loop.

A distribution is a fixed-size histogram (bins of ``bin_s`` up to ``max_s``; the rare larger
values are kept exactly), so a run of any length holds the same memory — a ten-minute run
must not grow the process — and each sample costs one integer increment. Percentiles are
exact to the bin width (nearest rank, reported as the bin centre, never above the maximum).
The loop's cycle statistics and ``rig sim``'s status (plant-thread lateness, SYNC → TPDO
latency, over a sliding window) use the same class.

Threads: one thread adds while another reads (``rig sim``'s plant thread and its status
writer). ``add`` and every reading method hold the histogram's lock; a reader copies the
state under the lock (:meth:`Histogram.copy`, a memcpy of the bins) and computes on its own
copy, so no reader holds a view of an array the writer grows, nor sees a count without its
sample. An uncontended lock costs the writer about 0.1 µs per sample.
"""

from __future__ import annotations

import math
import threading
from array import array
from typing import Any, Optional

import numpy as np

BIN_S = 1e-7                 # cycle statistics: 0.1 µs bins …
N_BINS = 100_000             # … 0 … 10 ms in the histogram; beyond, the values themselves


class Histogram:
    """A distribution of non-negative durations in seconds (negative ones count as 0).

    ``window_s`` > 0: only the current and the previous window are counted ("the last
    ``window_s`` to 2·``window_s``"); ``add`` then needs the time ``t`` of the sample. Safe to add from one thread while
    others read (see the module docstring); ``counts``/``over``/``n``/``max`` read directly
    are for the thread that adds, or after it ended."""

    __slots__ = ("bin_s", "n_bins", "window_s", "counts", "over", "n", "max", "last",
                 "_inv", "_prev", "_t_window", "_lock")

    def __init__(self, bin_s: float = BIN_S, max_s: float = BIN_S * N_BINS, window_s: float = 0.0) -> None:
        self.bin_s = bin_s
        self._inv = 1.0 / bin_s
        self.n_bins = int(round(max_s / bin_s))
        self.window_s = window_s
        self._lock = threading.Lock()
        self.clear()

    def clear(self) -> None:
        """Forget every sample (the memory is allocated and touched now, not while adding)."""
        counts = array("q", bytes(8 * self.n_bins))
        with self._lock:
            self.counts = counts
            self.over = array("d")
            self.n = 0
            self.max = 0.0
            self.last = 0.0
            self._prev: Optional[tuple[array, array, int, float]] = None   # the previous window
            self._t_window = math.nan           # end of the current window

    def add(self, x: float, t: float = 0.0) -> None:
        i = int(x * self._inv) if x > 0.0 else 0
        with self._lock:
            if self.window_s and not t < self._t_window:
                self._rotate(t)
            if i < self.n_bins:
                self.counts[i] += 1
            else:
                self.over.append(x)
            self.last = x
            self.n += 1
            if x > self.max:
                self.max = x

    def _rotate(self, t: float) -> None:
        """A new window starts at ``t``; the current one becomes the previous one."""
        if self._t_window == self._t_window:
            self._prev = (self.counts, self.over, self.n, self.max)
            self.counts = array("q", bytes(8 * self.n_bins))
            self.over = array("d")
            self.n = 0
            self.max = 0.0
        self._t_window = t + self.window_s

    def copy(self) -> "Histogram":
        """A consistent copy, taken under the lock (the previous window's arrays are never
        written again once rotated out, so the copy shares them)."""
        h = Histogram.__new__(Histogram)
        with self._lock:
            for k in Histogram.__slots__:
                setattr(h, k, getattr(self, k))
            h.counts = array("q", self.counts)
            h.over = array("d", self.over)
        h._lock = threading.Lock()
        return h

    def _merged(self) -> tuple[np.ndarray, np.ndarray, int, float]:
        """Counts, large values, n and max of the current and previous window; on a private
        copy (call it on the result of :meth:`copy`)."""
        counts = np.frombuffer(self.counts, dtype=np.int64)
        over = np.frombuffer(self.over, dtype=float)
        n, mx = self.n, self.max
        if self._prev is not None:
            pc, po, pn, pm = self._prev
            counts = counts + np.frombuffer(pc, dtype=np.int64)
            over = np.concatenate([over, np.frombuffer(po, dtype=float)])
            n, mx = n + pn, max(mx, pm)
        return counts, over, n, mx

    def percentiles(self, qs: tuple[float, ...]) -> list[float]:
        """The ``q``-th percentiles (0…100) in seconds (nearest rank; 0 without samples)."""
        return self.copy()._percentiles(qs)

    def _percentiles(self, qs: tuple[float, ...]) -> list[float]:
        counts, over, n, mx = self._merged()
        if n == 0:
            return [0.0] * len(qs)
        cum = np.cumsum(counts)
        in_hist = int(cum[-1])
        over_sorted = None
        out = []
        for q in qs:
            rank = max(1, int(np.ceil(q / 100.0 * n)))          # the rank-th smallest value
            if rank <= in_hist:
                i = int(np.searchsorted(cum, rank))
                out.append(min((i + 0.5) * self.bin_s, mx))
            else:
                if over_sorted is None:
                    over_sorted = np.sort(over)
                out.append(float(over_sorted[rank - in_hist - 1]))
        return out

    def percentile(self, q: float) -> float:
        return self.percentiles((q,))[0]

    def distribution_us(self) -> dict:
        """``{"p50", "p99", "p999", "max"}`` in µs (0 without samples)."""
        snap = self.copy()
        p50, p99, p999 = snap._percentiles((50.0, 99.0, 99.9))
        return {"p50": p50 * 1e6, "p99": p99 * 1e6, "p999": p999 * 1e6, "max": snap._merged()[3] * 1e6}

    def summary(self, scale: float = 1.0) -> dict[str, Any]:
        """``{"n", "p50", "p99", "p999", "max"}`` in seconds × ``scale`` (None without samples)."""
        snap = self.copy()
        _, _, n, mx = snap._merged()
        if not n:
            return {"n": 0, "p50": None, "p99": None, "p999": None, "max": None}
        p50, p99, p999 = snap._percentiles((50.0, 99.0, 99.9))
        return {"n": n, "p50": p50 * scale, "p99": p99 * scale, "p999": p999 * scale, "max": mx * scale}


class CycleStats:
    """Release lateness and work time of every cycle, deadline misses and overrun bursts."""

    def __init__(self) -> None:
        self.lateness = Histogram()
        self.work = Histogram()
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
