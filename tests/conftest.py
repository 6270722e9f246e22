"""Shared fixtures and checks for the whole suite."""

from importlib.metadata import version

import pytest
import torch
from packaging.version import Version


@pytest.fixture(autouse=True)
def single_torch_thread():
    """Small networks run fastest on one thread; on a busy machine two threads can be 20x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def pytest_configure(config):
    """``make test`` runs ``--dist loadgroup``: pytest-xdist sends the tests of one ``xdist_group``
    to one worker (the demo's share one quick demo run). pytest 9.2 with pytest-xdist <= 3.8
    drops the groups without a word (pytest-xdist issue 1386): refuse that pair."""
    if config.getoption("dist", "no") != "loadgroup":
        return
    if Version(version("pytest")) >= Version("9.2") and Version(version("pytest-xdist")) < Version("3.9"):
        raise pytest.UsageError(f"--dist loadgroup: pytest {version('pytest')} with pytest-xdist "
                                f"{version('pytest-xdist')} ignores xdist_group marks (pytest-xdist "
                                "issue 1386); install the versions constraints.txt allows: make venv")
