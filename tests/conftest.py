import pathlib

import pytest

from rig_runtime import config

ROOT = pathlib.Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def cfg():
    """The shipped simulated-rig configuration."""
    return config.load()
