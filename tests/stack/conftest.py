"""Fixtures shared by the stack tests."""

from __future__ import annotations

import pytest

from stack.cli import main


@pytest.fixture(scope="session")
def quick_run(tmp_path_factory):
    """The folder of one finished `formation demo --quick` (train, transfer, export, fleet,
    report). Tests read it, or copy it before they change anything."""
    out = tmp_path_factory.mktemp("demo") / "run"
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    return out
