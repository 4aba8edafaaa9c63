import os
import pathlib
import shutil
import tempfile

import pytest
from hypothesis import settings

from rig_runtime import config

# No per-example time limit: on a loaded 2-core VM one example may stall for hundreds of
# milliseconds, which hypothesis's default 200 ms deadline would report as a failure.
settings.register_profile("rig", deadline=None)
settings.load_profile("rig")

ROOT = pathlib.Path(__file__).resolve().parent.parent


def pytest_configure(config):
    """The session's own disk cache (rig_runtime/memo.py ``across_processes``), shared by the
    test process and the ``rig`` processes it starts: no test reads or writes the user's."""
    config._rig_cache_dir = tempfile.mkdtemp(prefix="rig-test-cache-")
    os.environ["RIG_CACHE_DIR"] = config._rig_cache_dir


def pytest_unconfigure(config):
    shutil.rmtree(getattr(config, "_rig_cache_dir", ""), ignore_errors=True)


@pytest.fixture(scope="session")
def cfg():
    """The shipped simulated-rig configuration."""
    return config.load()


@pytest.fixture(scope="session")
def shared_run(tmp_path_factory):
    """``shared_run(scenario, seed=None, duration_s=None, on_lateral_loss=None, on_drive_loss=None)``: tests/e2e.py
    ``run`` of a shipped scenario on the shipped configuration (``lateral_loss_config``), done once per session for each (scenario, seed,
    duration) and shared by the tests that only read it (test_faults_e2e.py's checks of each
    fault scenario; test_lifecycle_e2e.py compares a second run of the same scenario with it).
    A test that needs a prepare hook, another configuration or a fresh run calls ``run``."""
    from .e2e import run
    done: dict = {}

    def get(scenario: str, seed=None, duration_s=None, on_lateral_loss=None, on_drive_loss=None):
        key = (scenario, seed, duration_s, on_lateral_loss, on_drive_loss)
        if key not in done:
            done[key] = run(tmp_path_factory.mktemp(scenario), scenario, seed=seed, duration_s=duration_s,
                            cfg=lateral_loss_config(on_lateral_loss, on_drive_loss))
        return done[key]
    return get


def lateral_loss_config(on_lateral_loss=None, on_drive_loss=None):
    """The shipped configuration, with ``degraded.on_lateral_loss`` and ``on_drive_loss`` set
    (None: as shipped; "stop": a lost lateral laser or drive is the rule's fault, as without an
    observer or reconfiguration)."""
    import dataclasses
    cfg = config.load()
    changes = {k: v for k, v in (("on_lateral_loss", on_lateral_loss), ("on_drive_loss", on_drive_loss))
               if v is not None}
    if not changes:
        return cfg
    return dataclasses.replace(cfg, degraded=dataclasses.replace(cfg.degraded, **changes))
