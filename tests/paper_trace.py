"""The paper's set-up's stored trace: ``single-step`` with configs/sim.yaml, seed 0, as the code
of commit 318336a (before the vehicle) ran it, so that tests/test_vehicle_e2e.py can check the
set-up is unchanged bit for bit and, when it is not, say which quantity changed, where and by
how much (:func:`differences`).

``python -m tests.paper_trace`` writes tests/data/paper_trace.json from a run of the current
code only if that run's full trace (every cycle of ``COLUMNS``) has the SHA-256 recorded at
318336a: the stored file is that commit's record, never a newer code's.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

PATH = Path(__file__).resolve().parent / "data" / "paper_trace.json"
COLUMNS = ("t_run", "y_r", "psi_ar", "rear_x_I", "rear_psi_ref", "rear_u_cmd", "rear_u_lim", "i_rl", "y_ref")
EVERY = 10                      # every EVERY-th cycle is stored (and the last one)
CYCLES = 3021
#: the SHA-256 of the full trace (COLUMNS, every cycle, little-endian float64) at 318336a
SHA256_AT_318336A = "1d87c4eeb73cff9338dc0b3fac6062a9a4e45bebb1acfb3b44cb2a01cd93408f"


def rows(n: int) -> list[int]:
    """The stored rows of an n-cycle trace."""
    return sorted(set(range(0, n, EVERY)) | {n - 1})


def sha256(columns) -> str:
    h = hashlib.sha256()
    for k in COLUMNS:
        h.update(np.ascontiguousarray(columns[k], dtype="<f8").tobytes())
    return h.hexdigest()


def load() -> dict[str, np.ndarray]:
    d = json.loads(PATH.read_text())
    return {k: np.array(v, dtype=float) for k, v in d["columns"].items()}


def differences(columns) -> list[str]:
    """Where ``columns`` (a run's log, every cycle) differ from the stored trace: one line per
    quantity that changed (first stored cycle where it differs, the values there, the largest
    |difference|); empty if every stored value is bit-identical."""
    stored = load()
    n = len(columns["t_run"])
    if n != CYCLES:
        return [f"{n} cycles, stored {CYCLES}"]
    idx = rows(n)
    out = []
    for k in COLUMNS:
        got, want = np.asarray(columns[k], dtype=float)[idx], stored[k]
        same = (got == want) | (np.isnan(got) & np.isnan(want))
        if not same.all():
            i = int(np.argmin(same))
            d = np.abs(got - want)
            out.append(f"{k}: first at cycle {idx[i]} (t_run {stored['t_run'][i]:.3f} s): {got[i]!r}, "
                       f"stored {want[i]!r}; largest |difference| {np.nanmax(d):.3g} "
                       f"in {int((~same).sum())} of {len(idx)} stored cycles")
    return out


def main() -> int:
    from rig_runtime import config
    from rig_runtime.app.dryrun import run_lockstep
    from rig_runtime.app.export import read_log
    from rig_runtime.scenario import load_scenario

    with tempfile.TemporaryDirectory() as d:
        s, code = run_lockstep(config.load(), load_scenario("single-step"), Path(d) / "paper.h5", seed=0)
        c = read_log(Path(d) / "paper.h5")["columns"]
    if sha256(c) != SHA256_AT_318336A:
        print("this code's trace is not 318336a's: not written", file=sys.stderr)
        return 1
    idx = rows(len(c["t_run"]))
    data = {k: [float(x) for x in np.asarray(c[k], dtype=float)[idx]] for k in COLUMNS}
    assert all(math.isfinite(x) for v in data.values() for x in v)
    PATH.write_text(json.dumps({"scenario": "single-step", "config": "sim.yaml", "seed": 0, "commit": "318336a",
                                "every": EVERY, "cycles": len(c["t_run"]), "columns": data}) + "\n")
    print(f"wrote {PATH} ({len(idx)} of {len(c['t_run'])} cycles)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
