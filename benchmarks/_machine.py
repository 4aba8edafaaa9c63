"""What the machine did during a measurement: CPU time stolen by the hypervisor.

On a shared VM the host can take the CPU away for milliseconds; Linux accounts that as
"steal" time (``/proc/stat``, 8th value of the ``cpu`` line). Reported next to a result,
it tells a slow run on a busy host from a slow program. Not available (None) where the
kernel does not account it.
"""

from __future__ import annotations

import os
import time
from typing import Optional

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _steal_ticks() -> Optional[int]:
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return None
    return int(fields[8]) if fields and fields[0] == "cpu" and len(fields) > 8 else None


class StealMeter:
    """``with StealMeter() as m: ...`` then ``m.percent``: stolen CPU time in % of the
    wall time of the block, summed over all CPUs (so up to 100·CPUs)."""

    def __enter__(self) -> "StealMeter":
        self._s0, self._t0 = _steal_ticks(), time.monotonic()
        self.percent: Optional[float] = None
        return self

    def __exit__(self, *exc: object) -> None:
        s1, dt = _steal_ticks(), time.monotonic() - self._t0
        if self._s0 is not None and s1 is not None and dt > 0:
            self.percent = 100.0 * (s1 - self._s0) / _TICK / dt
