"""deploy.bridge_timing: the partial-sort percentile behind the command delay bound."""

from __future__ import annotations

from collections import deque

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from deploy.bridge_timing import percentile


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
