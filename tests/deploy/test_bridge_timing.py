"""deploy.bridge_timing: the partial-sort percentile behind the command delay bound, and the
lock-step clock."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from deploy.bridge_timing import TickClock, percentile


def test_percentile_by_hand():
    values = deque([4, 1, 3, 2])               # sorted 1 2 3 4, positions 0..3
    assert percentile(values, 50) == 2.5       # position 1.5: halfway between 2 and 3
    assert percentile(values, 100) == 4.0
    assert percentile(values, 0) == 1.0
    assert percentile(values, 99) == 3.0 + 0.97   # position 2.97
    assert percentile([7], 99) == 7.0


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 10**9), min_size=1, max_size=300), st.floats(0, 100))
def test_percentile_equals_numpys(values, q):
    assert np.isclose(percentile(deque(values), q), np.percentile(values, q), rtol=1e-12, atol=1e-6)


def test_the_tick_clock_tells_a_bursts_late_part_from_the_next_tick():
    """Hand-worked: r0 and r1 answered at 1 period; r1's state of that tick comes late (looked at
    after the advance) and reads 1 period again; then a state of r0 (answered at this tick) means
    the fleet stepped: 2 periods, and who was answered starts afresh. A look with nothing new
    changes nothing."""
    clock = TickClock(0.05)
    assert not clock.begin({"r0", "r1"}) and clock() == 50_000_000
    clock.answered.add("r0")                      # r1's state was not there: answered r0 only
    clock.advance()
    assert clock.begin({"r1"}) and clock() == 50_000_000      # the late part, at its burst's time
    clock.answered.add("r1")
    clock.advance()
    assert not clock.begin(set()) and clock() == 100_000_000 and clock.answered == {"r0", "r1"}
    assert not clock.begin({"r1", "r0"}) and clock() == 100_000_000 and clock.answered == set()


def test_the_uplink_floors_are_bounded_and_the_least_recently_heard_goes_first():
    """MAX_SENDERS floors: a sender heard again stays; the one heard longest ago is forgotten, so
    its next message starts a floor anew (excess 0) where a kept one measures its 5 ms."""
    from deploy.bridge_timing import UplinkExcess

    uplink = UplinkExcess()
    cap = UplinkExcess.MAX_SENDERS
    for k in range(cap):
        uplink.excess_ns(f"s{k}", 1, 0, 1_000_000)
    uplink.excess_ns("s0", 1, 0, 1_000_000)                  # heard again: now the most recent
    uplink.excess_ns("new", 1, 0, 1_000_000)                  # one too many: s1 goes
    assert uplink.excess_ns("s0", 1, 0, 6_000_000) == pytest.approx(5_000_000, rel=1e-3)
    assert uplink.excess_ns("s1", 1, 0, 6_000_000) == 0.0
