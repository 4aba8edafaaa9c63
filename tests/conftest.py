import pathlib

import pytest
from hypothesis import settings

from rig_runtime import config

# No per-example time limit: on a loaded 2-core VM one example may stall for hundreds of
# milliseconds, which hypothesis's default 200 ms deadline would report as a failure.
settings.register_profile("rig", deadline=None)
settings.load_profile("rig")

ROOT = pathlib.Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def cfg():
    """The shipped simulated-rig configuration."""
    return config.load()
