"""``rig latency``: the bare real-time loop (:mod:`rig_runtime.app.bare_loop`) at the
configured period on this machine — a histogram of the wake-up lateness, p50/p99/p99.9/max,
deadline misses, and what that leaves of the period for the cycle's work — with
``cyclictest`` beside it for the same duration when rt-tests is installed.

The cycle's work is not measured here (that needs the devices): the figure it is set
against is the runtime's measured cycle work against ``rig sim`` on the real-time clock
(``docs/performance.md``), or ``--work-us`` for another machine's figure."""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
from dataclasses import dataclass, replace
from typing import Optional

from ..errors import ConfigError
from ..stats import Histogram
from .command import arg, command

# docs/performance.md, session 6 (loop_timing.py --fifo 80 --cpu 1): the runtime's cycle
# against `rig sim`, recording and telemetry on, the worst part's p99.9
WORK_REFERENCE_US = 755.0
WORK_REFERENCE_SOURCE = "the runtime's cycle work p99.9 against rig sim, SCHED_FIFO 80 on CPU 1 (docs/performance.md, session 6)"

BUCKETS_US = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000)


@dataclass(frozen=True)
class LoopFigures:
    """The bare loop's wake-up lateness (µs), misses and periods."""

    n: int
    p50_us: float
    p99_us: float
    p999_us: float
    max_us: float
    deadline_misses: int
    skipped_periods: int


def buckets(hist: Histogram, edges_us=BUCKETS_US) -> list[tuple[str, int]]:
    """Counts of ``hist`` per range ``[0, e0)``, ``[e0, e1)``, …, ``>= e_last`` (µs)."""
    import numpy as np
    counts = np.frombuffer(hist.counts, dtype=np.int64)       # a histogram without a window: all samples
    cum = np.concatenate([[0], np.cumsum(counts)])
    edges_bins = [min(int(round(e * 1e-6 / hist.bin_s)), len(counts)) for e in edges_us]
    over = np.frombuffer(hist.over, dtype=float) * 1e6
    out, lo_bin, lo_us = [], 0, 0
    for e, b in zip(edges_us, edges_bins):
        n = int(cum[b] - cum[lo_bin]) + int(((over >= lo_us) & (over < e)).sum())
        out.append((f"{lo_us:g}-{e:g} us", n))
        lo_bin, lo_us = b, e
    out.append((f">= {lo_us:g} us", int(cum[-1] - cum[lo_bin]) + int((over >= lo_us).sum())))
    return out


def check_options(duration_s: float, fifo: Optional[int], cpu: Optional[int]) -> None:
    """Bad input is one line, exit 2: a duration > 0, a SCHED_FIFO priority in the OS's
    range, a CPU this machine has."""
    from .preflight import check_duration
    check_duration(duration_s)
    if fifo is not None:
        lo, hi = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
        if not lo <= fifo <= hi:
            raise ConfigError(None, "--fifo", f"a SCHED_FIFO priority {lo}..{hi}", fifo)
    if cpu is not None:
        n = os.cpu_count() or 1
        if not 0 <= cpu < n:
            raise ConfigError(None, "--cpu", f"a CPU of this machine (0..{n - 1})", cpu)


def headroom_lines(h: float, loop: LoopFigures, work_us: float, work_source: str) -> list[str]:
    """What the lateness leaves of the period for the cycle's work."""
    h_us = h * 1e6
    out = [f"the {h_us / 1e3:g} ms cycle: work {work_us:.0f} us ({work_source})"]
    for name, lat in (("p99.9", loop.p999_us), ("max", loop.max_us)):
        left = h_us - lat - work_us
        out.append(f"  at lateness {name} {lat:.1f} us: {left:.0f} us left of {h_us:.0f} us "
                   f"({100 * left / h_us:.1f} %)" + ("  -> a deadline miss" if left < 0 else ""))
    return out


@command("latency", "the bare real-time loop at the configured period on this machine: wake-up latency "
                    "histogram, percentiles, deadline misses, headroom of the cycle; cyclictest beside it if installed")
@arg("--config", help="config file for the period and realtime: settings (default: configs/rig.yaml)")
@arg("--duration", type=float, default=10.0, help="seconds to measure (default 10)")
@arg("--fifo", type=int, metavar="P", help="SCHED_FIFO priority (default: realtime.sched_fifo_priority)")
@arg("--cpu", type=int, metavar="N", help="pin to CPU N (default: realtime.cpu_affinity)")
@arg("--work-us", type=float, help=f"the cycle's work to set against the period (default {WORK_REFERENCE_US:g} us: "
     "the runtime's measured figure, docs/performance.md)")
