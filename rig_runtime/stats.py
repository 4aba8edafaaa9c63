"""Cycle timing statistics: release lateness and work time per cycle, deadline misses."""

from __future__ import annotations

from array import array

import numpy as np


class CycleStats:
    """Appends two floats per cycle (array.array: amortised O(1), no per-cycle objects)."""

    def __init__(self) -> None:
        self.lateness = array("d")
        self.work = array("d")
        self.deadline_misses = 0
        self.skipped_periods = 0
        self.consecutive_misses = 0
        self.overrun_periods = 0      # periods lost in the current burst of misses (missed + skipped)

    def update(self, lateness_s: float, work_s: float, missed: bool, skipped: int) -> None:
        self.lateness.append(lateness_s)
        self.work.append(work_s)
        if missed:
            self.deadline_misses += 1
            self.consecutive_misses += 1
            self.skipped_periods += skipped
            self.overrun_periods += 1 + skipped
        else:
            self.consecutive_misses = 0
            self.overrun_periods = 0

    @staticmethod
    def distribution_us(values) -> dict:
        a = np.frombuffer(values, dtype=float) * 1e6 if len(values) else np.zeros(1)
        return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
                "p999": float(np.percentile(a, 99.9)), "max": float(a.max())}

    def summary(self) -> dict:
        return {"release_lateness_us": self.distribution_us(self.lateness),
                "cycle_work_us": self.distribution_us(self.work),
                "deadline_misses": self.deadline_misses,
                "skipped_periods": self.skipped_periods,
                "cycles": len(self.work)}
