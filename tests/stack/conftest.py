"""Fixtures shared by the stack tests."""

from __future__ import annotations

import pytest

from stack.cli import main

QUICK_BUDGET = 16   # episodes of each training stage: one batch of 16 environments


@pytest.fixture(scope="session")
def quick_run(tmp_path_factory):
    """The folder of one finished `formation demo --quick` (train, transfer, export, fleet,
    report) with training budgets of :data:`QUICK_BUDGET` episodes (two evaluations each: the
    files and the rule are tested, not learning). Tests read it, or copy it before they change
    anything."""
    out = tmp_path_factory.mktemp("demo") / "run"
    budget = str(QUICK_BUDGET)
    assert main(["demo", "--quick", "--budget-3", budget, "--budget-5", budget, "--budget-generalist",
                 budget, "--out", str(out)]) == 0
    return out
