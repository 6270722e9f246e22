"""The compiled docking tick equals its numpy formulation (scipy's assignment) bit for bit."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.docking import Docking
from tests.controllers.docking_reference import NumpyDocking

R, ACCEL = 0.04, 1.0


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 7), crowded=st.booleans(), ties=st.booleans())
def test_compiled_docking_equals_numpy_formulation(seed, n, crowded, ties):
    """Sequences of ticks: robots settle onto targets (0-10 cm off, slow and fast), two robots
    near one target (taken), targets equidistant from a robot (the assignment solver decides),
    stale robots that may not dock; the docking set carries over from tick to tick."""
    rng = np.random.default_rng(seed)
    compiled, reference = Docking(R, ACCEL), NumpyDocking(R, ACCEL)
    ids = tuple(f"r{k}" for k in range(n))
    targets = rng.uniform(0.1, 0.9, (n, 2))
    if ties and n > 1:
        targets[1] = targets[0] + (0.1, 0.0)
    pos = targets[rng.permutation(n)] + rng.normal(0.0, 0.05, (n, 2))
    for _ in range(25):
        if crowded and n > 1:
            pos[1] = pos[0] + rng.normal(0.0, 0.03, 2)
        if ties and n > 1:
            pos[0] = targets[0] + (0.05, 0.0)                        # halfway: both at 5 cm
        vel = rng.normal(0.0, 0.15, (n, 2))
        a_nom = rng.uniform(-1, 1, (n, 2))
        movable = rng.random(n) < 0.9
        got = compiled(ids, pos, vel, targets, a_nom, movable)
        want = reference(ids, pos, vel, targets, a_nom, movable)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
        assert compiled._docking == reference._docking
        pos = pos + 0.3 * (targets[rng.permutation(n)] - pos) * (rng.random() < 0.2) + rng.normal(0, 0.01, (n, 2))


def test_the_reference_is_not_the_compiled_code():
    assert NumpyDocking._dock is not Docking._dock