@arg("--no-cyclictest", action="store_true", help="do not run cyclictest beside")
def cmd_latency(args: argparse.Namespace) -> int:
    from .. import config
    from ..clock import RealtimeClock, apply_realtime
    from . import cyclictest
    from .bare_loop import bare_loop
    check_options(args.duration, args.fifo, args.cpu)
    if args.work_us is not None and not (math.isfinite(args.work_us) and args.work_us >= 0):
        raise ConfigError(None, "--work-us", "a finite number of microseconds >= 0", args.work_us)
    cfg = config.load(args.config or config.CONFIG_DIR / "rig.yaml")
    rt = cfg.realtime
    if args.fifo is not None:
        rt = replace(rt, sched_fifo_priority=args.fifo)
    if args.cpu is not None:
        rt = replace(rt, cpu_affinity=(args.cpu,))
    h = cfg.controller.h
    prio = rt.sched_fifo_priority
    cpu = rt.cpu_affinity[0] if rt.cpu_affinity else None

    exe = None if args.no_cyclictest else cyclictest.find()
    peer = peer_cmd = None
    if exe:
        peer_cmd = cyclictest.command(exe, duration_s=args.duration, period_s=h, priority=prio, cpu=cpu,
                                      hist_max_us=int(round(h * 1e6)))
        peer = cyclictest.start(peer_cmd)       # started first: it does not inherit this process's settings
    report = apply_realtime(rt)
    print(f"rig latency: bare loop (RealtimeClock: sleep, then spin {rt.spin_us:g} us to absolute deadlines) "
          f"at h = {h * 1e3:g} ms for {args.duration:g} s; config {cfg.source}")
    for line in report:
        print(f"realtime: {line}")
    # half a period off cyclictest's wake-ups (it wakes on the grid of h: --secaligned)
    stats = bare_loop(RealtimeClock(rt.spin_us * 1e-6), h, args.duration, phase_s=h / 2 if peer else None)
    lat = stats.lateness
    p50, p99, p999 = lat.percentiles((50.0, 99.0, 99.9))
    loop = LoopFigures(n=lat.n, p50_us=p50 * 1e6, p99_us=p99 * 1e6, p999_us=p999 * 1e6, max_us=lat.max * 1e6,
                       deadline_misses=stats.deadline_misses, skipped_periods=stats.skipped_periods)
    peer_result = peer_error = None
    if peer is not None:
        try:
            out, err = peer.communicate(timeout=args.duration + 30)
        except subprocess.TimeoutExpired as e:      # a hung peer must not hide our own figures
            peer.kill()
            out, err = peer.communicate()
            peer_error = f"did not finish ({type(e).__name__})"
        if peer_error is None:
            if peer.returncode != 0:
                last = (err or out).strip().splitlines()
                peer_error = f"exit {peer.returncode}" + (f": {last[-1]}" if last else "")
            else:
                try:
                    peer_result = cyclictest.parse(out)
                except ValueError as e:
                    peer_error = str(e)

    print("wake-up lateness histogram (bare loop):")
    for label, n in buckets(lat):
        if n:
            print(f"  {label:>14s}  {n:8d}")
    print(f"{'':22s} {'rig latency':>14s} {'cyclictest':>14s}")

    def row(name: str, ours: str, theirs: str) -> None:
        print(f"  {name:20s} {ours:>14s} {theirs:>14s}")
    pr = peer_result
    row("samples", str(loop.n), str(pr.n) if pr else "-")
    for name, a, b in (("p50 [us]", loop.p50_us, pr and pr.p50_us), ("p99 [us]", loop.p99_us, pr and pr.p99_us),
                       ("p99.9 [us]", loop.p999_us, pr and pr.p999_us), ("max [us]", loop.max_us, pr and pr.max_us)):
        row(name, f"{a:.1f}", f"{b:.1f}" if pr else "-")
    row("deadline misses", str(loop.deadline_misses), "-")
    if pr:
        row(f"over {int(round(h * 1e6))} us", "-", str(pr.overflows))
    if peer_cmd is None:
        print("cyclictest: " + ("not run (--no-cyclictest)" if args.no_cyclictest else
                                "not installed (Debian/Ubuntu: apt install rt-tests) — only rig latency's figures"))
    else:
        print(f"cyclictest: {' '.join(['cyclictest'] + peer_cmd[1:])}"
              + (f" — failed: {peer_error}" if peer_error else " (clock_nanosleep alone, no spin)"))
    work = args.work_us if args.work_us is not None else WORK_REFERENCE_US
    source = "--work-us" if args.work_us is not None else WORK_REFERENCE_SOURCE
    for line in headroom_lines(h, loop, work, source):
        print(line)
    sys.stdout.flush()
    return 0
