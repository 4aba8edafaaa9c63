"""`rig latency`: cyclictest's output parsed from a hand-written sample, the histogram
buckets and the headroom arithmetic on given numbers, bad input refused with one line, and
one short end-to-end run checked for its structure (the figures are printed, not asserted:
they are this machine's)."""

import subprocess
import sys

import pytest

from rig_runtime.app import cyclictest
from rig_runtime.app.latency import LoopFigures, buckets, headroom_lines
from rig_runtime.stats import Histogram

RIG = [sys.executable, "-m", "rig_runtime"]


def rig(*args, timeout=120):
    return subprocess.run(RIG + list(args), capture_output=True, text=True, timeout=timeout)


CYCLICTEST_OUT = """\
# /dev/cpu_dma_latency set to 0us
000000 000000
000001 000000
000002 000500
000003 000400
000004 000090
000010 000009
000250 000000
# Total: 000000999
# Min Latencies: 00002
# Avg Latencies: 00003
# Max Latencies: 06200
# Histogram Overflows: 00001
# Histogram Overflow at cycle number:
# Thread 0: 00417
"""


def test_cyclictest_parse():
    r = cyclictest.parse(CYCLICTEST_OUT)
    assert r.n == 1000 and r.overflows == 1
    assert (r.p50_us, r.p99_us, r.p999_us) == (2.0, 4.0, 10.0)
    assert r.max_us == 6200.0 and r.avg_us == 3.0
    assert r.histogram == ((2, 500), (3, 400), (4, 90), (10, 9))
    # the overflowing rank is the maximum
    assert cyclictest.parse(CYCLICTEST_OUT.replace("000010 000009", "000010 000008")
                            .replace("Overflows: 00001", "Overflows: 00002")).p999_us == 6200.0
    with pytest.raises(ValueError):
        cyclictest.parse("cyclictest: unrecognized option\n")


def test_cyclictest_command():
    cmd = cyclictest.command("/usr/bin/cyclictest", duration_s=10, period_s=0.005, priority=80, cpu=1,
                             hist_max_us=5000)
    assert cmd[0] == "/usr/bin/cyclictest"
    s = " ".join(cmd)
    for part in ("-q", "-m", "-t 1", "-l 2000", "-i 5000", "-h 5000", "-p 80", "--policy=fifo", "-a 1", "--secaligned"):
        assert part in s
    bare = " ".join(cyclictest.command("c", duration_s=0.3, period_s=0.001, priority=None, cpu=None, hist_max_us=1000))
    assert "-l 300" in bare and "-i 1000" in bare and "-p" not in bare and "-a" not in bare


def test_bare_loop_deadlines_at_the_phase():
    """Half a period off the grid cyclictest wakes on (simulated time: no timing here)."""
    from rig_runtime.app.bare_loop import bare_loop
    from rig_runtime.clock import LockstepClock
    deadlines = []
    stats = bare_loop(LockstepClock(advance=deadlines.append, t0=1234.5671), 0.005, 0.1, phase_s=0.0025)
    assert stats.cycles == 20 and stats.deadline_misses == 0 and len(deadlines) == 20
    for t in deadlines:
        assert abs((t - 0.0025) / 0.005 - round((t - 0.0025) / 0.005)) < 1e-6
    assert deadlines[0] > 1234.5671
    free = []
    bare_loop(LockstepClock(advance=free.append, t0=1234.5671), 0.005, 0.1)
    assert abs(free[0] - (1234.5671 + 0.005)) < 1e-9         # without a phase: one period from now


def test_buckets_count_every_sample():
    h = Histogram()
    for us in (0.0, 0.5, 1.5, 30.0, 30.0, 700.0, 12_000.0):    # 12 ms: beyond the histogram, kept exactly
        h.add(us * 1e-6)
    b = dict(buckets(h))
    assert b["0-1 us"] == 2 and b["1-2 us"] == 1 and b["20-50 us"] == 2 and b["500-1000 us"] == 1
    assert b[">= 5000 us"] == 1
    assert sum(b.values()) == h.n


def test_headroom():
    loop = LoopFigures(n=100, p50_us=1.0, p99_us=10.0, p999_us=100.0, max_us=4500.0, deadline_misses=0,
                       skipped_periods=0)
    lines = headroom_lines(0.005, loop, 750.0, "given")
    assert "work 750 us (given)" in lines[0]
    assert "4150 us left of 5000 us (83.0 %)" in lines[1]
    assert "-250 us left" in lines[2] and "deadline miss" in lines[2]


@pytest.mark.parametrize("args, names", [
    (["--duration", "-1"], "--duration"),
    (["--duration", "nan"], "--duration"),
    (["--fifo", "100"], "--fifo"),
    (["--fifo", "0"], "--fifo"),
    (["--cpu", "4096"], "--cpu"),
    (["--cpu", "-1"], "--cpu"),
])
def test_bad_input_is_one_line_exit_2(args, names):
    r = rig("latency", *args)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and names in lines[0] and "Traceback" not in r.stderr
    assert r.stdout == ""


def test_one_second_run_prints_the_figures():
    r = rig("latency", "--duration", "1")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "h = 5 ms for 1 s" in out
    assert "wake-up lateness histogram (bare loop):" in out
    for row in ("samples", "p50 [us]", "p99 [us]", "p99.9 [us]", "max [us]", "deadline misses"):
        assert f"  {row}" in out
    samples = next(l for l in out.splitlines() if l.strip().startswith("samples")).split()
    assert int(samples[1]) > 0
    assert "the 5 ms cycle: work" in out and "left of 5000 us" in out
    assert "cyclictest: " in out         # either its command line and figures, or why it did not run
    if cyclictest.find() is None:
        assert "not installed" in out
