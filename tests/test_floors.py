"""The real-time loop's process carries only what the loop needs: the loop module imports
nothing that loads scipy, h5py or matplotlib, and a running ``rig dry-run --realtime`` has
neither h5py nor matplotlib mapped — the recording sidecar writes the log, plots are drawn
after the run. (The static side, module by module, is in tests/test_layers.py.)
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from rig_runtime.app.ctl_server import CtlError, request

from .conftest import ROOT

HEAVY = ("scipy", "h5py", "matplotlib")


def _loaded_after_import(module: str) -> list[str]:
    """Which of HEAVY a fresh interpreter has in ``sys.modules`` after ``import module``."""
    code = f"import sys, {module}; print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return [m for m in r.stdout.strip().split(",") if m]


def test_the_loop_module_loads_no_scipy_h5py_or_matplotlib():
    assert _loaded_after_import("rig_runtime.loop") == []


@pytest.mark.parametrize("module", ["rig_runtime.recorder", "rig_runtime.app.runner", "rig_runtime.app.cli"])
def test_what_the_runs_process_imports_loads_no_h5py_or_matplotlib(module):
    """The recorder's loop side, the run itself and every command module ``rig`` loads at
    start-up (scipy may come with the pre-run stability gate: docs/performance.md)."""
    assert set(_loaded_after_import(module)) <= {"scipy"}


def test_the_probe_sees_a_heavy_import():
    """The probe itself can fail: importing the log writer loads h5py."""
    assert "h5py" in _loaded_after_import("rig_runtime.logfile")


# ------------------------------------------------------------------------------ end to end
def _mapped(pid: int, libs: tuple[str, ...]) -> set[str]:
    """Which of ``libs`` have a file mapped in process ``pid`` (a package directory, or its
    bundled ``<name>.libs`` directory of shared objects, in the mapped path)."""
    with open(f"/proc/{pid}/maps") as f:
        paths = {line.split(None, 5)[5].strip() for line in f if len(line.split(None, 5)) == 6}
    return {lib for lib in libs for p in paths if f"/{lib}/" in p or f"/{lib}.libs/" in p}


def _children(pid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    if int(f.read().rsplit(") ", 1)[1].split()[1]) == pid:
                        out.append(int(d))
            except (OSError, IndexError, ValueError):
                continue
    return out


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _tolerant_config(tmp: Path) -> Path:
    """configs/sim.yaml with a wider overrun burst: 40 periods (200 ms, the hardware ceiling
    raised to match — a simulated rig has no mechanics to protect). A stall of this shared
    2-CPU VM must not end the run before its process is looked at; this test checks what the
    process has loaded, not its timing."""
    src = ROOT / "configs"
    main = yaml.safe_load((src / "sim.yaml").read_text())
    for name in main["include"]:
        part = yaml.safe_load((src / name).read_text())
        if "limits" in part:
            part["limits"]["overrun_burst"] = 40
        if "ceilings" in part.get("hardware", {}):
            part["hardware"]["ceilings"]["overrun_s"] = 0.2
        (tmp / name).write_text(yaml.safe_dump(part, sort_keys=False))
    (tmp / "sim.yaml").write_text(yaml.safe_dump(main, sort_keys=False))
    return tmp / "sim.yaml"


@pytest.mark.slow
def test_a_running_realtime_loop_has_no_h5py_or_matplotlib_mapped(tmp_path):
    """A real ``rig dry-run --realtime`` (it starts ``rig sim`` and the recording sidecar):
    once the loop has reported RUNNING over its ``rig ctl`` socket (the status's ``t_run``),
    the loop's process (the ``rig`` process itself), still cycling, maps no h5py and no
    matplotlib, while the sidecar, its child, maps h5py (it writes the log). ``--report`` is
    asked for: the plots' matplotlib is checked before the run and drawn after it, never
    loaded while the loop runs.

    Tolerances, for what this test does not check (timing, faults): the wider overrun burst
    of :func:`_tolerant_config`, and ``--hold-on-fault`` — a fault after RUNNING began keeps
    the loop cycling in its process until the maps are read (the maps are then read in FAULT,
    after RUNNING; a status is polled every 0.1 s and a fault can come sooner); a generous
    deadline of 120 s to reach RUNNING on a loaded machine. A run that ends or faults before
    RUNNING fails the test."""
    cfg = _tolerant_config(tmp_path)
    sock, log = tmp_path / "ctl.sock", tmp_path / "run.h5"
    p = subprocess.Popen([sys.executable, "-m", "rig_runtime", "dry-run", "--realtime", "--config", str(cfg),
                          "--duration", "60", "--log", str(log), "--ctl-socket", str(sock), "--json",
                          "--hold-on-fault", "--report", str(tmp_path / "report")],
                         cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        st: dict = {}
        deadline = time.monotonic() + 120
        while st.get("t_run") is None:      # set once the loop is RUNNING (and kept after a held fault)
            assert p.poll() is None, f"the run ended before RUNNING (exit {p.returncode}): {p.communicate()}"
            assert not st.get("faults"), f"the run faulted before RUNNING: {st['faults']}"
            assert time.monotonic() < deadline, f"RUNNING not reached in 120 s (last state {st.get('state')})"
            time.sleep(0.1)
            try:
                st = request(sock, {"cmd": "status"}, timeout_s=5.0).get("status") or {}
            except (CtlError, OSError):
                continue            # the socket is not there yet
        in_loop = _mapped(p.pid, ("h5py", "matplotlib"))
        sidecars = [c for c in _children(p.pid) if "rig_runtime.sidecar" in _cmdline(c)]
        in_sidecar = _mapped(sidecars[0], ("h5py",)) if sidecars else set()
        assert p.poll() is None         # the maps above are of the running loop's process
    finally:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)        # a clean stop (the process group: start_new_session)
        try:
            out, err = p.communicate(timeout=90)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            out, err = p.communicate(timeout=30)
    assert in_loop == set(), f"mapped in the loop's process while RUNNING: {sorted(in_loop)}"
    assert len(sidecars) == 1 and in_sidecar == {"h5py"}, (sidecars, in_sidecar)
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["log"] == str(log) and summary["report"], err[-800:]
