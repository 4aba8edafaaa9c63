"""A campaign run reads its log once: the metrics from the log ``run_lockstep_read`` read
equal the metrics read from the file, and so do the step metrics."""

import math

from rig_runtime import config
from rig_runtime.app.campaign.outcome import metrics
from rig_runtime.app.dryrun import run_lockstep_read
from rig_runtime.app.metrics import steps_from_log
from rig_runtime.scenario import load_scenario


def _same(a, b):
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


def test_metrics_from_the_read_log_equal_metrics_from_the_file(tmp_path):
    cfg = config.load(config.CONFIG_DIR / "sim.yaml")
    sc = load_scenario("single-step")
    log = tmp_path / "run.h5"
    summary, code, read = run_lockstep_read(cfg, sc, log, seed=3, duration_s=2.5)
    assert code == 0 and read is not None
    assert read["rows"] > 0
    assert summary["steps"] == steps_from_log(log, sc, cfg.controller.h)
    from_file, from_read = metrics(summary, log, 0.2), metrics(summary, read, 0.2)
    assert from_file.keys() == from_read.keys()
    assert all(_same(from_file[k], from_read[k]) for k in from_file), (from_file, from_read)
    assert summary["steps"] and from_read["max_abs_y_mm"] is not None
