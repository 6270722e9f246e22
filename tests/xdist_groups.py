"""The suite's pytest-xdist groups: ``make test`` runs ``--dist loadgroup``, which keeps the tests
of one group on one worker and hands the groups out before the single tests, largest first.
One name per group here, so a misspelt name cannot split a group without a word."""

import pytest

DEMO = pytest.mark.xdist_group("demo")                    # the tests that share one quick demo run
RAY = pytest.mark.xdist_group("ray")                      # one local Ray at a time on the machine
EXPORT = pytest.mark.xdist_group("export")                # test_export.py's module fixture, built once
ROBOT_RUNTIME = pytest.mark.xdist_group("robot_runtime")  # the robot's venv, built once
