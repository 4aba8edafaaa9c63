"""``cyclictest`` (Debian's rt-tests) as an independent peer of ``rig latency``: the
command line for the same period, duration, priority and CPU, and the parse of its
histogram output (``-q -h N``) into the same figures (p50/p99/p99.9/max in µs).

cyclictest measures the wake-up of ``clock_nanosleep`` alone; ``rig latency`` measures the
project's sleep-then-spin clock, whose spin hides the sleep's own lateness: the two answer
different questions on the same machine, which is why both are printed."""

from __future__ import annotations

import math
import re
import shutil
import subprocess
from dataclasses import dataclass
from typing import Optional


@dataclass(frozen=True)
class PeerResult:
    """cyclictest's figures for one thread (µs); ``overflows``: samples above the histogram."""

    n: int
    p50_us: float
    p99_us: float
    p999_us: float
    max_us: float
    avg_us: float
    overflows: int
    histogram: tuple[tuple[int, int], ...]     # (µs, count), non-empty buckets only


def find() -> Optional[str]:
    """The cyclictest executable, or None when rt-tests is not installed."""
    return shutil.which("cyclictest")


def command(exe: str, *, duration_s: float, period_s: float, priority: Optional[int], cpu: Optional[int],
            hist_max_us: int) -> list[str]:
    """One measuring thread at ``period_s`` for ``duration_s`` (as many periods: ``-l``,
    so both loops count the same number of periods), memory locked, quiet, with a histogram
    up to ``hist_max_us``; its wake-ups aligned to the full second (``--secaligned``, which
    waits up to 2 s before the first), so on CLOCK_MONOTONIC's grid of the period
    (``rig latency`` puts its own half a period off it: neither falls into the other's run)."""
    cmd = [exe, "-q", "-m", "-t", "1", "-l", str(max(1, round(duration_s / period_s))),
           "-i", f"{round(period_s * 1e6)}", "-h", str(hist_max_us), "--secaligned"]
    if priority is not None:
        cmd += ["-p", str(priority), "--policy=fifo"]
    if cpu is not None:
        cmd += ["-a", str(cpu)]
    return cmd


def start(cmd: list[str]) -> subprocess.Popen:
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.DEVNULL)


def parse(text: str) -> PeerResult:
    """cyclictest's ``-q -h N`` output: bucket lines "000012 000345" (µs, count of thread 0),
    then "# Min/Avg/Max Latencies:", "# Histogram Overflows:". Percentiles by nearest rank
    over the buckets; an overflowing rank is reported as the maximum."""
    hist = []
    for line in text.splitlines():
        m = re.fullmatch(r"\s*(\d+)\s+(\d+)(?:\s+\d+)*\s*", line)
        if m:
            us, count = int(m.group(1)), int(m.group(2))
            if count:
                hist.append((us, count))

    def field(name: str) -> Optional[float]:
        m = re.search(rf"^# {name}:\s*([\d.]+)", text, re.M)
        return float(m.group(1)) if m else None
    mx, avg, over = field("Max Latencies"), field("Avg Latencies"), field("Histogram Overflows")
    if mx is None:
        raise ValueError("no '# Max Latencies' line in cyclictest's output")
    overflows = int(over or 0)
    n = sum(c for _, c in hist) + overflows

    def pct(q: float) -> float:
        rank = max(1, math.ceil(q / 100.0 * n - 1e-9))     # nearest rank
        acc = 0
        for us, c in hist:
            acc += c
            if acc >= rank:
                return float(us)
        return mx
    return PeerResult(n=n, p50_us=pct(50.0), p99_us=pct(99.0), p999_us=pct(99.9), max_us=mx, avg_us=avg or 0.0,
                      overflows=overflows, histogram=tuple(hist))
