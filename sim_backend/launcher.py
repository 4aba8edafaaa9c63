"""Start ``rig sim`` as a subprocess and wait until it serves: the Python API that tests,
benchmarks and ``rig dry-run --realtime`` use (docs/sim-process.md, "Python API")."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from . import child_process
from .port_lines import parse_port_line

__all__ = ["SimProcess", "start_sim_process"]


@dataclass
class SimProcess:
    """A running ``rig sim`` subprocess (from :func:`start_sim_process`)."""

    proc: subprocess.Popen
    workdir: Path
    config_path: Path
    status_path: Path
    stderr_path: Path
    ports: dict[str, Any] = field(default_factory=dict)
    lines: list[str] = field(default_factory=list)
    owns_workdir: bool = False      # a temporary directory of its own: removed on exit

    def status(self, timeout_s: float = 2.0) -> dict[str, Any]:
        """The latest status snapshot (rewritten every ``--status-period``, 50 ms)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return json.loads(self.status_path.read_text())
            except (OSError, ValueError):
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.01)

    def wait_status(self, pred: Callable[[dict], bool], timeout_s: float = 10.0, period_s: float = 0.02) -> dict:
        """Poll the status until ``pred(status)``; TimeoutError with the last snapshot otherwise."""
        deadline = time.monotonic() + timeout_s
        st: dict = {}
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"rig sim exited with {self.proc.returncode}: {self.stderr()[-2000:]}")
            st = self.status()
            if pred(st):
                return st
            time.sleep(period_s)
        raise TimeoutError(f"status condition not met within {timeout_s} s; last status: {st}")

    def stderr(self) -> str:
        try:
            return self.stderr_path.read_text(errors="replace")
        except OSError:
            return ""

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 10.0) -> int:
        """Signal the simulator and wait; kills it after ``timeout_s``. Returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        return self.proc.returncode

    def __enter__(self) -> "SimProcess":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        if self.owns_workdir:
            shutil.rmtree(self.workdir, ignore_errors=True)


def start_sim_process(config: str | Path | None = None, scenario: str | Path | None = None, seed: Optional[int] = 0,
                      extra_args: Sequence[str] = (), *, workdir: str | Path | None = None,
                      timeout_s: float = 60.0, python: str | None = None,
                      env: Optional[dict[str, str]] = None, die_with_parent: bool = True) -> SimProcess:
    """Spawn ``python -m rig_runtime sim --write-config … --status-file …`` and wait for ``ready``.

    The generated config, the status file and the simulator's stderr go to ``workdir``
    (a new temporary directory if None, removed when the context manager exits). Stop it
    with ``.stop()`` (or use it as a context manager). The simulator runs in a session of
    its own, so a Ctrl-C at the terminal reaches only the runtime, which stops it after its
    own clean stop. ``die_with_parent``: the simulator gets SIGTERM when the thread that started it
    ends (Linux ``PR_SET_PDEATHSIG``), so a crashed test or benchmark leaves no simulator
    behind (with SCHED_FIFO, one would keep a CPU busy)."""
    wd = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="rig-sim-"))
    wd.mkdir(parents=True, exist_ok=True)
    cfg_path, status_path, err_path = wd / "sim-process.yaml", wd / "sim-status.json", wd / "sim.stderr"
    out_path = wd / "sim.stdout"
    cmd = [python or sys.executable, "-m", "rig_runtime", "sim", "--write-config", str(cfg_path),
           "--status-file", str(status_path)]
    if config is not None:
        cmd += ["--config", str(config)]
    if scenario is not None:
        cmd += ["--scenario", str(scenario)]
    if seed is not None:
        cmd += ["--seed", str(seed)]
    cmd += list(extra_args)
    err = open(err_path, "wb")
    out = open(out_path, "wb")
    try:
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, stdin=subprocess.DEVNULL,
                                env=env, start_new_session=True,
                                preexec_fn=child_process.die_with_parent if die_with_parent else None)
    finally:
        err.close()
        out.close()
    sp = SimProcess(proc, wd, cfg_path, status_path, err_path, owns_workdir=workdir is None)
    # stdout goes to a file read here until "ready": no reader thread in the caller's process
    # (the runtime's process runs a single thread)
    deadline = time.monotonic() + timeout_s
    seen = 0
    while True:
        text = out_path.read_text(errors="replace")
        complete = text[:text.rfind("\n") + 1].splitlines()
        for line in complete[seen:]:
            sp.lines.append(line)
            if line == "ready":
                return sp
            parse_port_line(line, sp.ports)
        seen = len(complete)
        if proc.poll() is not None:
            err_text = sp.stderr()[-2000:]
            sp.__exit__()
            raise RuntimeError(f"rig sim exited with {proc.returncode} before ready: {err_text}")
        if time.monotonic() > deadline:
            sp.stop(signal.SIGKILL)
            err_text = sp.stderr()[-2000:]
            sp.__exit__()
            raise TimeoutError(f"rig sim not ready within {timeout_s} s: {err_text}") from None
        time.sleep(0.02)

