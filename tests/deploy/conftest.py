"""Fixtures shared by the deploy tests."""

from __future__ import annotations

import pytest

from deploy.bridge import BridgeConfig

pytest.register_assert_rewrite("tests.deploy.bridge_fleet")   # its asserts report as a test's do


@pytest.fixture
def fleet():
    """A bridge and two linked robots (:func:`tests.deploy.bridge_fleet.linked_fleet`):
    ``(bridge, links, seen)``."""
    from tests.deploy.bridge_fleet import linked_fleet

    with linked_fleet(BridgeConfig(ttl_ms=100, stale_after_s=0.2, estop_after_s=0.6)) as parts:
        yield parts
