"""The full-length acceptance run of Sec. 5.2.4: the whole ``step-sequence`` scenario (72
steps, 1441 s simulated) in lockstep, judged by the same check as the test suite's shorter
run (``tests/e2e.py`` ``assert_steps_tracked``); prints every step and the wall time, exits 1
if a step misses the criterion. The suite runs a part of the sequence
(tests/test_closed_loop.py ``test_step_sequence``); this run is the acceptance for a change
to the controller, the plant or the loop (docs/performance.md, "The test suite's time").

    python benchmarks/step_sequence.py [--seed N] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig_runtime import config  # noqa: E402
from tests.e2e import assert_steps_tracked, run  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    cfg = config.load()
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory() as d:
        r = run(Path(d), "step-sequence", seed=a.seed)
    wall = time.monotonic() - t0
    verdict = "pass"
    try:
        assert_steps_tracked(r, cfg, n_steps=72)
    except AssertionError as e:
        verdict = f"FAIL: {e}"
    steps = r.summary["steps"]
    if a.json:
        print(json.dumps({"verdict": verdict, "wall_s": round(wall, 1), "steps": steps}))
    else:
        for st in steps:
            size = abs(st["to_mm"] - st["from_mm"])
            err = st["steady_state_error_mm"]
            print(f"{st['from_mm']:+5.1f} -> {st['to_mm']:+5.1f} mm  rise {st['rise_time_s']:5.2f} s  "
                  f"settling {st['settling_time_s'] if st['settling_time_s'] is None else round(st['settling_time_s'], 2)}  "
                  f"error {err * 1e3:+7.2f} µm (limit {max(0.02 * size, 0.005) * 1e3:.1f} µm)")
        print(f"{len(steps)} steps, largest current {r.summary['max_abs_current_A']:.2f} A; {verdict}; "
              f"wall {wall:.1f} s")
    return 0 if verdict == "pass" else 1


if __name__ == "__main__":
    sys.exit(main())
