"""What recording costs a run: per row (``Recorder.append``) and per run (opening and closing
the log), with the recording sidecar process and with the inline writer lockstep runs use
(issue 26: no interpreter started per run).

- ``append_us``: ``Recorder.append`` of a 24-column row (the ring in shared memory; best of
  20 × 5000 calls — the loop's share of recording in real time);
- ``sidecar_open_s`` / ``sidecar_close_s``: a ``Recorder`` with its sidecar process — an
  interpreter started, imports, the log created; and the close (drain, flush, attributes,
  the process's exit) — median of ``--runs``;
- ``inline_open_s`` / ``inline_close_s``: the same with ``writer="inline"`` (the same ring
  and :class:`~rig_runtime.sidecar.Sidecar`, in this process);
- ``*_run_s``: a 10 s lockstep run's worth of rows (2000 × 60 columns, two events) from open
  to closed, each way;
- ``ipc_round_trip_ms``: one request/answer over a socket pair with a warm child process —
  what a recording sidecar kept per worker (the other option of issue 26) would add to the
  inline cost twice per run (open, close), on top of the same file work;
- ``warm_dry_run_s``: with ``--dry-runs N``, a 0.1 s lockstep dry run (``run_lockstep``,
  configs/sim.yaml, single-step) in a warm process, median of N after a first one.

    python benchmarks/recorder_cost.py [--runs N] [--dry-runs N] [--json]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import tempfile
import time
import timeit
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime.recorder import Recorder  # noqa: E402


def _echo(conn) -> None:
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            return
        conn.send(msg)


def append_us(d: Path) -> float:
    rec = Recorder(d / "append.h5", [f"c{i}" for i in range(24)], attrs={}, buffer_cycles=1 << 18)
    rec.open()
    r = tuple(float(i) for i in range(24))
    n = 5_000
    per_call = min(timeit.repeat(lambda: rec.append(r), number=n, repeat=20)) / n
    rec.close()
    return per_call * 1e6


def open_close(d: Path, writer: str, runs: int, rows: int) -> tuple[float, float, float]:
    cols = ["t"] + [f"c{i}" for i in range(59)]
    opens, closes, totals = [], [], []
    for k in range(runs):
        t0 = time.perf_counter()
        rec = Recorder(d / f"{writer}-{rows}-{k}.h5", cols, attrs={"a": "b"}, when_full="wait", writer=writer)
        rec.open()
        t1 = time.perf_counter()
        for i in range(rows):
            rec.append([i * 0.005] + [float(i)] * 59)
            if i in (10, rows - 10):
                rec.event(i * 0.005, "state", message="x")
        t2 = time.perf_counter()
        rec.close()
        t3 = time.perf_counter()
        opens.append(t1 - t0)
        closes.append(t3 - t2)
        totals.append(t3 - t0)
    return statistics.median(opens), statistics.median(closes), statistics.median(totals)


def ipc_round_trip_ms(n: int = 200) -> float:
    ctx = multiprocessing.get_context("spawn")
    a, b = ctx.Pipe()
    p = ctx.Process(target=_echo, args=(b,), daemon=True)
    p.start()
    a.send("warm")
    a.recv()
    t0 = time.perf_counter()
    for _ in range(n):
        a.send(("close", {}))
        a.recv()
    dt = (time.perf_counter() - t0) / n
    a.close()
    p.join(5)
    return dt * 1e3


def warm_dry_run_s(d: Path, n: int) -> float:
    from rig_runtime import config
    from rig_runtime.app.dryrun import run_lockstep
    from rig_runtime.scenario import load_scenario
    cfg, sc = config.load(), load_scenario("single-step")
    run_lockstep(cfg, sc, d / "warm.h5", duration_s=0.1)
    ts = []
    for k in range(n):
        t0 = time.perf_counter()
        run_lockstep(cfg, sc, d / f"dry-{k}.h5", duration_s=0.1)
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--dry-runs", type=int, default=0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as td:
        d = Path(td)
        out = {"append_us": append_us(d)}
        for writer in ("sidecar", "inline"):
            o, c, _ = open_close(d, writer, args.runs, 20)
            _, _, run = open_close(d, writer, args.runs, 2000)
            out.update({f"{writer}_open_s": o, f"{writer}_close_s": c, f"{writer}_run_s": run})
        out["ipc_round_trip_ms"] = ipc_round_trip_ms()
        if args.dry_runs:
            out["warm_dry_run_s"] = warm_dry_run_s(d, args.dry_runs)
    if args.json:
        print(json.dumps(out))
        return
    for k, v in out.items():
        print(f"{k:20s} {v:.4g}")


if __name__ == "__main__":
    main()
